"""A byte budget over a map's tiles (issue 17): which tiles are in memory, and which go first.

:class:`TileCache` holds what a ``prepare`` function makes of each tile read from a
:class:`~rangemcl.mapping.store.TileStore` (by default the tile's arrays; the localizer's will be a Warp
mesh), with its size in bytes, and never more than ``budget_bytes`` in all. :meth:`TileCache.request`
takes focus points (the estimate, or each hypothesis cluster's centre) and a radius (the sensor's maximum
range): the tiles whose box lies within the radius of a focus are wanted, nearest first; tiles no longer
wanted are evicted farthest first to make room, and wanted tiles that do not fit are left out, farthest
first, and reported (the caller falls back on a coarse level or goes without them, and says so).

Pure Python and numpy; single-threaded (a background loader calls it from one thread).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rangemcl.mapping.store import TileStore


def tile_distances(store: TileStore, focus_xy) -> np.ndarray:
    """``(T,)`` distance in x, y from each tile's box (its mesh's bounds) to the nearest focus point (0 for a
    focus inside the box)."""
    b = np.array([e.bounds for e in store.entries], np.float64)  # (T, 6)
    f = np.asarray(focus_xy, np.float64).reshape(-1, 2)
    dx = np.maximum(0.0, np.maximum(b[:, None, 0] - f[None, :, 0], f[None, :, 0] - b[:, None, 3]))
    dy = np.maximum(0.0, np.maximum(b[:, None, 1] - f[None, :, 1], f[None, :, 1] - b[:, None, 4]))
    return np.hypot(dx, dy).min(axis=1)


def caster_tiles(caster, bytes_per_triangle: float = 62.0, bytes_per_vertex: float = 12.0):
    """``(prepare, release)`` for a :class:`TileCache` whose tiles live as meshes of ``caster``: a tile's
    item is its mesh handle, its size the BVH's estimate (about 62 bytes a triangle with Warp's BVH and
    the float32 vertices, measured on ``town_large``'s tiles: ``docs/design/issue17_notes.md``)."""

    def prepare(v, f, g):
        handle = caster.add_mesh(v, f, name="tile")
        return handle, int(bytes_per_triangle * len(f) + bytes_per_vertex * len(v))

    return prepare, caster.remove_mesh


def array_bytes(v: np.ndarray, f: np.ndarray, g: np.ndarray) -> tuple[Any, int]:
    """The default ``prepare``: keep the tile's arrays; their bytes."""
    return (v, f, g), int(v.nbytes + f.nbytes + g.nbytes)


@dataclass
class Request:
    """What one :meth:`TileCache.request` did."""

    wanted: list[int]  # tiles within the radius, nearest first
    held: list[int]  # ... of them in memory now
    left_out: list[int]  # ... of them that did not fit the budget (farthest first)
    loaded: list[int] = field(default_factory=list)  # read at this request
    evicted: list[int] = field(default_factory=list)  # dropped at this request, in order


class TileCache:
    """Tiles in memory within a byte budget (module docstring).

    Args:
        store: the map's tiles.
        budget_bytes: the most the cache holds, as ``prepare`` counts it.
        prepare: ``(vertices, faces, is_ground) -> (item, nbytes)``; default :func:`array_bytes`.
        read: ``(store, k) -> (vertices, faces, is_ground)``; default ``store.read(k)`` (tests slow it).
        release: called with a tile's item when it is evicted (e.g. to take its mesh out of a
            :class:`~rangemcl.raycast.RayCaster`: :func:`caster_tiles`).
    """

    def __init__(
        self,
        store: TileStore,
        budget_bytes: int,
        *,
        prepare: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[Any, int]] = array_bytes,
        read: Callable[[TileStore, int], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
        release: Callable[[Any], None] | None = None,
    ):
        if budget_bytes <= 0:
            raise ValueError(f"budget_bytes must be positive, got {budget_bytes}")
        self.store = store
        self.budget_bytes = int(budget_bytes)
        self.prepare = prepare
        self.read = read or (lambda s, k: s.read(k))
        self.release = release
        self.items: dict[int, tuple[Any, int]] = {}  # tile index -> (item, bytes)
        self.peak_bytes = 0

    @property
    def nbytes(self) -> int:
        return sum(n for _item, n in self.items.values())

    def get(self, k: int):
        """The prepared item of tile ``k`` if held, else None."""
        it = self.items.get(k)
        return None if it is None else it[0]

    def request(self, focus_xy, radius_m: float) -> Request:
        """Hold the tiles within ``radius_m`` of the focus points, nearest first, within the budget: room
        for a tile is made by evicting, farthest first, the tiles no longer wanted and then the wanted
        ones farther than it; a tile that still does not fit is left out."""
        dist = tile_distances(self.store, focus_xy)
        wanted = [int(k) for k in np.argsort(dist, kind="stable") if dist[k] <= radius_m]
        want = set(wanted)
        out = Request(wanted=wanted, held=[], left_out=[])
        for k in wanted:
            if k in out.evicted:  # made room for a nearer tile at this request: not read again
                out.left_out.append(k)
                continue
            if k in self.items:
                out.held.append(k)
                continue
            v, f, g = self.read(self.store, k)
            item, size = self.prepare(v, f, g)
            del v, f, g
            # farthest first: tiles not wanted, then wanted tiles farther than this one
            spare = sorted(
                (j for j in self.items if j not in want or dist[j] > dist[k]),
                key=lambda j: (j in want, -dist[j]),
            )
            while self.nbytes + size > self.budget_bytes and spare:
                gone = spare.pop(0)
                item_gone, _n = self.items.pop(gone)
                if self.release is not None:
                    self.release(item_gone)
                out.evicted.append(gone)
                if gone in out.held:
                    out.held.remove(gone)
                    out.left_out.append(gone)
            if self.nbytes + size > self.budget_bytes:
                out.left_out.append(k)
                continue
            self.items[k] = (item, size)
            out.loaded.append(k)
            out.held.append(k)
            self.peak_bytes = max(self.peak_bytes, self.nbytes)
        return out
