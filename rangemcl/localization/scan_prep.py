"""Scan preparation for the localizer: which measured rays weigh the particles, de-skewed with the frame's
odometry and each point's firing time, levelled with the IMU's roll and pitch. Pure numpy; the rays'
randomness comes from the generator handed in.

Ray selection (``sampling``): ``points`` draws evenly over the valid points; ``elevation`` evenly over 2°
elevation bands (a sensor whose beams crowd the road near the car still sends rays farther and higher);
``structure`` gives the road (points within ``STRUCTURE_M`` of the sensor's ground) at most
``ground_share`` of the rays and what stands on it the rest, each part evenly over the elevation bands:
500 rays drawn evenly over an HDL-64E's points are mostly road, which fits almost anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.se2 import rotation_roll_pitch, se2_between

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


def select_rays(
    points: np.ndarray,
    rng: np.random.Generator,
    *,
    rays: int = 500,
    sampling: str = "structure",
    ground_share: float = 0.2,
    min_range_m: float = 2.0,
    max_range_m: float = 40.0,
    deskew: bool = True,
    level_with_imu: bool = True,
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
    r = np.linalg.norm(p, axis=1)
    ok = np.isfinite(r) & (r >= min_range_m) & (r <= max_range_m)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    if len(idx) > rays:
        weight = None
        if sampling in ("elevation", "structure"):
            key = np.floor(np.degrees(np.arcsin(p[idx, 2] / r[idx])) / ELEVATION_BAND_DEG).astype(np.int64)
            part = np.zeros(len(idx), np.int64)
            part_share = np.array([1.0, 0.0])
            if sampling == "structure":
                # height above the sensor's ground (levelled enough: a car's roll and pitch are small)
                part = (p[idx, 2] + sensor_height_m < STRUCTURE_M).astype(np.int64)  # 1: road
                if 0 < part.sum() < len(part):
                    part_share = np.array([1.0 - ground_share, ground_share])
                else:
                    part[:] = 0
            _, inverse, counts = np.unique(key * 2 + part, return_inverse=True, return_counts=True)
            group_part = np.zeros(len(counts), np.int64)
            group_part[inverse] = part
            groups_in_part = np.bincount(group_part, minlength=2)
            # each part its share, split evenly over its elevation bands, each band's points alike
            weight = part_share[part] / groups_in_part[part] / counts[inverse]
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
    rng_ = np.linalg.norm(q, axis=1)
    structure = q[:, 2] + sensor_height_m > STRUCTURE_M  # after levelling: height above the ground
    return ScanRays(q / rng_[:, None], rng_, int(ok.sum()), structure)
