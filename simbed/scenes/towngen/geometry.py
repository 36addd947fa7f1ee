"""Ground-plane geometry the generator places things with (oriented rectangles, their distances to road
segments, an :class:`Occupancy` hash of placed footprints), and the pieces of a town that the MJCF writer
writes (:class:`Box`, :class:`Pole`, :class:`Tree`, :class:`ParkedCar`)."""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def rect_corners(center, yaw: float, half) -> np.ndarray:
    """The (4, 2) corners of the rectangle of half sides ``half`` about ``center``, turned by ``yaw``."""
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * np.asarray(half, float)
    return local @ _rot(yaw).T + np.asarray(center, float)


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between points p (..., 2) and segments a-b (..., 2), broadcast."""
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def rect_segment_distance(center, yaw: float, half, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance between an oriented rectangle and each segment a[i]-b[i] (0 where they intersect)."""
    center = np.asarray(center, float)
    hx, hy = (float(h) for h in half)
    R = _rot(yaw)
    la = (np.atleast_2d(a) - center) @ R  # world -> rectangle frame
    lb = (np.atleast_2d(b) - center) @ R
    # segment intersects the box? (Liang-Barsky clipping)
    d = lb - la
    t0 = np.zeros(len(la))
    t1 = np.ones(len(la))
    ok = np.ones(len(la), dtype=bool)
    for k, h in ((0, hx), (1, hy)):
        p = d[:, k]
        q0 = la[:, k]
        flat = np.abs(p) < 1e-12
        ok &= ~flat | (np.abs(q0) <= h)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-h - q0) / p
            tb = (h - q0) / p
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(flat, t1, np.minimum(t1, np.maximum(ta, tb)))
    hit = ok & (t0 <= t1)
    # otherwise: endpoints to the box, box corners to the segment
    h2 = np.array([hx, hy])
    d_end = np.minimum(
        np.linalg.norm(np.maximum(np.abs(la) - h2, 0.0), axis=1),
        np.linalg.norm(np.maximum(np.abs(lb) - h2, 0.0), axis=1),
    )
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    d_corner = point_segment_distance(corners[None, :, :], la[:, None, :], lb[:, None, :]).min(axis=1)
    return np.where(hit, 0.0, np.minimum(d_end, d_corner))


def _rects_overlap(c1, yaw1, half1, c2, yaw2, half2, margin: float) -> bool:
    """Whether two oriented rectangles come closer than ``margin`` (separating axis test, inflated)."""
    p1 = rect_corners(c1, yaw1, np.asarray(half1) + margin / 2)
    p2 = rect_corners(c2, yaw2, np.asarray(half2) + margin / 2)
    for yaw in (yaw1, yaw2):
        for axis in (np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])):
            s1, s2 = p1 @ axis, p2 @ axis
            if s1.max() < s2.min() or s2.max() < s1.min():
                return False
    return True


class Occupancy:
    """Placed footprints (oriented rectangles) in a spatial hash, for overlap tests."""

    def __init__(self, cell: float = 32.0):
        self.cell = cell
        self.items: list[tuple[np.ndarray, float, np.ndarray]] = []
        self.grid: dict[tuple[int, int], list[int]] = defaultdict(list)

    def _cells(self, center, radius: float):
        c = self.cell
        i0, i1 = math.floor((center[0] - radius) / c), math.floor((center[1] - radius) / c)
        j0, j1 = math.floor((center[0] + radius) / c), math.floor((center[1] + radius) / c)
        for i in range(i0, j0 + 1):
            for j in range(i1, j1 + 1):
                yield (i, j)

    def free(self, center, yaw: float, half, margin: float) -> bool:
        radius = float(np.hypot(*half)) + margin  # items are filed under every cell they touch
        seen: set[int] = set()
        for key in self._cells(center, radius):
            for k in self.grid.get(key, ()):
                if k in seen:
                    continue
                seen.add(k)
                c2, yaw2, half2 = self.items[k]
                if _rects_overlap(center, yaw, half, c2, yaw2, half2, margin):
                    return False
        return True

    def add(self, center, yaw: float, half) -> None:
        k = len(self.items)
        self.items.append((np.asarray(center, float), float(yaw), np.asarray(half, float)))
        for key in self._cells(center, float(np.hypot(*half))):
            self.grid[key].append(k)


# ------------------------------------------------------------------------------------- the pieces of a town


@dataclass
class Box:
    """A box geom (road, building part, wall): centre, half sizes, heading and pitch (radians), material."""

    name: str
    pos: tuple[float, float, float]
    size: tuple[float, float, float]  # half sizes
    yaw: float
    material: str
    pitch: float = 0.0


@dataclass
class Pole:
    """A pole (cylinder) standing at ``xy`` from ``z0`` (below the ground) up ``height``."""

    name: str
    xy: tuple[float, float]
    z0: float
    radius: float
    height: float


@dataclass
class Tree:
    """A tree at ``xy``: a trunk cylinder from ``z0`` (below the ground) and an ellipsoid crown."""

    name: str
    xy: tuple[float, float]
    z0: float
    trunk_r: float
    trunk_h: float
    crown: tuple[float, float, float]  # ellipsoid semi-axes
    crown_z: float  # crown centre height above z0


@dataclass
class ParkedCar:
    """A parked car: a static body at ``pos`` (on the ground) heading ``yaw``, its size and body colour."""

    name: str
    pos: tuple[float, float, float]
    yaw: float
    length: float
    width: float
    height: float
    rgba: tuple[float, float, float]
