"""Ground labels of one scan (paper, map building): ``n · e3 > cos 30°`` and ``z < z_thres``.

``e3`` is the unit eigenvector of the smallest eigenvalue of the covariance of the scan's points, i.e.
the normal of the plane that fits them best, which on a road is the ground plane's normal. Heights are
measured along ``e3``, so a tilted sensor (roll, pitch) still splits ground from the rest.
"""

from __future__ import annotations

import numpy as np

from rangemcl.errors import InputError

_UP = np.array([0.0, 0.0, 1.0])


def _points(points, name: str = "points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.size == 0:
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {p.shape}")
    return p


def _plane_normal(p: np.ndarray) -> np.ndarray | None:
    """Smallest-eigenvalue eigenvector of the covariance of ``p``; ``None`` when the points are collinear."""
    centred = p - p.mean(axis=0)
    cov = centred.T @ centred / len(p)
    values, vectors = np.linalg.eigh(cov)
    if not values[1] > 1e-12 * max(values[2], 1e-300):
        return None
    return vectors[:, 0]


def ground_normal(
    points,
    normals=None,
    valid=None,
    *,
    max_tilt_deg: float = 45.0,
    min_points: int = 10,
) -> np.ndarray:
    """``e3`` of one scan (sensor frame), a unit ``(3,)`` vector pointing up (``e3_z > 0``).

    Which points enter the covariance:

    * ``normals`` given (oriented toward the sensor, as :func:`~rangemcl.mapping.normals.scan_normals`
      gives them): only points with a valid normal within ``max_tilt_deg`` of +z, i.e. surfaces below
      the sensor that face up (ground, kerbs, car bonnets); walls, poles and ceilings do not pull e3
      sideways. Without normals: all finite points (the paper's choice).
    * ``valid`` (``(N,)`` bool, e.g. the normals' validity) restricts the points in both cases.

    The plane is fitted twice: once to those points, then again to the half of them closest to the first
    plane, which drops car roofs and other raised parts. The result falls back to +z when fewer than
    ``min_points`` points are left, when they are collinear, or when the fitted axis is more than
    ``max_tilt_deg`` from +z (in a street canyon, for example, the smallest spread of a whole scan can be
    across the street).
    """
    p = _points(points)
    use = np.isfinite(p).all(axis=1)
    if valid is not None:
        v = np.asarray(valid, dtype=bool).reshape(-1)
        if v.shape != (len(p),):
            raise InputError(f"valid: expected shape ({len(p)},), got {v.shape}")
        use &= v
    cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
    if normals is not None:
        n = _points(normals, "normals")
        if n.shape != p.shape:
            raise InputError(f"normals: expected shape {p.shape}, got {n.shape}")
        with np.errstate(invalid="ignore"):
            use &= np.isfinite(n).all(axis=1) & (n[:, 2] >= cos_tilt * np.linalg.norm(n, axis=1))
    p = p[use]
    if len(p) < max(min_points, 3):
        return _UP.copy()
    e3 = _plane_normal(p)
    if e3 is None:
        return _UP.copy()
    distance = np.abs((p - p.mean(axis=0)) @ e3)
    near = p[distance <= np.median(distance)]
    if len(near) >= max(min_points, 3):
        refined = _plane_normal(near)
        if refined is not None:
            e3 = refined
    e3 = e3 / np.linalg.norm(e3)
    if e3[2] < 0:
        e3 = -e3
    if e3[2] < cos_tilt:
        return _UP.copy()
    return e3


def label_ground(
    points,
    normals,
    valid,
    *,
    sensor_height_m: float,
    max_angle_deg: float = 30.0,
    z_margin_m: float = 1.0,
    e3=None,
) -> np.ndarray:
    """Ground flags ``(N,)`` bool for the points of one scan (sensor frame).

    A point is ground when its normal is valid, ``|n · e3| > cos(max_angle_deg)`` (the absolute value
    makes the test indifferent to how normals are oriented; for normals oriented toward a sensor above
    the ground it is the paper's ``n · e3 > cos 30°``), and its height along ``e3`` is below
    ``z_thres = −sensor_height_m + z_margin_m`` (the ground lies ``sensor_height_m`` below the sensor).
    ``e3`` defaults to :func:`ground_normal` of the scan with its normals. Empty scans, non-finite points
    and invalid normals give False.
    """
    p = _points(points)
    n = _points(normals, "normals")
    if n.shape != p.shape:
        raise InputError(f"normals: expected shape {p.shape}, got {n.shape}")
    ok = np.asarray(valid, dtype=bool).reshape(-1)
    if ok.shape != (len(p),):
        raise InputError(f"valid: expected shape ({len(p)},), got {ok.shape}")
    if not np.isfinite(sensor_height_m):
        raise InputError(f"sensor_height_m must be finite, got {sensor_height_m!r}")
    if len(p) == 0 or not ok.any():
        return np.zeros(len(p), bool)
    if e3 is None:
        e3 = ground_normal(p, n, ok)
    e3 = np.asarray(e3, dtype=np.float64).reshape(-1)
    length = np.linalg.norm(e3) if e3.shape == (3,) else 0.0
    if not (np.isfinite(length) and length > 0):
        raise InputError(f"e3: expected a non-zero finite 3-vector, got {e3!r}")
    e3 = e3 / length
    z_thres = -float(sensor_height_m) + float(z_margin_m)
    with np.errstate(invalid="ignore"):
        aligned = np.abs(n @ e3) > np.cos(np.deg2rad(max_angle_deg))
        low = p @ e3 < z_thres
    return ok & aligned & low & np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
