"""A byte budget over a map's tiles (issue 17): which tiles are in memory, which go first, and a loader
that works in the background.

:class:`TileCache` holds what a :class:`TileKind` makes of each tile of a
:class:`~rangemcl.mapping.store.TileStore` (by default the tile's arrays; the localizer's are Warp meshes
in its ray caster, :func:`caster_tiles`), never more than ``budget_bytes`` in all. A tile's size is known
from the index before it is read, so room is made before a tile is loaded and a tile being loaded counts
against the budget. :meth:`TileCache.request` takes focus points (the estimate, or each hypothesis
cluster's centre) and a radius (the sensor's maximum range): the tiles whose box lies within the radius
of a focus are wanted, nearest first, and those within ``radius + prefetch`` are loaded ahead; tiles no
longer wanted are evicted farthest first to make room, and wanted tiles that do not fit are left out and
reported (the caller goes without them and says so).

With ``background=True`` tiles are read and prepared (file, checksum, inflation, BVH build) in a worker
thread: a request starts the loads it needs and returns at once with what is held, the tiles still
loading reported as left out, unless it is told to ``wait`` (the first request of a run, or a search
that must not score particles against missing tiles). Loaded tiles enter the cache (``install``, e.g.
into the ray caster's scene) only inside :meth:`TileCache.request`, on the caller's thread, so the scene
never changes while the caller casts rays.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rangemcl.errors import InputError
from rangemcl.mapping.store import TileEntry, TileStore


def tile_distances(store: TileStore, focus_xy) -> np.ndarray:
    """``(T,)`` distance in x, y from each tile's box (its mesh's bounds) to the nearest focus point (0 for a
    focus inside the box)."""
    b = np.array([e.bounds for e in store.entries], np.float64)  # (T, 6)
    f = np.asarray(focus_xy, np.float64).reshape(-1, 2)
    dx = np.maximum(0.0, np.maximum(b[:, None, 0] - f[None, :, 0], f[None, :, 0] - b[:, None, 3]))
    dy = np.maximum(0.0, np.maximum(b[:, None, 1] - f[None, :, 1], f[None, :, 1] - b[:, None, 4]))
    return np.hypot(dx, dy).min(axis=1)


@dataclass(frozen=True)
class TileKind:
    """How a cache holds a tile.

    ``size_of(entry)``: its bytes, from the index alone; ``prepare(vertices, faces, is_ground)``: the item,
    on any thread; ``install(item)``: what the cache holds, on the requesting thread; ``release(held)``:
    called when the tile is evicted."""

    size_of: Callable[[TileEntry], int]
    prepare: Callable[[np.ndarray, np.ndarray, np.ndarray], Any]
    install: Callable[[Any], Any] = lambda item: item
    release: Callable[[Any], None] | None = None


def tile_arrays() -> TileKind:
    """The default kind: a tile's arrays as the store reads them (float64 vertices, int32 faces, bool
    ground flags)."""
    return TileKind(
        size_of=lambda e: 25 * e.vertices + 12 * e.triangles,
        prepare=lambda v, f, g: (v, f, g),
    )


def caster_tiles(caster, bytes_per_triangle: float = 62.0, bytes_per_vertex: float = 12.0) -> TileKind:
    """Tiles that live as meshes of ``caster`` (a :class:`~rangemcl.raycast.RayCaster`): the BVH is built
    by ``prepare`` (the loader thread), the mesh enters the scene at ``install`` and leaves it at
    ``release``; a tile's size is the BVH's estimate, about 62 bytes a triangle with Warp's BVH and the
    float32 vertices (measured on ``town_large``'s tiles: ``docs/design/issue17_notes.md``)."""
    return TileKind(
        size_of=lambda e: int(bytes_per_triangle * e.triangles + bytes_per_vertex * e.vertices),
        prepare=lambda v, f, g: caster.build_mesh(v, f, name="tile"),
        install=caster.insert_mesh,
        release=caster.remove_mesh,
    )


@dataclass
class Request:
    """What one :meth:`TileCache.request` did."""

    wanted: list[int]  # tiles within the radius, nearest first
    held: list[int]  # ... of them in memory now
    left_out: list[int]  # ... of them not held: no room in the budget, still loading, or broken
    loading: list[int] = field(default_factory=list)  # tiles (wanted or ahead) the loader is working on
    loaded: list[int] = field(default_factory=list)  # entered the cache at this request
    evicted: list[int] = field(default_factory=list)  # dropped at this request, in order
    broken: list[int] = field(default_factory=list)  # found unreadable at this request (see TileCache.broken)
    wait_ms: float = 0.0  # how long this request waited for tiles to load


class TileCache:
    """Tiles in memory within a byte budget (module docstring).

    Args:
        store: the map's tiles.
        budget_bytes: the most the cache holds and loads at once, as ``kind.size_of`` counts it.
        kind: how a tile is held (:class:`TileKind`); default :func:`tile_arrays`.
        read: ``(store, k) -> (vertices, faces, is_ground)``; default ``store.read(k)`` (tests slow it).
        background: load in a worker thread (module docstring).
    """

    def __init__(
        self,
        store: TileStore,
        budget_bytes: int,
        *,
        kind: TileKind | None = None,
        read: Callable[[TileStore, int], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
        background: bool = False,
    ):
        if budget_bytes <= 0:
            raise ValueError(f"budget_bytes must be positive, got {budget_bytes}")
        self.store = store
        self.budget_bytes = int(budget_bytes)
        self.kind = kind or tile_arrays()
        self.read = read or (lambda s, k: s.read(k))
        self.sizes = [int(self.kind.size_of(e)) for e in store.entries]
        self.items: dict[int, Any] = {}  # tile index -> held item
        self.broken: dict[int, str] = {}  # tile index -> the error line; never read again
        self.peak_bytes = 0
        self._loading: dict[int, Future] = {}
        self._dropped: list[tuple[int, Future]] = []  # evicted while loading: their bytes count until done
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="tiles") if background else None

    @property
    def nbytes(self) -> int:
        """Bytes of the tiles held."""
        return sum(self.sizes[k] for k in self.items)

    @property
    def reserved_bytes(self) -> int:
        """Bytes of the tiles held and of those being loaded (what the budget bounds)."""
        self._dropped = [(k, fu) for k, fu in self._dropped if not fu.done()]
        return (
            self.nbytes
            + sum(self.sizes[k] for k in self._loading)
            + sum(self.sizes[k] for k, _ in self._dropped)
        )

    def get(self, k: int):
        """The held item of tile ``k``, else None."""
        return self.items.get(k)

    def _load(self, k: int):
        v, f, g = self.read(self.store, k)
        return self.kind.prepare(v, f, g)

    def _start(self, k: int, out: Request) -> None:
        if self._pool is None:
            fu: Future = Future()
            t0 = time.perf_counter()
            try:
                fu.set_result(self._load(k))
            except InputError as e:
                fu.set_exception(e)
            out.wait_ms += (time.perf_counter() - t0) * 1e3
        else:
            fu = self._pool.submit(self._load, k)
        self._loading[k] = fu
        self.peak_bytes = max(self.peak_bytes, self.reserved_bytes)

    def _evict(self, k: int, out: Request) -> None:
        if k in self.items:
            held = self.items.pop(k)
            if self.kind.release is not None:
                self.kind.release(held)
        else:
            fu = self._loading.pop(k)
            if not fu.cancel():
                self._dropped.append((k, fu))
        out.evicted.append(k)

    def _harvest(self, out: Request) -> None:
        """Loads that have finished enter the cache (on this thread)."""
        for k in [k for k, fu in self._loading.items() if fu.done()]:
            fu = self._loading.pop(k)
            try:
                item = fu.result()
            except InputError as e:
                self.broken[k] = str(e)
                out.broken.append(k)
                continue
            self.items[k] = self.kind.install(item)
            out.loaded.append(k)

    def request(self, focus_xy, radius_m: float, *, prefetch_m: float = 0.0, wait: bool = True) -> Request:
        """Hold the tiles within ``radius_m`` of the focus points and load those within ``radius_m +
        prefetch_m``, nearest first, within the budget: room for a tile is made by evicting, farthest first,
        the tiles no longer wanted and then the wanted ones farther than it; a tile that still does not fit
        is left out. In the background, ``wait`` blocks until the wanted tiles' loads have finished."""
        out = Request(wanted=[], held=[], left_out=[])
        self._harvest(out)
        dist = tile_distances(self.store, focus_xy)
        order = np.argsort(dist, kind="stable")
        ahead = [int(k) for k in order if dist[k] <= radius_m + prefetch_m and int(k) not in self.broken]
        want = set(ahead)
        out.wanted = [k for k in (int(k) for k in order) if dist[k] <= radius_m]
        for k in ahead:
            if k in self.items or k in self._loading or k in out.evicted:
                continue
            spare = sorted(
                (j for j in [*self.items, *self._loading] if j not in want or dist[j] > dist[k]),
                key=lambda j: (j in want, -dist[j]),
            )
            while self.reserved_bytes + self.sizes[k] > self.budget_bytes and spare:
                self._evict(spare.pop(0), out)
            if self.reserved_bytes + self.sizes[k] <= self.budget_bytes:
                self._start(k, out)
        pending = [self._loading[k] for k in out.wanted if k in self._loading]
        if pending and wait and self._pool is not None:
            t0 = time.perf_counter()
            wait_futures(pending)
            out.wait_ms += (time.perf_counter() - t0) * 1e3
        self._harvest(out)
        out.held = [k for k in out.wanted if k in self.items]
        out.left_out = [k for k in out.wanted if k not in self.items]
        out.loading = sorted(self._loading)
        return out

    def close(self) -> None:
        """Stop the loader (loads not started are cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
