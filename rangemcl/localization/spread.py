"""Where global localization puts its particles before any scan has spoken: the drivable area.

:func:`drivable_cells` gives the map's measured ground cells, and, for a map that keeps its mapping drive
(``drive_xy``), only those within ``drive_radius_m`` of it, with the drive's heading there.
:func:`uniform_particles` spreads particles over them: yaw along the drive (either way, within
``heading_sigma``) with a share of uniform yaw, or uniform yaw without a drive. The place prior
(:mod:`rangemcl.localization.place_prior`) then redraws a share of them where the scan fits.

Pure numpy and scipy; all randomness from the generator handed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError
from rangemcl.se2 import wrap_angle


@dataclass
class DrivableArea:
    """Lower-left corners ``(K, 2)`` of square cells of ``cell_m``, and the mapping drive's heading near
    each cell (None without a drive)."""

    corners: np.ndarray
    cell_m: float
    headings: np.ndarray | None


def drivable_cells(mesh_map, drive_radius_m: float) -> DrivableArea:
    """The map's measured ground cells, and of those only the ones within ``drive_radius_m`` of the
    mapping drive when the map keeps its drive (``drive_xy``), with the drive's heading there."""
    g = mesh_map.ground
    j, i = np.nonzero(g.measured)
    if len(i) == 0:
        raise InputError("map: no ground cell was measured, so there is no area to spread particles over")
    corners = g.origin_xy + np.column_stack([i, j]) * g.cell_m
    drive = mesh_map.drive_xy
    if drive is None or len(drive) < 2 or drive_radius_m <= 0:
        return DrivableArea(corners, float(g.cell_m), None)
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(drive).query(corners + 0.5 * g.cell_m)
    near = dist <= drive_radius_m
    if not near.any():
        return DrivableArea(corners, float(g.cell_m), None)
    step = np.diff(drive, axis=0)
    seg_heading = np.arctan2(step[:, 1], step[:, 0])
    heading = seg_heading[np.minimum(nearest[near], len(seg_heading) - 1)]
    return DrivableArea(corners[near], float(g.cell_m), heading)


def uniform_particles(
    area: DrivableArea,
    n: int,
    rng: np.random.Generator,
    *,
    uniform_yaw_share: float,
    heading_sigma_rad: float,
) -> np.ndarray:
    """``n`` particles ``(x, y, yaw)`` uniform over the area's cells; where the area has the drive's
    headings, all but ``uniform_yaw_share`` of them face along it (either way)."""
    k = rng.integers(0, len(area.corners), n)
    xy = area.corners[k] + rng.uniform(0.0, area.cell_m, (n, 2))
    yaw = rng.uniform(-np.pi, np.pi, n)
    if area.headings is not None:
        along = rng.uniform(0.0, 1.0, n) >= uniform_yaw_share
        m = int(along.sum())
        yaw[along] = wrap_angle(
            area.headings[k[along]] + np.pi * rng.integers(0, 2, m) + rng.normal(0.0, heading_sigma_rad, m)
        )
    return np.column_stack([xy, yaw])
