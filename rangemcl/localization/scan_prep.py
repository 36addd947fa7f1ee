"""Scan preparation for the localizer: which measured rays weigh the particles, de-skewed with the frame's
odometry and each point's firing time, levelled with the IMU's roll and pitch. Pure numpy; the rays'
randomness comes from the generator handed in.

Ray selection (``sampling``): ``points`` draws evenly over the valid points; ``elevation`` evenly over 2°
elevation bands (a sensor whose beams crowd the road near the car still sends rays farther and higher);
``structure`` gives the road (points within ``STRUCTURE_M`` of the sensor's ground) at most
``ground_share`` of the rays and what stands on it the rest, each part evenly over the elevation bands:
500 rays drawn evenly over the points of a sensor whose beams crowd the road (such as an HDL-64E) are
mostly road, which fits almost anywhere. Of what stands on the road, ``tall_share`` goes to points at
least ``tall_m`` above the ground (facades above the parked cars) and the rest to the points below: a
sensor whose beams point down (most of an HDL-64E's 2° bands meet structure only within 10-15 m of the
car) otherwise spends most of its structure rays on parked cars, which differ between the mapping drive
and today, and beside a row of cars the map lacks its true pose can score worse than a look-alike street
for many updates. A structure part without points gives its share to the other (the road keeps its own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError
from rangemcl.se2 import rotation_roll_pitch, row_norms, se2_between

RAY_SAMPLINGS = ("points", "elevation", "structure")
ELEVATION_BAND_DEG = 2.0  # sampling "elevation" and "structure": the bands sampled alike
STRUCTURE_M = 0.5  # a point this far above the sensor's ground met structure, not road


@dataclass
class ScanRays:
    """The measured rays used to weight the particles: unit directions in the levelled sensor frame at
    the scan's stamp, ranges, and which met structure (not the road)."""

    directions: np.ndarray  # (R, 3) float64
    ranges: np.ndarray  # (R,) float64
    valid_points: int  # valid points in the scan before subsampling
    structure: np.ndarray | None = None  # (R,) bool: the point lies STRUCTURE_M above the ground
    sensor_height_m: float | None = None  # the sensor's height above the ground the rays were levelled to

    def subset(self, which) -> ScanRays:
        """The rays selected by ``which`` (a boolean mask or a slice)."""
        return ScanRays(
            self.directions[which],
            self.ranges[which],
            self.valid_points,
            None if self.structure is None else self.structure[which],
            self.sensor_height_m,
        )


def lit_returns(intensity: np.ndarray, n: int) -> np.ndarray:
    """Which of a scan's ``n`` returns report intensity above zero (``(n,)`` bool), where any does: a
    scan whose returns all report zero (the ideal simulated sensor, a source without intensity) keeps
    every one. Fog, rain and dust echo weaker than any surface and report zero on a calibrated scale."""
    it = np.asarray(intensity, np.float64).reshape(-1)
    if len(it) != n:
        raise InputError(f"intensity of {len(it)} returns for a scan of {n} points")
    lit = it > 0
    return lit if lit.any() else np.ones(n, bool)


def _band_weights(
    p: np.ndarray,
    r: np.ndarray,
    sampling: str,
    ground_share: float,
    tall_share: float,
    tall_m: float,
    sensor_height_m: float,
) -> np.ndarray:
    """Each point's probability of being drawn: the parts (tall structure, low structure, road; one part
    for ``elevation``) get their shares, a part's share is split evenly over its elevation bands, a band's
    share evenly over its points. A structure part without points gives its share to the other."""
    key = np.floor(np.degrees(np.arcsin(p[:, 2] / r)) / ELEVATION_BAND_DEG).astype(np.int64)
    part = np.zeros(len(p), np.int64)
    share = np.array([1.0, 0.0, 0.0])
    if sampling == "structure":
        # height above the sensor's ground (levelled enough: a car's roll and pitch are small)
        h = p[:, 2] + sensor_height_m
        tall = (h >= tall_m) & (tall_share > 0)
        part = np.ones(len(p), np.int64)  # 0 tall, 1 low structure, 2 road
        part[tall] = 0
        part[h < STRUCTURE_M] = 2
        has = np.bincount(part, minlength=3) > 0
        t = tall_share if has[0] and has[1] else float(has[0])  # a structure part alone takes its share
        g = ground_share if has[2] and (has[0] or has[1]) else float(has[2])  # ... and the road alike
        share = np.array([(1.0 - g) * t, (1.0 - g) * (1.0 - t), g])  # sums to 1 over the parts present
    group = (key - key.min()) * 3 + part  # (band, part) groups: a small range of integers, counted directly
    counts = np.bincount(group)
    groups_in_part = np.bincount(np.flatnonzero(counts) % 3, minlength=3)
    # each group's weight, then each point's (the same divisions as point by point, done once per group)
    gp = np.arange(len(counts)) % 3  # each group's part
    weight = (share[gp] / np.maximum(groups_in_part[gp], 1) / np.maximum(counts, 1))[group]
    return weight / weight.sum()


VEHICLE_CELL_M = 0.3  # grid cell of the vehicle segmentation: points in touching cells are one object
VEHICLE_MIN_LENGTH_M = 1.0  # shorter objects (poles, trunks) are kept: they do not move between drives
VEHICLE_MAX_WIDTH_M = 3.0  # wider objects are not a vehicle seen from the road
VEHICLE_AZIMUTH_BIN = np.radians(0.5)  # azimuth bins of the check for objects in front of an object's ends
VEHICLE_OCCLUDER_M = 0.5  # something this much nearer beside an object's end hides part of it
VEHICLE_TOP_BEAM_MARGIN = np.radians(0.25)  # an object this near the top beam's elevation reaches it
VEHICLE_CUT_TOP_M = 2.5  # an object seen higher than this, cut off by the top beam, may be taller still


def top_elevation(points: np.ndarray) -> float:
    """The highest elevation in radians among ``points`` ``(M >= 1, 3)``: ``arctan2(z, hypot(x, y)).max()``,
    the same number, with the arctangent of the steepest few points only (it grows with ``z / r``)."""
    r_xy = np.hypot(points[:, 0], points[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = points[:, 2] / r_xy
    m = slope[np.isfinite(slope)].max(initial=-np.inf)
    steep = ~(slope < m - 1e-9 * abs(m))  # far wider than rounding; a NaN (0 / 0) is kept: arctan2 gives 0
    return float(np.arctan2(points[steep, 2], r_xy[steep]).max())


def vehicle_points(
    points: np.ndarray, sensor_height_m: float, max_length_m: float, max_height_m: float | None
) -> np.ndarray:
    """Which points ``(M, 3)`` (sensor frame, levelled) lie on an object that may be a parked vehicle: the
    points more than ``STRUCTURE_M`` above the sensor's ground, grouped into objects by touching cells of
    ``VEHICLE_CELL_M`` in (x, y); an object whose footprint (along its principal axes) is between
    ``VEHICLE_MIN_LENGTH_M`` and ``max_length_m`` long and at most ``VEHICLE_MAX_WIDTH_M`` wide, and whose
    highest point lies at most ``max_height_m`` above the ground (``None``: any height), is one, unless
    something nearer stands just beside one of its ends as the sensor sees it (then part of it is hidden
    and it may be longer: a wall seen between parked cars), or unless it is seen higher than a car
    (``VEHICLE_CUT_TOP_M``) up to the scan's top beam (its top is unseen: a wall or a facade near a
    sensor whose beams end a few metres up). A car against a wall, or cars parked bumper to bumper, join
    the larger object and stay."""
    from scipy import ndimage

    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(p), bool)
    h = p[:, 2] + sensor_height_m
    idx = np.flatnonzero(np.isfinite(h) & (h > STRUCTURE_M))
    if len(idx) == 0:
        return out
    ij = np.floor(p[idx, :2] / VEHICLE_CELL_M).astype(np.int64)
    ij -= ij.min(axis=0)
    occupied = np.zeros(tuple(ij.max(axis=0) + 1), bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    labels, n = ndimage.label(occupied, structure=np.ones((3, 3), bool))
    comp = labels[ij[:, 0], ij[:, 1]] - 1  # each point's object, 0..n-1
    xy = p[idx, :2]
    count = np.bincount(comp, minlength=n).astype(np.float64)
    mean = np.stack([np.bincount(comp, xy[:, k], n) for k in (0, 1)], axis=1) / count[:, None]
    d = xy - mean[comp]
    cxx, cyy, cxy = (
        np.bincount(comp, a * b, n) / count
        for a, b in ((d[:, 0], d[:, 0]), (d[:, 1], d[:, 1]), (d[:, 0], d[:, 1]))
    )
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # each object's major axis
    cos, sin = np.cos(angle)[comp], np.sin(angle)[comp]
    u = d[:, 0] * cos + d[:, 1] * sin
    v = -d[:, 0] * sin + d[:, 1] * cos
    extent = []
    for a in (u, v):
        hi = np.full(n, -np.inf)
        lo = np.full(n, np.inf)
        np.maximum.at(hi, comp, a)
        np.minimum.at(lo, comp, a)
        extent.append(hi - lo + VEHICLE_CELL_M)
    top = np.full(n, -np.inf)
    np.maximum.at(top, comp, h[idx])
    vehicle = (extent[0] >= VEHICLE_MIN_LENGTH_M) & (extent[0] <= max_length_m)
    vehicle &= extent[1] <= VEHICLE_MAX_WIDTH_M
    if max_height_m is not None:
        vehicle &= top <= max_height_m
    # an object cut short by something in front of it (a wall seen between parked cars, a facade behind
    # a pole) is longer than it looks: one whose end, seen from the sensor, meets a nearer object is kept
    az = np.arctan2(xy[:, 1], xy[:, 0])
    rng_xy = np.hypot(xy[:, 0], xy[:, 1])
    bins = int(round(2.0 * np.pi / VEHICLE_AZIMUTH_BIN))
    b = np.floor((az + np.pi) / VEHICLE_AZIMUTH_BIN).astype(np.int64) % bins
    nearest = np.full(bins, np.inf)
    np.minimum.at(nearest, b, rng_xy)
    # ... and so is an object seen up to more than a car's height that reaches the sensor's top beam: its
    # top is unseen (a wall or a facade near the sensor; a car there is seen over). The elevations are
    # needed only when such a tall object is among the candidates.
    top_beam = elevation = None
    if (vehicle & (top > VEHICLE_CUT_TOP_M)).any():
        top_beam = top_elevation(p)
        elevation = np.arctan2(p[idx, 2], rng_xy)
    # each object's points, in their order, as one slice of a stable sort by object
    order = np.argsort(comp, kind="stable")
    start = np.concatenate([[0], np.cumsum(count).astype(np.int64)])
    for k in np.flatnonzero(vehicle):
        mine = order[start[k] : start[k + 1]]
        if top[k] > VEHICLE_CUT_TOP_M and elevation[mine].max() > top_beam - VEHICLE_TOP_BEAM_MARGIN:
            vehicle[k] = False
            continue
        rel = np.angle(np.exp(1j * (az[mine] - np.angle(np.exp(1j * az[mine]).mean()))))
        for end, sign in ((rel.argmin(), -1), (rel.argmax(), 1)):
            at = b[mine][end]
            beyond = nearest[(at + sign * np.arange(1, 3)) % bins]
            if (beyond < rng_xy[mine][end] - VEHICLE_OCCLUDER_M).any():
                vehicle[k] = False
    out[idx] = vehicle[comp]
    return out


def select_rays(
    points: np.ndarray,
    rng: np.random.Generator,
    *,
    rays: int,
    sampling: str,
    ground_share: float,
    tall_share: float,
    tall_m: float,
    min_range_m: float,
    max_range_m: float,
    deskew: bool,
    level_with_imu: bool,
    vehicle_length_m: float | None,
    movable_height_m: float | None,
    fire_time_s: np.ndarray | None = None,
    frame_period_s: float | None = None,
    frame_motion: np.ndarray | None = None,
    roll_pitch: tuple[float, float] | None = None,
    sensor_height_m: float = 1.73,
) -> ScanRays | None:
    """Pick, de-skew and level ``rays`` rays of one scan ``(M, 3)``; ``None`` when it has no valid point
    (finite, within ``min_range_m`` … ``max_range_m``).

    ``fire_time_s`` are the points' firing times relative to the scan's stamp (<= 0), ``frame_motion`` the
    odometry motion ``(dx, dy, dyaw)`` over the frame period that ends at the stamp (in the previous
    frame's pose), assumed uniform: a point fired at time ``t`` is moved by the part of that motion that
    happened after ``t``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    r = row_norms(p)
    ok = np.isfinite(r) & (r >= min_range_m) & (r <= max_range_m)
    valid = int(ok.sum())
    if vehicle_length_m is not None and valid:
        q0 = (
            p[ok] @ rotation_roll_pitch(*roll_pitch).T if level_with_imu and roll_pitch is not None else p[ok]
        )
        ok[np.flatnonzero(ok)[vehicle_points(q0, sensor_height_m, vehicle_length_m, movable_height_m)]] = (
            False
        )
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    if len(idx) > rays:
        weight = None
        if sampling in ("elevation", "structure"):
            every = len(idx) == len(p)  # (most scans: no copy of every point)
            weight = _band_weights(
                p if every else p[idx],
                r if every else r[idx],
                sampling,
                ground_share,
                tall_share,
                tall_m,
                sensor_height_m,
            )
            drawable = int(np.count_nonzero(weight))
            if drawable < rays:  # a part with no share holds the rest: they fill the draw, least likely
                weight = np.where(weight > 0, weight, weight[weight > 0].min() * 1e-6)
                weight /= weight.sum()
        # sorted: the rays keep sweep order, which keeps them coherent in memory
        idx = np.sort(rng.choice(idx, rays, replace=False, p=weight))
    q = p[idx]
    if (
        deskew
        and fire_time_s is not None
        and frame_motion is not None
        and frame_period_s is not None
        and frame_period_s > 0
    ):
        t = np.asarray(fire_time_s, np.float64).reshape(-1)[idx]
        # pose at firing time relative to the stamp's pose: the remaining share of the frame's motion, undone
        share = np.clip(-t / frame_period_s, 0.0, 1.0)  # 0 at the stamp, 1 a whole period before it
        end = np.asarray(frame_motion, np.float64)  # stamp pose in the previous frame's pose
        at = np.stack([(1 - share) * end[0], (1 - share) * end[1], (1 - share) * end[2]], axis=1)
        rel = se2_between(np.broadcast_to(end, at.shape), at)  # firing pose in the stamp's frame
        c, s = np.cos(rel[:, 2]), np.sin(rel[:, 2])
        q = np.stack(
            [c * q[:, 0] - s * q[:, 1] + rel[:, 0], s * q[:, 0] + c * q[:, 1] + rel[:, 1], q[:, 2]], axis=1
        )
    if level_with_imu and roll_pitch is not None:
        q = q @ rotation_roll_pitch(*roll_pitch).T
    rng_ = row_norms(q)
    structure = q[:, 2] + sensor_height_m > STRUCTURE_M  # after levelling: height above the ground
    return ScanRays(q / rng_[:, None], rng_, valid, structure, float(sensor_height_m))
