"""The place prior: where in the map, and facing which way, could this scan have been taken?

Global localization in a town-sized map fails when the few particles that land near the true pose are
outnumbered by look-alike places. The prior points the particles at the places that already look right,
from the map alone:

* **Map side, once per map** (:meth:`PlacePrior.build`): on a grid of ``cell_m`` over the drivable area, a
  virtual sensor casts horizontal rays all around (``bins`` azimuths) at a few heights above the map's
  ground; each azimuth keeps the nearest hit (capped at ``max_range_m``). The result is a *profile*: the
  distance to the nearest structure in every direction, in two height bands: **high** (``high_heights_m``,
  2.2-3.4 m: above parked cars, which differ from drive to drive and hide the facades in the low band,
  so the high band ranks the true place first for several times as many scans) and **low**
  (``heights_m``, 0.6-1.4 m: for sensors that see nothing above their own height, such as an 8-beam
  sensor whose beams all point below the horizon). Stored quantised to ``quant_m`` (one byte per azimuth
  and band) in the map folder (``place_prior.npz``, with a version stamp and a key of the map and the
  parameters, rebuilt when either changes).
* **A sensor's own top beam** (``beam_deg``, a prior of its own, :func:`beam_params`): a sensor that sees
  nothing above the parked cars (all its beams below the horizon) is left with the low band, where
  today's parked cars and the mapping drive's hide the facades. Its highest beam passes over the cars a
  few metres away and reaches the facades (or the road, some 60 m out for a beam 1.5° below the horizon),
  so the profile of that beam alone, rendered from the sensor's height at the beam's elevation, is
  compared instead: it ranks the true place first about twice as often as the low band, and its
  aligned yaw is within a few degrees where the low band's is often far off
  (``tools/prior_rank.py`` measures both on a drive). Stored beside the band prior
  (``place_prior_beam*.npz``, one per beam elevation and sensor height).
* **Scan side, every search update** (:func:`scan_profile`): the scan's points whose height above the
  ground lies in a band (``high_band_m``, ``band_m``), or for a beam prior whose elevation lies within
  ``beam_tol_deg`` of the beam's, give, per azimuth bin, the nearest horizontal distance. Bins with no
  such point are unknown and left out of the comparison; the high band is used when
  the scan knows at least ``min_known_share`` of its bins, else the low one. So any sensor (8 to 128 beams)
  gives a profile of the same kind.
* **Matching** (:meth:`PlacePrior.match`): a rotation of the car is a circular shift of its profile, so
  every cell is compared with the scan at *every* yaw at once: the masked squared difference for all
  shifts is three circular correlations, done by FFT for all cells together. Each cell gets its best
  shift (its yaw, refined between bins) and cost. The profile's FFT magnitude is the rotation-invariant
  descriptor of the Scan Context / ring-key family; the full shift search makes it unnecessary to keep
  it: the profile itself is the descriptor and the search is exact over yaw.

Values are compared as ``log(1 + r)``: a 1 m error at 3 m matters, at 30 m it hardly does.
Pure numpy apart from :meth:`PlacePrior.build`, which casts through a :class:`~rangemcl.raycast.RayCaster`.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError
from rangemcl.se2 import wrap_angle

PRIOR_FILE = "place_prior.npz"
PRIOR_VERSION = 2


@dataclass(frozen=True)
class PriorParams:
    """How the prior is rendered; part of its cache key."""

    cell_m: float = 2.0  # grid spacing over the drivable area
    bins: int = 360  # azimuth bins (1 degree)
    heights_m: tuple[float, ...] = (0.6, 1.0, 1.4)  # low band: virtual horizontal rays above the ground
    band_m: tuple[float, float] = (0.4, 1.6)  # ... and the scan points that count for it
    high_heights_m: tuple[float, ...] = (2.2, 2.8, 3.4)  # high band (above parked cars)
    high_band_m: tuple[float, float] = (2.0, 3.6)
    min_known_share: float = 0.1  # the high band is used when the scan knows this share of its bins
    max_range_m: float = 30.0  # profiles are capped here (and the scan's points beyond are ignored)
    min_range_m: float = 1.5  # scan points closer than this are ignored (the car itself)
    quant_m: float = 0.125  # storage step: one byte per bin reaches 255 · 0.125 = 31.9 m (two bytes
    # per bin where max_range_m needs more)
    beam_deg: float | None = None  # a beam prior: one profile, the sensor's beam at this elevation ...
    beam_height_m: float = 1.73  # ... cast from this height above the ground ...
    beam_tol_deg: float = 0.3  # ... compared with the scan's points within this of its elevation

    def check(self) -> None:
        if not (self.cell_m > 0 and self.bins >= 8 and self.max_range_m > self.min_range_m >= 0):
            raise InputError(f"place prior: bad parameters {self}")
        if not self.quant_m > 0 or self.max_range_m / self.quant_m > 65535:
            raise InputError("place prior: max_range_m / quant_m must fit two bytes (<= 65535)")
        if self.beam_deg is not None and not (
            -60.0 < self.beam_deg < 60.0 and self.beam_height_m > 0 and self.beam_tol_deg > 0
        ):
            raise InputError(f"place prior: bad beam ({self.beam_deg} deg at {self.beam_height_m} m)")
        for band, heights in ((self.band_m, self.heights_m), (self.high_band_m, self.high_heights_m)):
            if not band[0] < band[1] or not heights:
                raise InputError(f"place prior: bad height band {band} or heights {heights}")

    @property
    def rows(self) -> int:
        """Profiles per cell: the low and the high band, or the one beam."""
        return 2 if self.beam_deg is None else 1

    @property
    def levels(self) -> int:
        """Quantisation steps stored (the range ``levels · quant_m`` covers ``max_range_m``)."""
        return max(255, int(math.ceil(self.max_range_m / self.quant_m)))

    @property
    def dtype(self):
        return np.uint8 if self.levels <= 255 else np.uint16

    def key_dict(self) -> dict:
        """The parameters as the cache key sees them: a band prior's without the beam fields, which do not
        apply to it (so band priors stored without them keep their key)."""
        d = asdict(self)
        if self.beam_deg is None:
            for k in ("beam_deg", "beam_height_m", "beam_tol_deg"):
                d.pop(k)
        return d

    @property
    def file_name(self) -> str:
        if self.beam_deg is None:
            return PRIOR_FILE
        return f"place_prior_beam{self.beam_deg:+.2f}_h{self.beam_height_m:.2f}.npz"


BEAM_MAX_RANGE_M = 100.0  # a beam prior's profiles reach this far (a beam 1.5° down meets the road ~60 m out)


def beam_params(base: PriorParams, beam_deg: float, sensor_height_m: float) -> PriorParams:
    """The beam prior's parameters for a sensor whose highest beam is at ``beam_deg`` (rounded to
    0.01°, so that one sensor's scans name one prior) mounted ``sensor_height_m`` above the ground."""
    return replace(
        base,
        beam_deg=round(float(beam_deg), 2),
        beam_height_m=round(float(sensor_height_m), 2),
        max_range_m=BEAM_MAX_RANGE_M,
    )


def elevations_deg(points: np.ndarray) -> np.ndarray:
    """Each point's elevation (degrees) in the frame of ``points`` ``(M, 3)`` (NaN for a point at the
    origin or not finite)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        r = np.hypot(p[:, 0], p[:, 1])
        return np.where(r > 0, np.degrees(np.arctan2(p[:, 2], r)), np.nan)


def top_beam_deg(points: np.ndarray, min_range_m: float = 1.5, min_points: int = 200) -> float | None:
    """The elevation of a scan's highest ring of returns (degrees, in the frame of ``points``: the
    sensor's own, not levelled): the median elevation of the points within 0.3° of the 99.5th
    percentile of all (a ring of an 8-beam sensor holds about 12 % of them, so the percentile lies in it
    and a few stray points above do not move it). ``None`` for fewer than ``min_points`` points beyond
    ``min_range_m``."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    keep = np.hypot(p[:, 0], p[:, 1]) >= min_range_m
    if keep.sum() < min_points:
        return None
    el = elevations_deg(p[keep])
    top = np.quantile(el, 0.995)
    return float(np.median(el[np.abs(el - top) <= 0.3]))


_MATCH_CHUNK = 512  # cells per pass of PlacePrior.match: about 9 MB of temporaries (4096: 70 MB, and slower)
TWO_STAGE_MIN_CELLS = 50_000  # priors this large are matched in two stages (PlacePrior.match): a city's
COARSE_FACTOR = 6  # ... first on bins this many times coarser (6 degrees) ...
SHORTLIST = 5_000  # ... then these best cells on the full bins
# A band's cell spectra are kept from one match to the next where they take at most this (MB): they are
# half of a match's work (a town's prior of 2,670 cells: 15 MB, 5,615 cells: 33 MB; a city's is larger
# and recomputes them at each match, as the memory budget of its map asks)
SPECTRA_MAX_MB = 64


def _encode(x: np.ndarray) -> np.ndarray:
    return np.log1p(np.asarray(x, np.float64))


SURFACE_SPREAD_FRAC = 0.1  # the distances one surface gives in one bin: within this share of the distance
SURFACE_SPREAD_MIN_M = 0.2  # ... and at least this (the range noise of a weak far return)


def surface_spread_m(r: np.ndarray) -> np.ndarray:
    """How far apart (m) the horizontal distances of one surface's returns in one azimuth bin can lie at
    distance ``r``: a 1-degree bin across a wall hit at up to 80 degrees' incidence spans
    ``r·tan(80°)·(π/180) ≈ 0.1·r``, and range noise sets a floor."""
    return np.maximum(SURFACE_SPREAD_MIN_M, SURFACE_SPREAD_FRAC * np.asarray(r, np.float64))


def _profile(p: np.ndarray, r: np.ndarray, keep: np.ndarray, params: PriorParams, returns: int = 1):
    """Per azimuth bin the nearest horizontal distance ``r`` of the points ``keep`` selects (beyond
    ``min_range_m``), and which bins have one. ``returns`` k > 1: the nearest distance at which k returns
    lie within one surface's spread (:func:`surface_spread_m`) at or beyond it; a bin without such a
    group is unknown. Scattered spurious returns (rain droplets, dust, mixed pixels) then set no bin
    unless k of them fall within a few centimetres to decimetres of each other, however many pulses the
    sensor fires per bin, while a surface returns several neighbouring pulses in each bin."""
    B = params.bins
    keep = keep & (r >= params.min_range_m)
    prof = np.full(B, params.max_range_m)
    known = np.zeros(B, bool)
    if keep.any():
        az = np.arctan2(p[keep, 1], p[keep, 0])
        b = np.clip(((az + np.pi) / (2 * np.pi) * B).astype(np.int64), 0, B - 1)
        rk = np.minimum(r[keep], params.max_range_m)
        if returns <= 1:
            np.minimum.at(prof, b, rk)
            known[b] = True
        else:
            order = np.lexsort((rk, b))  # by bin, then by distance
            bs, rs = b[order], rk[order]
            # one sorted key over all bins (a bin's keys lie apart from the next bin's by more than any
            # distance plus its spread), so one search finds each return's group within its own bin
            stride = 2.0 * params.max_range_m + 1.0
            key = bs * stride + rs
            group = np.searchsorted(key, key + surface_spread_m(rs), side="right") - np.arange(len(rs))
            good = np.flatnonzero(group >= returns)
            gb = bs[good]  # sorted by bin, then distance: each bin's first is its nearest good return
            first = np.flatnonzero(np.diff(gb, prepend=-1) != 0)
            prof[gb[first]] = rs[good[first]]
            known[gb[first]] = True
    return prof, known


def scan_profile(
    points: np.ndarray,
    sensor_height_m: float,
    params: PriorParams,
    elevation_deg: np.ndarray | None = None,
    returns: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Per band (row 0 low, row 1 high) and azimuth bin the nearest horizontal distance of the scan's
    points in that height band, and a mask of the bins that have one. ``points`` ``(M, 3)`` in the
    *levelled* sensor frame (x forward); bin ``i`` spans azimuths ``[−π + iΔ, −π + (i+1)Δ)``. Returns
    ``(profile (2, B), known (2, B) bool)``; for a beam prior (``params.beam_deg``) one row, of the
    points within ``beam_tol_deg`` of the beam's elevation: ``elevation_deg`` ``(M,)`` gives each point's
    elevation in the sensor's own frame (before levelling, which tilts a ring by the roll and pitch: a
    fraction of a degree can be half the ring spacing of a sensor with few beams), else it is read from
    ``points``. ``returns`` k > 1: each bin the nearest distance with k returns within one surface's spread
    at or beyond it, a bin without such a group unknown (scattered spurious returns do not set a bin)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    finite = np.isfinite(p[:, 0] + p[:, 1] + p[:, 2])  # a NaN or an infinity in a row makes its sum one
    p = p[finite]
    h = p[:, 2] + float(sensor_height_m)
    r = np.hypot(p[:, 0], p[:, 1])
    if params.beam_deg is not None:
        el = elevations_deg(p) if elevation_deg is None else np.asarray(elevation_deg, np.float64)[finite]
        prof, known = _profile(p, r, np.abs(el - params.beam_deg) <= params.beam_tol_deg, params, returns)
        return prof[None], known[None]
    low = _profile(p, r, (h >= params.band_m[0]) & (h <= params.band_m[1]), params, returns)
    high = _profile(p, r, (h >= params.high_band_m[0]) & (h <= params.high_band_m[1]), params, returns)
    return np.stack([low[0], high[0]]), np.stack([low[1], high[1]])


@dataclass
class PriorMatch:
    """Every cell's best agreement with one scan: ``cost`` (mean squared difference of the encoded
    profiles over the scan's known bins, lower is better), ``yaw`` of the sensor at the best shift,
    ``known_bins`` (how many bins the scan could compare) and the ``band`` compared (0 low, 1 high)."""

    cost: np.ndarray  # (K,)
    yaw: np.ndarray  # (K,) radians
    known_bins: int
    band: int = 1


class PlacePrior:
    """Profiles rendered on a grid over the map's drivable area (see the module docstring).

    Args:
        xy: ``(K, 2)`` cell centres in the map frame.
        profiles: ``(K, 2, B)`` quantised ranges (``quant_m`` steps), low and high band (a beam prior:
            ``(K, 1, B)``, the beam); uint8, or uint16 where ``max_range_m`` needs more steps.
        params: the :class:`PriorParams` they were rendered with.
    """

    def __init__(
        self, xy: np.ndarray, profiles: np.ndarray, params: PriorParams, *, build_s: float | None = None
    ):
        self.xy = np.asarray(xy, np.float64).reshape(-1, 2)
        self.profiles = np.asarray(profiles, params.dtype)
        self.params = params
        # seconds it took to render, for a prior rendered in this process (None: read from a file, whose
        # bytes hold no timing: the same map gives the same file; rangemcl.mapping.report keeps timings)
        self.build_s = None if build_s is None else float(build_s)
        if self.profiles.shape != (len(self.xy), params.rows, params.bins) or len(self.xy) == 0:
            raise InputError(f"place prior: {len(self.xy)} cells but profiles of shape {self.profiles.shape}")
        # the encoded value of each quantised range: a profile's spectra are computed from these at match
        # time, a chunk of cells at a time (kept whole they take about 12 KB a cell: 280 MB for 24,000 cells)
        self._table = _encode(np.arange(params.levels + 1, dtype=np.float64) * params.quant_m)
        self._coarse: np.ndarray | None = None  # the two-stage match's coarse profiles, made on first use
        self._tree = None  # a k-d tree of the cell centres (cell_tree), made on first use
        self._spectra: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}  # by band (_cell_spectra)
        # the most the kept spectra may take (MB): 0 keeps none (a map held within a memory budget, which
        # counted this prior's nbytes when it was loaded)
        self.spectra_max_mb = SPECTRA_MAX_MB
        # the returns a scan's profile bin needs in candidates() (scan_profile's ``returns``; the filter
        # sets its `init.prior_profile_returns`)
        self.scan_returns = 1

    @property
    def nbytes(self) -> int:
        """Bytes held in memory (the cell centres and the profiles; for priors matched in two stages the
        coarse profiles too, made at the first match; the cell spectra kept since the first match)."""
        coarse = self.profiles.nbytes // COARSE_FACTOR if len(self.xy) >= TWO_STAGE_MIN_CELLS else 0
        spectra = sum(a.nbytes + b.nbytes for a, b in filter(None, self._spectra.values()))
        return int(self.xy.nbytes + self.profiles.nbytes + coarse + spectra)

    # --- building -----------------------------------------------------------------------------------------

    @classmethod
    def build(
        cls,
        caster,
        cells_xy: np.ndarray,
        ground_z: np.ndarray,
        params: PriorParams | None = None,
        chunk: int = 2048,
    ) -> PlacePrior:
        """Render the profiles of the cells ``cells_xy`` ``(K, 2)`` (ground height ``ground_z`` ``(K,)``)
        through ``caster`` (the map's mesh)."""
        params = params or PriorParams()
        params.check()
        t0 = time.perf_counter()
        xy = np.asarray(cells_xy, np.float64).reshape(-1, 2)
        gz = np.asarray(ground_z, np.float64).reshape(-1)
        B = params.bins
        az = -np.pi + (np.arange(B) + 0.5) * (2 * np.pi / B)
        if params.beam_deg is None:  # horizontal rays at the bands' heights
            dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros(B)])  # (B, 3)
            heights = np.asarray([*params.heights_m, *params.high_heights_m])
            cast_m, horizontal = params.max_range_m, 1.0
        else:  # the beam from the sensor's height: its hits' horizontal distances
            el = math.radians(params.beam_deg)
            horizontal = math.cos(el)
            dirs = np.column_stack(
                [horizontal * np.cos(az), horizontal * np.sin(az), np.full(B, math.sin(el))]
            )
            heights = np.asarray([params.beam_height_m])
            cast_m = params.max_range_m / horizontal
        H, n_low = len(heights), len(params.heights_m)
        out = np.empty((len(xy), params.rows, B), params.dtype)
        for lo in range(0, len(xy), chunk):
            c = xy[lo : lo + chunk]
            k = len(c)
            origins = np.empty((k, H, B, 3))
            origins[..., 0] = c[:, None, None, 0]
            origins[..., 1] = c[:, None, None, 1]
            origins[..., 2] = gz[lo : lo + chunk, None, None] + heights[None, :, None]
            d = np.broadcast_to(dirs, (k, H, B, 3))
            hits = caster.cast(origins.reshape(-1, 3).astype(np.float32), d.reshape(-1, 3), cast_m)
            r = np.where(np.isfinite(hits.ranges), hits.ranges * horizontal, params.max_range_m)
            r = np.minimum(r, params.max_range_m).reshape(k, H, B)
            if params.beam_deg is None:
                bands = np.stack([r[:, :n_low].min(axis=1), r[:, n_low:].min(axis=1)], axis=1)  # (k, 2, B)
            else:
                bands = r  # (k, 1, B)
            q = np.clip(np.rint(bands / params.quant_m), 0, params.levels)
            out[lo : lo + chunk] = q.astype(params.dtype)
        return cls(xy, out, params, build_s=time.perf_counter() - t0)

    # --- matching ----------------------------------------------------------------------------------------

    def match(
        self, profile: np.ndarray, known: np.ndarray, *, two_stage: bool | None = None, cells=None
    ) -> PriorMatch:
        """Compare a scan's profile (:func:`scan_profile`) with every cell at every yaw.

        ``cells`` (indices): compare only these cells, in one stage; the others get an infinite cost (a
        search that spreads the prior's cells over its updates).

        ``two_stage`` (default: for priors of at least ``TWO_STAGE_MIN_CELLS`` cells, a city's) first
        compares every cell on ``COARSE_FACTOR``-times coarser azimuth bins (each the nearest of its bins:
        the same kind of profile), then only the ``SHORTLIST`` best of them on the full bins; the other
        cells get an infinite cost. The shortlisted cells' costs and yaws are exactly the one-stage ones."""
        B, R = self.params.bins, self.params.rows
        prof = np.asarray(profile, np.float64).reshape(R, B)
        kn = np.asarray(known, bool).reshape(R, B)
        band = 1 if R == 2 and kn[1].sum() >= self.params.min_known_share * B else 0
        q = _encode(prof[band])
        m = kn[band].astype(np.float64)
        n = m.sum()
        K = len(self.xy)
        if n < 1:
            return PriorMatch(np.full(K, np.inf), np.zeros(K), 0, band)
        if cells is not None:
            keep = np.asarray(cells, np.int64).reshape(-1)
            best, yaw = np.full(K, np.inf), np.zeros(K)
            sp = self._cell_spectra(band)
            sp = None if sp is None else (sp[0][keep], sp[1][keep])
            best[keep], yaw[keep] = self._best_shifts(self.profiles[keep, band], q, m, sp)
            return PriorMatch(np.maximum(best, 0.0), wrap_angle(yaw), int(n), band)
        if two_stage is None:
            two_stage = K >= TWO_STAGE_MIN_CELLS
        F = COARSE_FACTOR
        if not two_stage or B % F or K <= SHORTLIST:
            best, yaw = self._best_shifts(self.profiles[:, band], q, m, self._cell_spectra(band))
            return PriorMatch(np.maximum(best, 0.0), wrap_angle(yaw), int(n), band)
        coarse_q = _encode(prof[band].reshape(-1, F).min(axis=1))
        coarse_m = kn[band].reshape(-1, F).any(axis=1).astype(np.float64)
        rough, _ = self._best_shifts(self._coarse_profiles()[:, band], coarse_q, coarse_m)
        keep = np.sort(np.argpartition(rough, SHORTLIST - 1)[:SHORTLIST])
        best, yaw = np.full(K, np.inf), np.zeros(K)
        best[keep], yaw[keep] = self._best_shifts(self.profiles[keep, band], q, m)
        return PriorMatch(np.maximum(best, 0.0), wrap_angle(yaw), int(n), band)

    def _coarse_profiles(self) -> np.ndarray:
        """``(K, rows, B / COARSE_FACTOR)``: each coarse bin the nearest of its bins (made once)."""
        if self._coarse is None:
            K, R, B = self.profiles.shape
            self._coarse = self.profiles.reshape(K, R, B // COARSE_FACTOR, COARSE_FACTOR).min(axis=3)
        return self._coarse

    def _cell_spectra(self, band: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The spectra of every cell's encoded profile in ``band`` and of its square, ``(K, B // 2 + 1)``
        complex each, as :meth:`_best_shifts` computes them (the same chunks, so the same bits): made at
        the first match and kept, or ``None`` where they would take more than ``spectra_max_mb``."""
        if band not in self._spectra:
            K, B = len(self.xy), self.params.bins
            size_mb = K * (B // 2 + 1) * 32 / 2**20  # two complex128 arrays
            if size_mb > self.spectra_max_mb:
                self._spectra[band] = None
            else:
                cells = self.profiles[:, band]
                s1 = np.empty((K, B // 2 + 1), np.complex128)
                s2 = np.empty_like(s1)
                for lo in range(0, K, _MATCH_CHUNK):
                    enc = self._table[cells[lo : lo + _MATCH_CHUNK]]
                    s1[lo : lo + len(enc)] = np.fft.rfft(enc, axis=1)
                    s2[lo : lo + len(enc)] = np.fft.rfft(enc * enc, axis=1)
                self._spectra[band] = (s1, s2)
        return self._spectra[band]

    def _best_shifts(
        self, cells: np.ndarray, q: np.ndarray, m: np.ndarray, spectra: tuple | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each cell's least masked mean squared difference over all circular shifts, and its yaw.

        ``cells`` ``(k, B)`` quantised profiles, ``q`` the scan's encoded profile, ``m`` its mask;
        ``spectra``: the cells' spectra (:meth:`_cell_spectra`'s rows for ``cells``), else computed here."""
        B = len(q)
        n = m.sum()
        # cost(s) = Σ_i m_i (q_i − c_{i+s})² / n, each sum a circular correlation over i
        A1 = np.conj(np.fft.rfft(m * q))
        A0 = np.conj(np.fft.rfft(m))
        qq = float(np.sum(m * q * q))
        K = len(cells)
        best, yaw = np.empty(K), np.empty(K)
        for lo in range(0, K, _MATCH_CHUNK):  # bounded temporaries: (chunk, B) arrays, not (K, B)
            if spectra is None:
                enc = self._table[cells[lo : lo + _MATCH_CHUNK]]  # (k, B)
                f1, f2 = np.fft.rfft(enc, axis=1), np.fft.rfft(enc * enc, axis=1)
            else:
                f1, f2 = spectra[0][lo : lo + _MATCH_CHUNK], spectra[1][lo : lo + _MATCH_CHUNK]
            cross = np.fft.irfft(A1[None, :] * f1, n=B, axis=1)  # Σ m q c_{i+s}
            sq = np.fft.irfft(A0[None, :] * f2, n=B, axis=1)  # Σ m c²_{i+s}
            cost = (qq - 2.0 * cross + sq) / n  # (k, B)
            s = np.argmin(cost, axis=1)
            rows = np.arange(len(cost))
            c0 = cost[rows, s]
            cm, cp = cost[rows, (s - 1) % B], cost[rows, (s + 1) % B]
            den = cm - 2 * c0 + cp
            frac = np.where(den > 1e-12, 0.5 * (cm - cp) / np.where(den > 1e-12, den, 1.0), 0.0)
            best[lo : lo + len(cost)] = c0
            yaw[lo : lo + len(cost)] = (s + np.clip(frac, -0.5, 0.5)) * (2 * np.pi / B)
        return best, yaw

    def cell_tree(self):
        """A k-d tree of the cell centres (made on first use)."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.xy)
        return self._tree

    def candidates(
        self,
        points: np.ndarray,
        sensor_height_m: float,
        top: int,
        elevation_deg: np.ndarray | None = None,
        cells=None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The ``top`` best cells for a scan: ``(xy (T, 2), yaw (T,), cost (T,), known_bins)``, best first
        (``elevation_deg``: as :func:`scan_profile`; ``cells``: only among these, as :meth:`match`)."""
        prof, known = scan_profile(points, sensor_height_m, self.params, elevation_deg, self.scan_returns)
        mt = self.match(prof, known, cells=cells)
        top = int(min(top, len(self.xy) if cells is None else len(np.asarray(cells).reshape(-1))))
        idx = np.argpartition(mt.cost, top - 1)[:top]
        idx = idx[np.argsort(mt.cost[idx], kind="stable")]
        return self.xy[idx], mt.yaw[idx], mt.cost[idx], mt.known_bins

    # --- files -------------------------------------------------------------------------------------------

    def save(self, path: Path, key: str) -> None:
        """Write the prior to ``path`` (atomically). The file holds the cells, the profiles and a meta
        record (version, key, parameters, a sha256 of the arrays): no timing, so the same map and
        parameters give the same bytes."""
        from rangemcl.common.atomic import atomic_write, savez_stable

        xy = self.xy.astype(np.float32)
        meta = {"version": PRIOR_VERSION, "key": key, "params": asdict(self.params)}
        meta["sha256"] = _arrays_sha256(xy, self.profiles)
        atomic_write(
            Path(path),
            lambda fh: savez_stable(
                fh, compressed=True, xy=xy, profiles=self.profiles, meta=np.array(json.dumps(meta))
            ),
        )

    @classmethod
    def load(cls, path: Path, key: str | None = None) -> PlacePrior | None:
        """The prior in ``path``; ``None`` when it is missing, of another version or (given ``key``) of
        another map or parameters (then it is rebuilt); a damaged file (truncated, a corrupt zip, arrays
        that do not match the sha256 stored with them) is one :class:`InputError` that names the command
        that renders it again."""
        path = Path(path)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                if not isinstance(meta, dict):
                    raise ValueError("its meta record is not a JSON object")
                if meta.get("version") != PRIOR_VERSION or (key is not None and meta.get("key") != key):
                    return None
                xy, profiles = z["xy"], z["profiles"]
                if "sha256" in meta and meta["sha256"] != _arrays_sha256(xy, profiles):
                    raise ValueError("its arrays do not match their sha256")
                p = meta["params"]
                params = PriorParams(
                    **{
                        **p,
                        **{k: tuple(p[k]) for k in ("heights_m", "band_m", "high_heights_m", "high_band_m")},
                    }
                )
                params.check()
                return cls(xy, profiles, params)
        except Exception as err:  # zip, zlib, npy format and JSON errors all mean a damaged file
            why = " ".join(str(err).split()) or type(err).__name__
            remedy = (
                f"render it again with `rangemcl place-prior {path.parent}`"
                if path.name == PRIOR_FILE
                else "delete it: the next global localization with this sensor renders it again"
            )
            raise InputError(f"{path}: the place prior is damaged ({why}); {remedy}") from None


def _arrays_sha256(xy: np.ndarray, profiles: np.ndarray) -> str:
    """The sha256 of a prior's stored arrays (their dtype, shape and bytes)."""
    h = hashlib.sha256()
    for a in (xy, profiles):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def prior_key(mesh_map, cells_xy: np.ndarray, params: PriorParams) -> str:
    """What a stored prior must match: the map's mesh (triangle count, extent; not the vertex count, which
    ``rangemcl map-upgrade`` changes: a tile file holds the vertices its faces use, so border vertices
    are in two files), the cells, the parameters."""
    h = hashlib.sha1()
    h.update(repr((int(mesh_map.n_triangles), tuple(np.round(mesh_map.extent, 3)))).encode())
    h.update(np.ascontiguousarray(np.round(cells_xy, 3)).tobytes())
    h.update(repr(params.key_dict()).encode())
    return h.hexdigest()[:20]


def grid_cells(corners: np.ndarray, cell_m: float, grid_m: float) -> np.ndarray:
    """Centres of a ``grid_m`` grid covering the drivable cells (lower-left ``corners`` of ``cell_m``)."""
    c = np.asarray(corners, np.float64) + 0.5 * cell_m
    ij = np.unique(np.floor(c / grid_m).astype(np.int64), axis=0)
    return (ij + 0.5) * grid_m


PARTIAL = "+partial"  # the key's suffix of a prior rendered with some tiles coarse or left out (a budget)


def load_or_build(
    mesh_map,
    caster,
    area_corners: np.ndarray,
    area_cell_m: float,
    params: PriorParams | None = None,
    *,
    notify=None,
    fallback_dir: str | Path | None = None,
    replace_damaged: bool = False,
):
    """The map's place prior: read from the map folder when one matches, else rendered (and written
    there when the folder is writable). Returns ``(prior, how)`` with how in ``loaded | built | built
    (not saved: ...)``.

    ``notify(message)``: told, before a render starts, what is rendered and where it goes (a render takes
    seconds to minutes and writes into the map folder). ``fallback_dir``: where the prior is read and
    written when the map folder is not writable (e.g. a run's results folder). ``replace_damaged``: a
    damaged stored prior is rendered again and replaced (else it is an :class:`InputError`)."""
    params = params or PriorParams()
    params.check()
    xy = grid_cells(area_corners, area_cell_m, params.cell_m)
    key = prior_key(mesh_map, xy, params)
    budget = mesh_map.budgeted  # a map seen within a memory budget
    src = getattr(mesh_map, "source_dir", None)
    path = None if src is None else Path(src) / params.file_name
    spare = None if fallback_dir is None else Path(fallback_dir) / params.file_name
    damaged = None
    for place in (p for p in (path, spare) if p is not None):
        # a prior rendered where the budget held some tiles coarse or none is stored under its own key: a
        # run within a budget may take it, a run with the whole map renders its own
        for k in (key, key + PARTIAL) if budget else (key,):
            try:
                prior = PlacePrior.load(place, k)
            except InputError as err:
                if not replace_damaged:
                    raise
                damaged = err
                break
            if prior is not None:
                return prior, "loaded"
    target = path
    if path is not None and spare is not None and not _writable(path):
        target = spare
    if notify is not None:
        where = "kept in memory only" if target is None else f"written to {target}"
        ahead = "" if src is None else f"; `rangemcl place-prior {src}` renders it ahead of a run"
        what = "place prior" if params.beam_deg is None else f"place prior of a {params.beam_deg:g} deg beam"
        notify(
            f"rendering the map's {what} ({len(xy):,} cells of {params.cell_m:g} m, {where}): the "
            f"first global localization on a map renders it once{ahead}"
        )
    gz = mesh_map.ground.height_at(xy[:, 0], xy[:, 1])
    t0 = time.perf_counter()
    if budget:  # rendered tile by tile
        tile = mesh_map.tile_at(xy[:, 0], xy[:, 1])
        profiles = np.empty((len(xy), params.rows, params.bins), params.dtype)
        partial = False
        for t in np.unique(tile):
            sel = np.flatnonzero(tile == t)
            held = mesh_map.update(xy[sel], params.max_range_m + 1.0)
            partial = partial or bool(held["map_coarse"] or held["map_left_out"])
            profiles[sel] = PlacePrior.build(caster, xy[sel], gz[sel], params).profiles
        prior = PlacePrior(xy, profiles, params, build_s=time.perf_counter() - t0)
        key += PARTIAL if partial else ""
    else:
        prior = PlacePrior.build(caster, xy, gz, params)
    how = "built" if damaged is None else "built (a damaged file replaced)"
    if target is not None:
        try:
            prior.save(target, key)
        except (OSError, InputError) as err:
            how = f"built (not saved: {err})"
        else:
            record_build(target, prior)
            if target != path:
                how += f" (saved in {target.parent}: the map folder is not writable)"
    return prior, how


def _writable(path: Path) -> bool:
    """Whether ``path`` can be written (replaced, or created in its folder)."""
    import os

    if path.exists():
        return os.access(path, os.W_OK) and os.access(path.parent, os.W_OK | os.X_OK)
    return path.parent.is_dir() and os.access(path.parent, os.W_OK | os.X_OK)


REPORT_FILE = "report.json"  # beside the prior: how long each stored prior took to render


def record_build(path: Path, prior: PlacePrior) -> None:
    """Note in ``report.json`` beside the prior file ``path`` how long it took to render (the prior's own
    bytes hold no timing). A report that cannot be read or written is left as it is: it is informative."""
    from rangemcl.common.atomic import atomic_write

    report = Path(path).parent / REPORT_FILE
    try:
        doc = json.loads(report.read_text()) if report.is_file() else {}
        if not isinstance(doc, dict):
            return
        entry = {"seconds": prior.build_s, "cells": len(prior.xy)}
        doc.setdefault("place_prior", {})[Path(path).name] = entry
        atomic_write(report, json.dumps(doc, indent=2) + "\n")
    except (OSError, ValueError, AttributeError):
        return


def recorded_build_s(path: Path) -> float | None:
    """The render time that :func:`record_build` noted for the prior file ``path``, if any."""
    try:
        doc = json.loads((Path(path).parent / REPORT_FILE).read_text())
        return float(doc["place_prior"][Path(path).name]["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def circular_distance_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute angle difference in degrees, wrapped."""
    return np.degrees(np.abs(wrap_angle(np.asarray(a) - np.asarray(b))))


def sequence_costs(
    prior: PlacePrior,
    current: PriorMatch,
    past: list,
    radius_m: float | None = None,
    yaw_tol_deg: float = 10.0,
) -> np.ndarray:
    """Each cell's cost over a short sequence of scans: today's match and the matches of past scans
    (``past``: ``(PriorMatch, rel)`` with ``rel`` the past sensor pose in today's sensor frame, from the
    odometry). For each cell (at its best yaw today) the pose where the odometry puts each past scan is
    found, and the past scan's match counts with its best cell within ``radius_m`` (default 1.5 grid
    steps) of that pose whose aligned yaw lies within ``yaw_tol_deg`` of it (none: the past match's
    worst cost). The mean over the scans. A look-alike that fits one scan rarely fits the scans of the
    last metres where the odometry puts them (sequence matching, as SeqSLAM does for images)."""
    from rangemcl.se2 import se2_compose

    radius = 1.5 * prior.params.cell_m if radius_m is None else float(radius_m)
    tol = np.radians(yaw_tol_deg)
    poses = np.column_stack([prior.xy, current.yaw])
    K = len(poses)
    total = np.array(current.cost, np.float64)
    for match, rel in past:
        at = se2_compose(poses, np.broadcast_to(np.asarray(rel, np.float64), poses.shape))
        _d, idx = prior.cell_tree().query(at[:, :2], k=9, distance_upper_bound=radius)
        finite = np.isfinite(match.cost)
        worst = float(match.cost[finite].max()) if finite.any() else 0.0
        cost = np.append(np.where(finite, match.cost, worst), worst)  # index K: no cell there
        yaw = np.append(match.yaw, 0.0)
        dyaw = np.abs(wrap_angle(yaw[idx] - at[:, 2:3]))
        c = np.where((idx < K) & (dyaw <= tol), cost[idx], worst)
        total = total + c.min(axis=1)
    return total / (1 + len(past))


def describe_prior_file(map_dir: Path) -> str:
    """One line about the place prior stored in ``map_dir`` (``rangemcl map-info``): cells, size, render
    time; a damaged file is an :class:`InputError`."""
    path = Path(map_dir) / PRIOR_FILE
    prior = PlacePrior.load(path)
    if prior is None:
        return "none (rangemcl place-prior renders one)" if not path.is_file() else "of an older version"
    with np.load(path, allow_pickle=False) as z:
        key = str(json.loads(str(z["meta"])).get("key", ""))
    partial = ", rendered with tiles held coarse (a budget)" if key.endswith(PARTIAL) else ""
    seconds = recorded_build_s(path)
    took = "" if seconds is None else f", rendered in {seconds:.1f} s"
    return (
        f"{len(prior.xy)} cells of {prior.params.cell_m:g} m, {path.stat().st_size / 1e6:.1f} MB"
        f"{took}{partial}"
    )
