"""A byte budget over a map's tiles: which tiles are in memory, which go first, and a loader
that works in the background.

:class:`TileCache` holds what a :class:`TileKind` makes of each tile of a
:class:`~rangemcl.maps.store.TileStore` (by default the tile's arrays; the localizer's are Warp meshes
in its ray caster, :func:`caster_tiles`), never more than ``budget_bytes`` in all. A tile's size is known
from the index before it is read, so room is made before a tile is loaded and a tile being loaded counts
against the budget. :meth:`TileCache.request` takes focus points (the estimate, or each hypothesis
cluster's centre) and a radius (the sensor's maximum range): the tiles whose box lies within the radius
of a focus are wanted, nearest first, and those within ``radius + prefetch`` are loaded ahead; tiles no
longer wanted are evicted farthest first to make room, and wanted tiles that do not fit are left out and
reported (the caller goes without them and says so). A request may also name ``extra_xy``, places to
look at without moving there (the lost detector's rival places): their tiles come last, in what the
wanted tiles and the prefetch ring leave of the budget, and are never waited for.

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

from rangemcl.common.heap import trim_freed_memory
from rangemcl.errors import InputError
from rangemcl.maps.store import TileEntry, TileStore


def tile_distances(store: TileStore, focus_xy, *, each: bool = False) -> np.ndarray:
    """``(T,)`` distance in x, y from each tile's box (its mesh's bounds) to the nearest focus point (0 for a
    focus inside the box); ``each``: ``(T, F)``, to every focus point."""
    b = np.array([e.bounds for e in store.entries], np.float64)  # (T, 6)
    f = np.asarray(focus_xy, np.float64).reshape(-1, 2)
    dx = np.maximum(0.0, np.maximum(b[:, None, 0] - f[None, :, 0], f[None, :, 0] - b[:, None, 3]))
    dy = np.maximum(0.0, np.maximum(b[:, None, 1] - f[None, :, 1], f[None, :, 1] - b[:, None, 4]))
    d = np.hypot(dx, dy)
    return d if each else d.min(axis=1)


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


TILE_LEAF_SIZE = 8  # triangles per BVH leaf of a tile held within a budget (RayCaster.build_mesh)


def caster_tiles(caster, bytes_per_triangle: float = 62.0, bytes_per_vertex: float = 12.0) -> TileKind:
    """Tiles that live as meshes of ``caster`` (a :class:`~rangemcl.raycast.RayCaster`): the BVH is built
    by ``prepare`` (the loader thread), the mesh enters the scene at ``install`` and leaves it at
    ``release``; a tile's size is what the process's resident memory grows by when it is loaded: about 62
    bytes a triangle (Warp's BVH with 8 triangles a leaf, the float32 vertices and the indices) and 12 a
    vertex, with the loader giving its temporaries back after each tile (:mod:`rangemcl.common.heap`;
    ``town_large``'s 60 tiles: 454 MB resident for 457 MB counted; ``docs/architecture.md``, "Design
    decisions and why")."""
    return TileKind(
        size_of=lambda e: int(bytes_per_triangle * e.triangles + bytes_per_vertex * e.vertices),
        prepare=lambda v, f, g: caster.build_mesh(v, f, name="tile", trim=True, leaf_size=TILE_LEAF_SIZE),
        install=caster.insert_mesh,
        release=caster.remove_mesh,
    )


FULL, COARSE = 0, 1  # a tile's levels
EXTRA_LOADS = 2  # loads of extra places' tiles (TileCache.request's extra_xy) in flight at once


@dataclass
class Request:
    """What one :meth:`TileCache.request` did."""

    wanted: list[int]  # tiles within the radius, nearest first
    held: list[int]  # ... of them in memory now (at either level)
    left_out: list[int]  # ... of them not held: no room in the budget, still loading, or broken
    coarse: list[int] = field(default_factory=list)  # ... of the held, those at the coarse level
    loading: list[int] = field(default_factory=list)  # tiles (wanted or ahead) the loader is working on
    loaded: list[int] = field(default_factory=list)  # entered the cache at this request
    evicted: list[int] = field(default_factory=list)  # dropped at this request, in order
    broken: list[int] = field(default_factory=list)  # found unreadable at this request (see TileCache.broken)
    wait_ms: float = 0.0  # how long this request waited for tiles to load
    extra: list[int] = field(default_factory=list)  # tiles within the radius of the extra places (not wanted)


class TileCache:
    """Tiles in memory within a byte budget (module docstring).

    Where the store has a coarse level (:mod:`rangemcl.maps.coarse`) and the wanted tiles do not all
    fit at full resolution, the farther ones are held at the coarse level: every wanted tile is given its
    coarse level first, then the nearest are raised to full resolution while the budget allows. Without a
    coarse level the wanted tiles are taken at full resolution nearest first while they fit.

    Args:
        store: the map's tiles.
        budget_bytes: the most the cache holds and loads at once, as ``kind.size_of`` counts it.
        kind: how a tile is held (:class:`TileKind`); default :func:`tile_arrays`.
        read: ``(store, k, coarse) -> (vertices, faces, is_ground)``; default ``store.read(k, coarse=...)``
            (tests slow it).
        background: load in a worker thread (module docstring).
        coarse: use the store's coarse level where the budget is short (when the store has one).
    """

    def __init__(
        self,
        store: TileStore,
        budget_bytes: int,
        *,
        kind: TileKind | None = None,
        read: Callable[[TileStore, int, bool], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
        background: bool = False,
        coarse: bool = True,
    ):
        if budget_bytes <= 0:
            raise ValueError(f"budget_bytes must be positive, got {budget_bytes}")
        self.store = store
        self.budget_bytes = int(budget_bytes)
        self.kind = kind or tile_arrays()
        self.read = read or (lambda s, k, c: s.read(k, coarse=c))
        self.use_coarse = bool(coarse and store.has_coarse)
        self.sizes = [
            (int(self.kind.size_of(e)), int(self.kind.size_of(e.coarse)) if self.use_coarse else None)
            for e in store.entries
        ]
        self.items: dict[int, Any] = {}  # tile index -> held item
        self.levels: dict[int, int] = {}  # tile index -> the level held
        self.broken: dict[int, str] = {}  # tile index -> the error line; never read again
        self.peak_bytes = 0
        self._loading: dict[int, tuple[int, Future]] = {}  # tile index -> (level, load)
        self._dropped: list[tuple[int, int, Future]] = []  # dropped while loading: bytes count until done
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="tiles") if background else None

    def size(self, k: int, level: int = FULL) -> int:
        return self.sizes[k][level]

    @property
    def nbytes(self) -> int:
        """Bytes of the tiles held."""
        return sum(self.sizes[k][lvl] for k, lvl in self.levels.items())

    @property
    def reserved_bytes(self) -> int:
        """Bytes of the tiles held and of those being loaded (what the budget bounds)."""
        self._dropped = [d for d in self._dropped if not d[2].done()]
        loading = sum(self.sizes[k][lvl] for k, (lvl, _fu) in self._loading.items())
        return self.nbytes + loading + sum(self.sizes[k][lvl] for k, lvl, _fu in self._dropped)

    def get(self, k: int):
        """The held item of tile ``k``, else None."""
        return self.items.get(k)

    def _load(self, k: int, level: int):
        v, f, g = self.read(self.store, k, level == COARSE)
        item = self.kind.prepare(v, f, g)
        del v, f, g
        trim_freed_memory()  # the tile's read arrays and temporaries: not under the next tile's BVH
        return item

    def _start(self, k: int, level: int, out: Request) -> None:
        if self._pool is None:
            fu: Future = Future()
            t0 = time.perf_counter()
            try:
                fu.set_result(self._load(k, level))
            except InputError as e:
                fu.set_exception(e)
            out.wait_ms += (time.perf_counter() - t0) * 1e3
        else:
            fu = self._pool.submit(self._load, k, level)
        self._loading[k] = (level, fu)
        self.peak_bytes = max(self.peak_bytes, self.reserved_bytes)

    def _release(self, k: int) -> None:
        held = self.items.pop(k)
        self.levels.pop(k)
        if self.kind.release is not None:
            self.kind.release(held)
        del held
        trim_freed_memory()

    def _evict(self, k: int, out: Request) -> None:
        if k in self.items:
            self._release(k)
        out.evicted.append(k)

    def _drop_load(self, k: int) -> None:
        level, fu = self._loading.pop(k)
        if not fu.cancel():
            self._dropped.append((k, level, fu))

    def _harvest(self, out: Request) -> None:
        """Loads that have finished enter the cache (on this thread); a tile raised to full resolution
        leaves its coarse level."""
        for k in [k for k, (_lvl, fu) in self._loading.items() if fu.done()]:
            level, fu = self._loading.pop(k)
            try:
                item = fu.result()
            except InputError as e:
                self.broken[k] = str(e)
                out.broken.append(k)
                continue
            if k in self.items:
                self._release(k)
            self.items[k] = self.kind.install(item)
            self.levels[k] = level
            out.loaded.append(k)

    def _plan(self, near: list[int], ahead: list[int], extra: list[int] = ()) -> dict[int, int]:
        """The level each tile should be held at: ``near`` (within the radius, nearest first) within the
        budget, then ``ahead`` (the prefetch ring) and ``extra`` (the extra places' tiles, in their order)
        in what is left, each at full resolution where it fits, else coarse."""
        target: dict[int, int] = {}
        left = self.budget_bytes
        if self.use_coarse:
            for k in near:  # every wanted tile at the coarse level, while they fit ...
                if self.size(k, COARSE) <= left:
                    target[k] = COARSE
                    left -= self.size(k, COARSE)
            for k in near:  # ... then the nearest raised to full resolution
                if k in target and self.size(k) - self.size(k, COARSE) <= left:
                    target[k] = FULL
                    left -= self.size(k) - self.size(k, COARSE)
        else:
            for k in near:
                if self.size(k) <= left:
                    target[k] = FULL
                    left -= self.size(k)
        for k in (*ahead, *extra):
            for level in (FULL, COARSE) if self.use_coarse else (FULL,):
                if self.size(k, level) <= left:
                    target[k] = level
                    left -= self.size(k, level)
                    break
        return target

    def request(
        self,
        focus_xy,
        radius_m: float,
        *,
        prefetch_m: float = 0.0,
        wait: bool = True,
        extra_xy=None,
    ) -> Request:
        """Hold the tiles within ``radius_m`` of the focus points and load those within ``radius_m +
        prefetch_m``, within the budget (the class docstring says at which level); tiles no longer wanted
        stay until their room is needed, then go farthest first, before the wanted tiles that the plan
        leaves out or holds at another level. In the background, ``wait`` blocks until the wanted tiles'
        loads have finished; a request also waits when it evicted a wanted tile to make room for a nearer
        one (a budget too small for the tiles in range) or holds none of the wanted tiles.

        ``extra_xy`` ``(E, 2)``, most important first: places whose tiles within ``radius_m`` are loaded
        in what is left of the budget after the wanted tiles and the prefetch ring, never waited for,
        and kept only while a request names them (``Request.extra``)."""
        out = Request(wanted=[], held=[], left_out=[])
        self._harvest(out)
        dist = tile_distances(self.store, focus_xy)
        order = [int(k) for k in np.argsort(dist, kind="stable")]
        out.wanted = [k for k in order if dist[k] <= radius_m]
        usable = [k for k in order if dist[k] <= radius_m + prefetch_m and k not in self.broken]
        extra: list[int] = []
        if extra_xy is not None and len(np.asarray(extra_xy).reshape(-1, 2)):
            taken = set(usable)
            per_place = tile_distances(self.store, extra_xy, each=True)  # (T, E)
            for d in per_place.T:
                for k in np.argsort(d, kind="stable"):
                    k = int(k)
                    if d[k] > radius_m:
                        break
                    if k not in taken and k not in self.broken:
                        taken.add(k)
                        extra.append(k)
        out.extra = extra
        target = self._plan(
            [k for k in usable if dist[k] <= radius_m], [k for k in usable if dist[k] > radius_m], extra
        )
        want = set(usable) | set(extra)
        for k in [k for k, (lvl, _fu) in self._loading.items() if target.get(k) != lvl]:
            self._drop_load(k)
        # loads nearest first, the extra places' tiles last and at most EXTRA_LOADS of them at a time (a
        # tile the car drives into never queues behind many of them); room is made by evicting what the
        # plan does not hold at its level, tiles no longer wanted first, farthest first (a coarse tile
        # waiting to be raised stays while it can)
        extras = set(extra)
        in_flight = sum(k in extras for k in self._loading)
        for k in [
            *sorted((j for j in target if j not in extras), key=lambda j: dist[j]),
            *(j for j in extra if j in target),
        ]:
            level = target[k]
            if self.levels.get(k) == level or (k in self._loading and self._loading[k][0] == level):
                continue
            if k in extras:
                if in_flight >= EXTRA_LOADS:
                    continue
                in_flight += 1
            spare = sorted(
                (j for j in self.items if j != k and target.get(j) != self.levels[j]),
                key=lambda j: (j in want, -dist[j]),
            )
            while self.reserved_bytes + self.size(k, level) > self.budget_bytes and spare:
                self._evict(spare.pop(0), out)
            if self.reserved_bytes + self.size(k, level) > self.budget_bytes and k in self.items:
                self._evict(k, out)  # no room to keep the coarse level while the full one loads
            if self.reserved_bytes + self.size(k, level) <= self.budget_bytes:
                self._start(k, level, out)
        # a wanted tile evicted for a nearer one, or none of the wanted held: waiting beats a frame
        # without them
        inside = set(out.wanted)
        wait = wait or any(k in inside for k in out.evicted) or not (inside & set(self.items))
        pending = [self._loading[k][1] for k in out.wanted if k in self._loading]
        if pending and wait and self._pool is not None:
            t0 = time.perf_counter()
            wait_futures(pending)
            out.wait_ms += (time.perf_counter() - t0) * 1e3
        self._harvest(out)
        out.held = [k for k in out.wanted if k in self.items]
        out.coarse = [k for k in out.held if self.levels[k] == COARSE]
        out.left_out = [k for k in out.wanted if k not in self.items]
        out.loading = sorted(self._loading)
        return out

    def close(self) -> None:
        """Stop the loader (loads not started are cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
