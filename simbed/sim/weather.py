"""Rain and fog as the realistic LiDAR meets them: extinction that shortens its range, and false returns
from the droplets near the sensor.

``--weather`` takes ``clear``, ``fog:V`` (meteorological visibility ``V`` in metres) or ``rain:R`` (rain
rate ``R`` in mm/h). Their models and sources:

* **Fog extinction** ``α = 3.912 / V`` per metre (Koschmieder's law, 2 % contrast threshold).
* **Fog backscatter**: the fog in the pulse's volume returns like a diffuse target of reflectivity
  ``π·β·L`` with ``β = FOG_BACKSCATTER_RATIO·α`` (sr⁻¹ m⁻¹) and ``L = c·τ/2`` the pulse length
  (Hahner et al. 2021, "Fog Simulation on Real LiDAR Point Clouds", their defaults: β = 0.046/MOR with
  MOR = ln 20/α, τ = 20 ns); the fog echo lies where its signal ``π·β·L·exp(-2αr)/r²`` is drawn from,
  between the transmitter's overlap distance and the pulse's hard target, so dense fog fills the first
  metres around the sensor with points, as real fog does.
* **Rain extinction** from the Marshall–Palmer drop sizes, ``N(D) = 8000·exp(-4.1·R^-0.21·D)`` (m⁻³
  mm⁻¹), with an extinction efficiency of 2: ``α = π·8000e-6 / Λ³`` per metre, ``Λ = 4.1·R^-0.21``
  (0.0016 /m at 10 mm/h; LISA, Kilic et al. 2021). Goodin et al. 2019's ``0.01·R^0.6`` is about 25×
  stronger; we keep the drop-size figure, which follows from the physics.
* **Rain droplets** in the beam near the sensor: a droplet echo on a share
  ``1 - exp(-RAIN_CLUTTER_PER_MM_H·R)`` of the pulses (about 1 % at 10 mm/h: an assumption, no measured
  figure found), at a range uniform between the sensor's minimum range and ``RAIN_CLUTTER_MAX_M``, as
  bright as a ``DROPLET_REFLECTIVITY`` target.

Weather dims what a calibrated sensor reports as reflectivity too (it corrects for range in clear air only),
and weaker signals are noisier (:mod:`simbed.sim.returns`): both follow from the extinction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError

KOSCHMIEDER = 3.912  # -ln(0.02): extinction x visibility
FOG_BACKSCATTER_RATIO = 0.046 / math.log(20.0)  # β / α (Hahner et al. 2021's default β = 0.046/MOR)
PULSE_LENGTH_M = 299_792_458.0 * 20e-9 / 2  # c·τ/2 with τ = 20 ns (Hahner et al. 2021's default)
OVERLAP_M = 1.0  # the transmitter and receiver fields of view overlap fully from here (Hahner: 0.9-1.0 m)
RAIN_CLUTTER_PER_MM_H = 0.001  # droplet echoes per pulse and mm/h (assumption: about 1 % at 10 mm/h)
RAIN_CLUTTER_MAX_M = 5.0  # droplet echoes lie within this range (assumption)
DROPLET_REFLECTIVITY = 0.05  # a droplet echo's equivalent reflectivity (assumption)
_GRID = 4096  # range samples of the fog echo's cumulative distribution (log-spaced)


@dataclass(frozen=True)
class Weather:
    """``clear``, ``fog`` (``visibility_m``) or ``rain`` (``rain_mm_h``)."""

    kind: str = "clear"
    visibility_m: float | None = None
    rain_mm_h: float | None = None

    @classmethod
    def parse(cls, text: str | None) -> Weather:
        """``clear``, ``fog:V`` (visibility, m) or ``rain:R`` (mm/h); one clear error line otherwise."""
        t = (text or "clear").strip().lower()
        if t == "clear":
            return cls()
        kind, _, value = t.partition(":")
        usage = "expected clear, fog:VISIBILITY_M (e.g. fog:100) or rain:MM_PER_HOUR (e.g. rain:10)"
        try:
            v = float(value)
        except ValueError:
            raise InputError(f"weather {text!r}: {usage}") from None
        if not math.isfinite(v) or v <= 0:
            raise InputError(f"weather {text!r}: the value must be a number > 0 ({usage})")
        if kind == "fog":
            return cls("fog", visibility_m=v)
        if kind == "rain":
            return cls("rain", rain_mm_h=v)
        raise InputError(f"weather {text!r}: {usage}")

    def __str__(self) -> str:
        if self.kind == "fog":
            return f"fog:{self.visibility_m:g}"
        if self.kind == "rain":
            return f"rain:{self.rain_mm_h:g}"
        return "clear"

    @property
    def extinction_per_m(self) -> float:
        if self.kind == "fog":
            return KOSCHMIEDER / self.visibility_m
        if self.kind == "rain":
            lam = 4.1 * self.rain_mm_h**-0.21  # 1/mm
            return math.pi * 8000e-6 / lam**3
        return 0.0

    def clutter(self, rng: np.random.Generator, hard_range_m: np.ndarray, min_range_m: float, model):
        """One weather echo candidate per pulse: ``(range (N,), signal (N,))``, range 0 for none.
        ``hard_range_m`` is each pulse's nearest surface (0: none within the maximum range)."""
        n = len(hard_range_m)
        r = np.zeros(n)
        s = np.zeros(n)
        if self.kind == "fog":
            alpha = self.extinction_per_m + model.alpha_per_m
            rho_fog = math.pi * FOG_BACKSCATTER_RATIO * self.extinction_per_m * PULSE_LENGTH_M
            lo = max(OVERLAP_M, min_range_m)
            far = np.where(hard_range_m > 0, hard_range_m, lo + 10.0 / alpha)
            far = np.maximum(far, lo * 1.001)
            # draw r with density proportional to exp(-2 alpha r)/r^2 on [lo, far] by inverse CDF: one
            # cumulative table over [lo, the farthest bound], each pulse drawing below its own bound's value
            grid = np.geomspace(lo, float(far.max()), _GRID)
            dens = np.exp(-2 * alpha * grid) / grid**2
            cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
            r = np.interp(rng.random(n) * np.interp(far, grid, cdf), cdf, grid)
            s = rho_fog * np.exp(-2 * alpha * r) / r**2
        elif self.kind == "rain":
            p = 1.0 - math.exp(-RAIN_CLUTTER_PER_MM_H * self.rain_mm_h)
            hit = rng.random(n) < p
            at = rng.uniform(min_range_m, RAIN_CLUTTER_MAX_M, n)
            r = np.where(hit, at, 0.0)
            s = np.where(hit, DROPLET_REFLECTIVITY / np.maximum(r, 1e-3) ** 2, 0.0)
        return r, s
