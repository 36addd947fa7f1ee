"""The realistic LiDAR's return model: from what a ray hits (material, angle, range) to whether the sensor
reports a point, how noisy its range is, and what intensity it reports.

The physics, per ray (monostatic sensor, target larger than the beam):

* **Effective reflectivity** ``ρ_eff``: the diffuse reflectivity the surface looks like from the sensor,
  ``reflectivity·cos θ`` (Lambertian) ``+ mirror·exp(-(θ/θ_s)²)/θ_s²`` (a specular lobe of half-width
  ``θ_s`` concentrates the reflected light ``1/θ_s²`` times more than a Lambertian surface spreads it,
  so a window or a chrome bumper glints only seen face on) ``+ retro·cos² θ`` (retro-reflectors return
  toward the source over a wide range of angles); θ is the angle of incidence.
* **Signal** ``S = ρ_eff · T · exp(-2 α r) / r²``: received power in units of a 100 % Lambertian target at
  1 m; ``T`` the two-way transmission of glass passed on the way, ``α`` the extinction per metre (the
  sensor's own losses, from its datasheet, plus the weather's).
* **Detection**: a datasheet states the range at which a 10 % and an 80 % target are detected. Those two
  points fix the detection threshold ``S_th`` and the sensor's extinction ``α`` (with ``α = 0`` when they
  are consistent with the inverse square alone); the probability of a return is
  ``Φ(ln(S/S_th)/DETECTION_SPREAD + Φ⁻¹(DATASHEET_DETECTION))``: ``DATASHEET_DETECTION`` at the threshold,
  rising to certainty for a few times stronger signals.
* **Range noise**: ``σ = σ_strong + (σ_weak - σ_strong)·min(1, sqrt(S_th / S))``: the datasheet's accuracy
  for strong returns, ``range_noise_weak_m`` at the threshold (shot-noise-limited timing degrades as the
  square root of the signal).
* **SNR** ``12·S/S_th``: the signal-to-noise ratio, 12 at the threshold (the SNR at which Ouster's
  datasheet states its weak-return accuracy); written beside the intensity (Ouster's signal channel
  counts photons, which grow the same way).
* **Intensity** by what the sensor family reports (``intensity_scale``): ``reflectivity_8bit`` (Velodyne's
  calibrated reflectivity and Ouster's reflectivity channel: ``100·ρ_eff`` for diffuse surfaces, 101-255
  for retro-reflectors on a log scale up to ``RETRO_FULL_SCALE``) or ``unit`` (0..1, as the KITTI HDL-64E
  scans store it: ``ρ_eff`` clipped to 1).

Constants marked "assumption" are not from a datasheet; docs/testbed.md lists them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from rangemcl.errors import InputError
from rangemcl.sensors import INTENSITY_SCALES  # noqa: F401  (the scales this model writes)

SPECULAR_LOBE_RAD = math.radians(2.0)  # half-width of a specular surface's glint (assumption: polished)
DETECTION_SPREAD = 0.3  # of ln(S): from 10 % to 90 % detection over a factor of 2.2 in signal (assumption)
DATASHEET_DETECTION = 0.9  # detection probability at a datasheet's stated range (Ouster states > 90 %)
SNR_AT_THRESHOLD = 12.0  # Ouster's datasheet quotes its weakest returns' accuracy at SNR 12
RETRO_FULL_SCALE = 100.0  # ρ_eff at which a reflectivity_8bit sensor reports 255 (assumption)


def sensor_extinction(range_10_m: float, range_80_m: float) -> tuple[float, float]:
    """``(S_th, α)``: the detection threshold and extinction (1/m) that put a 10 % target's limit at
    ``range_10_m`` and an 80 % one's at ``range_80_m``; ``α = 0`` when the ranges need none (or less)."""
    if not 0 < range_10_m < range_80_m:
        raise InputError(
            f"range at 10 % ({range_10_m} m) must be > 0 and below the range at 80 % ({range_80_m} m)"
        )
    alpha = (math.log(8.0) - 2.0 * math.log(range_80_m / range_10_m)) / (2.0 * (range_80_m - range_10_m))
    alpha = max(alpha, 0.0)
    s_th = 0.10 * math.exp(-2.0 * alpha * range_10_m) / range_10_m**2
    return s_th, alpha


@dataclass(frozen=True)
class ReturnModel:
    """One sensor's returns (see the module docstring); build it with :meth:`for_spec`."""

    s_threshold: float
    alpha_per_m: float
    noise_strong_m: float
    noise_weak_m: float
    intensity_scale: str
    extra_alpha_per_m: float = 0.0  # the weather's extinction, added to the sensor's

    @classmethod
    def for_spec(cls, spec, weather=None) -> ReturnModel:
        """The model of ``spec`` (its datasheet figures) in ``weather``
        (:class:`simbed.sim.weather.Weather`, clear by default)."""
        missing = [
            k
            for k in ("range_at_10pct_m", "range_at_80pct_m", "range_noise_weak_m")
            if getattr(spec, k) is None
        ]
        if missing:
            raise InputError(
                f"lidar spec {spec.name!r}: the realistic sensor model needs {', '.join(missing)} in the "
                "spec (the datasheet's detection ranges at 10 % and 80 % reflectivity; the range noise of "
                "weak returns)"
            )
        s_th, alpha = sensor_extinction(spec.range_at_10pct_m, spec.range_at_80pct_m)
        return cls(
            s_th,
            alpha,
            spec.range_noise_m,
            max(spec.range_noise_weak_m, spec.range_noise_m),
            spec.intensity_scale,
            0.0 if weather is None else weather.extinction_per_m,
        )

    def weather_dimming(self, range_m) -> np.ndarray:
        """What the weather takes from a return at ``range_m``, both ways: a calibrated sensor corrects
        for range in clear air only, so it reports the reflectivity dimmed by this."""
        return np.exp(-2.0 * self.extra_alpha_per_m * np.asarray(range_m, np.float64))

    # --- the physics -------------------------------------------------------------------------------------
    @staticmethod
    def effective_reflectivity(reflectivity, mirror, retro, cos_incidence) -> np.ndarray:
        c = np.clip(np.asarray(cos_incidence, np.float64), 0.0, 1.0)
        theta = np.arccos(c)
        glint = np.exp(-((theta / SPECULAR_LOBE_RAD) ** 2)) / SPECULAR_LOBE_RAD**2
        return reflectivity * c + mirror * glint + retro * c**2

    def signal(self, rho_eff, range_m, transmission=1.0) -> np.ndarray:
        r = np.maximum(np.asarray(range_m, np.float64), 1e-3)
        return rho_eff * transmission * np.exp(-2.0 * (self.alpha_per_m + self.extra_alpha_per_m) * r) / r**2

    def detection_probability(self, signal) -> np.ndarray:
        s = np.maximum(np.asarray(signal, np.float64), 1e-300)
        return ndtr(np.log(s / self.s_threshold) / DETECTION_SPREAD + ndtri(DATASHEET_DETECTION))

    def snr(self, signal) -> np.ndarray:
        """The signal-to-noise ratio of a return: ``SNR_AT_THRESHOLD`` at the detection threshold, in
        proportion to the signal above it (what Ouster reports as its signal channel, up to a scale)."""
        return SNR_AT_THRESHOLD * np.asarray(signal, np.float64) / self.s_threshold

    def noise_sigma(self, signal) -> np.ndarray:
        s = np.maximum(np.asarray(signal, np.float64), 1e-300)
        weak = np.minimum(1.0, np.sqrt(self.s_threshold / s))
        return self.noise_strong_m + (self.noise_weak_m - self.noise_strong_m) * weak

    def intensity(self, rho_eff) -> np.ndarray:
        rho = np.asarray(rho_eff, np.float64)
        if self.intensity_scale == "unit":
            return np.clip(rho, 0.0, 1.0).astype(np.float32)
        diffuse = np.clip(np.round(100.0 * rho), 0, 100)
        retro = 101.0 + np.round(
            154.0 * np.clip(np.log(np.maximum(rho, 1.0)) / math.log(RETRO_FULL_SCALE), 0, 1)
        )
        return np.where(rho > 1.0, np.minimum(retro, 255.0), diffuse).astype(np.float32)

    def range_limit_m(self, reflectivity: float) -> float:
        """The range at which a face-on target of ``reflectivity`` is detected with the datasheet's
        probability (where its signal meets the threshold), by bisection."""
        lo, hi = 1e-3, 1e4
        for _ in range(200):
            mid = math.sqrt(lo * hi)
            if self.signal(reflectivity, mid) >= self.s_threshold:
                lo = mid
            else:
                hi = mid
        return lo
