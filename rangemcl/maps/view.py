"""The localizer's view of a map within a memory budget (``rangemcl localize --map-memory MB``).

:class:`MapView` opens a map folder of format 2 by its index alone (:class:`~rangemcl.maps.store.
TileStore`) and keeps in the ray caster only the tiles near where the particles are, within a byte budget
(:class:`~rangemcl.maps.cache.TileCache`: a tile's BVH estimate, about 62 bytes a triangle). Before each
weighting the filter calls :meth:`MapView.update` with the particles' positions: every tile whose box
lies within ``radius_m`` (the observation's longest ray) of a particle is wanted, nearest first; tiles no
longer wanted leave the caster, farthest first, when room is needed; wanted tiles that do not fit are left
out and counted in the frame log (``map_left_out``). A ray that crosses a tile border hits the
neighbour tile exactly as it would hit the whole mesh, so while everything wanted fits, the filter's
results are those of the whole map (tested).

Tiles are read and their BVHs built in a background thread (:class:`~rangemcl.maps.cache.TileCache`
with ``background=True``) and enter the caster's scene only inside :meth:`MapView.update`, between two
weightings. The tiles within ``prefetch_m`` beyond the radius are loaded ahead, so that a car driving
into new tiles finds them loaded; while tracking (``wait=False``) an update never waits for a tile: a
tile still loading is left out of that update (``map_left_out``), and ``map_load_ms`` is 0. A search
(``wait=True``, and every first update) waits for the tiles its particles need, since a particle scored
against a missing tile would die for it. A broken tile file (missing, truncated, bad checksum) is one
line on stderr naming the file, and the run goes on without that tile.

Where the tiles in range do not all fit at full resolution and the map has a coarse level (``rangemcl
map-coarse``: each tile decimated to 5 %), the nearest tiles are held at full resolution and the farther
ones coarse (``map_coarse`` in the frame log); without one, the farther tiles are left out.

The lost detector's second opinion scores rival places anywhere in the map (the place prior's best
places for the scan): :meth:`MapView.consult` names them, their tiles are loaded in the background in
what the budget leaves after the particles' tiles and the prefetch ring (never waited for, never in the
way of a tile the car drives into), and a place is scored only once all its tiles in range are held, so
that it is scored as against the whole map (the places not yet scoreable are counted in the summary).

The likelihood-field model (a baseline) makes its surface voxels tile by tile for the tiles held
(:class:`rangemcl.localization.models.TiledLikelihoodFieldModel`), and they count against the budget as
well.

The ground grid, the mapping drive and the index stay whole (13 bytes per m² of map, 16 bytes a drive
point, a line per tile), and so do the place prior's profiles and the drivable area's cells: all of them
count against the budget (:meth:`MapView.reserve`), and the tiles get what is left. Before its first
frame the localizer checks the budget against all it needs (:meth:`MapView.check_budget`: what is held
besides the tiles, the place priors it may load later, and room for the largest tile at its smallest
level): a budget short of that is one error line with the total and its parts, not a failure frames later.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from rangemcl.common.heap import return_freed_memory
from rangemcl.errors import InputError
from rangemcl.maps.cache import TileCache, caster_tiles, tile_distances
from rangemcl.maps.meshmap import open_map_folder, read_ground_and_drive, tile_keys

# What the localizer holds of a whole map (MeshMap + one BVH) per triangle: town_large's 6.7 M triangles
# took 1.10 GB in `rangemcl localize` (docs/maps.md, "Large maps: --map-memory")
WHOLE_MAP_BYTES_PER_TRIANGLE = 165.0


def _mb(nbytes: int, up: bool = False) -> str:
    """``nbytes`` in MB to 3 significant digits (at most 4 decimals); ``up``: rounded up, so that
    ``--map-memory`` given the number it prints holds ``nbytes``."""
    x = nbytes / 1e6
    d = 0 if x >= 100 else 4 if x <= 0 else min(4, 2 - math.floor(math.log10(x)))
    if not up:
        return f"{x:.{d}f} MB"
    s = f"{math.ceil(x * 10**d) / 10**d:.{d}f}"
    while int(float(s) * 1e6) < nbytes:  # as MapView reads the budget
        s = f"{float(s) + 10**-d:.{d}f}"
    return f"{s} MB"


def available_memory_bytes() -> int:
    """The memory available to a new process (``MemAvailable``), else the physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def open_map(map_dir, memory_mb: float | None = None, *, device: str = "cpu", threads: int | None = None):
    """The map as the localizer holds it: ``(map, caster)``.

    ``memory_mb`` set: a :class:`MapView` within that budget and its own ray caster. None: the whole map
    (a :class:`~rangemcl.maps.meshmap.MeshMap`, caster None: the localizer builds one) when it takes
    under a quarter of the memory available (about 165 bytes a triangle), else a view within that quarter
    (a map of format 1 is then loaded whole all the same: ``rangemcl map-upgrade`` makes it tiles)."""
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.raycast import RayCaster

    map_dir = Path(map_dir)
    opened = open_map_folder(map_dir)  # map.yaml and the tile index, read once
    if memory_mb is None:
        version, _doc, store = opened
        quarter = available_memory_bytes() / 4
        if version < 2 or store.n_triangles * WHOLE_MAP_BYTES_PER_TRIANGLE <= quarter:
            return MeshMap.load(map_dir, opened=opened), None
        memory_mb = quarter / 1e6
    caster = RayCaster(device, threads)
    return MapView(map_dir, memory_mb, caster, opened=opened), caster


class MapView:
    """A map folder of format 2 seen through a memory budget (module docstring).

    Args:
        map_dir: the map folder.
        budget_mb: the most the held tiles may take (MB of BVH estimate).
        caster: the :class:`~rangemcl.raycast.RayCaster` the held tiles live in (tile meshes only).
        background: load tiles in a background thread (module docstring).
        prefetch_m: load the tiles this far beyond the update's radius ahead of need.
        coarse: where the tiles in range do not all fit, hold the farther ones at the map's coarse level
            (``rangemcl map-coarse``), if it has one.
    """

    budgeted = True  # the Map protocol (rangemcl.maps.meshmap.Map): held within a budget

    def __init__(
        self,
        map_dir,
        budget_mb: float,
        caster,
        *,
        background: bool = True,
        prefetch_m: float = 20.0,
        coarse: bool = True,
        opened: tuple | None = None,
    ):
        map_dir = Path(map_dir)
        version, doc, store = opened if opened is not None else open_map_folder(map_dir)
        if version < 2:
            raise InputError(
                f"{map_dir}: a map of format {version} is read whole; to bound its memory (--map-memory) "
                f"rewrite it as tiles first: rangemcl map-upgrade {map_dir}"
            )
        if not (np.isfinite(budget_mb) and budget_mb > 0):
            raise InputError(f"--map-memory must be a positive number of MB, got {budget_mb}")
        return_freed_memory()
        self.source_dir = map_dir
        self.format_version = version
        self.meta = doc["meta"]
        self.store = store
        self.ground, self.drive_xy = read_ground_and_drive(map_dir, doc)
        self.tiles = self.store.tiles
        self.tile_size_m = self.store.tile_size_m
        self.tile_origin_xy = self.store.origin_xy
        keys = tile_keys(self.tiles[:, 0], self.tiles[:, 1])
        self._key_order = np.argsort(keys)
        self._keys_sorted = keys[self._key_order]
        self.caster = caster
        self.budget_bytes = int(budget_mb * 1e6)
        self.cache = TileCache(
            self.store, self.budget_bytes, kind=caster_tiles(caster), background=background, coarse=coarse
        )
        self.derived: dict[str, int] = {}  # what else is held of the map, counted in the budget (reserve)
        self.expected: dict[str, int] = {}  # what the run may hold later, counted by check_budget
        self.checked = False  # check_budget passed: from then on a reserve that leaves nothing is an error
        ground = sum(a.nbytes for a in vars(self.ground).values() if isinstance(a, np.ndarray))
        self.reserve("ground grid", ground)
        if self.drive_xy is not None:
            self.reserve("mapping drive", self.drive_xy.nbytes)
        self.prefetch_m = float(prefetch_m)
        self.updates = 0
        self.longest_wait_ms = 0.0  # the longest an update waited for tiles
        self.startup_ms = 0.0  # the load before the first frame (preload)
        self.loads = 0  # tiles read over the run
        self.coarse_updates = 0  # updates at which a wanted tile was held at the coarse level
        self.left_out_updates = 0  # updates at which a wanted tile did not fit
        self._last: tuple[np.ndarray, float] | None = None  # the last update's focus points and radius
        self.in_range: list[int] = []  # the tiles within the last update's radius that are held
        self.last_wait = True
        self._extra_xy: np.ndarray | None = None  # places consulted (consult), kept for a few updates
        self._extra_left = 0
        self.consulted_places = 0  # places named to consult over the run ...
        self.unscored_places = 0  # ... of them not yet held when named

    # --- what the localizer reads of a map ------------------------------------------------------------

    @property
    def extent(self) -> tuple[float, float, float, float, float, float]:
        return self.store.extent()

    @property
    def n_triangles(self) -> int:
        return self.store.n_triangles

    def tile_at(self, x, y) -> np.ndarray:
        """Index into ``tiles`` of the tile holding each world ``x, y``; -1 outside every tile (as
        :meth:`MeshMap.tile_at`)."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        ok = np.isfinite(x) & np.isfinite(y)
        i = np.floor((np.where(ok, x, 0.0) - self.tile_origin_xy[0]) / self.tile_size_m)
        j = np.floor((np.where(ok, y, 0.0) - self.tile_origin_xy[1]) / self.tile_size_m)
        keys = tile_keys(i, j)
        pos = np.clip(np.searchsorted(self._keys_sorted, keys), 0, len(self._keys_sorted) - 1)
        found = ok & (self._keys_sorted[pos] == keys)
        return np.where(found, self._key_order[pos], -1).astype(np.int64)

    # --- the budget -----------------------------------------------------------------------------------

    def reserve(self, what: str, nbytes: int) -> None:
        """Count ``nbytes`` of something the localizer derives from the map and holds (the ground grid, the
        mapping drive, the place prior's profiles, the drivable area's cells) against the budget, under the
        name ``what`` (a second call with the same name replaces the first): the tiles get what is left.
        Call it before the tiles are loaded, or (an item that follows the tiles held, the likelihood
        field's voxels) between updates: the next update evicts what no longer fits. An error line when
        nothing is left for the tiles, saying what the run needs in all (:meth:`needed`); before
        :meth:`check_budget` (the localizer's, before its first frame) it waits for that check or for the
        first update, so that the line counts everything."""
        self.derived[what] = int(nbytes)
        left = self.budget_bytes - sum(self.derived.values())
        if left <= 0 and self.checked:
            raise self._too_small(self.needed())
        self.cache.budget_bytes = max(left, 0)

    def needed(self, tile: tuple[str, int] | None = None) -> dict[str, int]:
        """What the budget must hold, by name, in bytes: what is held besides the tiles (:meth:`reserve`),
        what the run may hold later (:meth:`check_budget`'s ``expected``: the place priors) and ``tile``
        (name, bytes), by default the largest tile at its smallest level (at the coarse level where the map
        has one): room for any one tile the particles may come to, so that an update never holds none of
        the tiles in range."""
        parts = dict(self.derived)
        parts.update({k: v for k, v in self.expected.items() if k not in parts})
        if tile is None and self.cache.sizes:
            full, coarse = max(self.cache.sizes, key=lambda fc: min(fc[0], fc[0] if fc[1] is None else fc[1]))
            if coarse is not None and coarse < full:
                tile = ("the largest tile (coarse level)", coarse)
            else:
                tile = ("the largest tile", full)
        if tile is not None:
            parts[tile[0]] = int(tile[1])
        return parts

    def check_budget(self, expected: dict[str, int] | None = None) -> None:
        """Before the first frame: one error line, saying the total and what it is made of, when the budget
        is smaller than what the run needs (:meth:`needed`, with ``expected``: name -> bytes of what the run
        may hold later, e.g. the place priors), instead of a failure frames later."""
        self.expected = {k: int(v) for k, v in (expected or {}).items()}
        parts = self.needed()
        if sum(parts.values()) > self.budget_bytes:
            raise self._too_small(parts)
        self.checked = True

    def _too_small(self, parts: dict[str, int], what: str = "is too small for this run") -> InputError:
        listed = ", ".join(f"{k} {_mb(v)}" for k, v in parts.items())
        return InputError(
            f"{self.source_dir}: --map-memory {self.budget_bytes / 1e6:g} MB {what}: it needs "
            f"{_mb(sum(parts.values()), up=True)} in all ({listed})"
            + ("" if self.cache.use_coarse else "; or add a coarse level: rangemcl map-coarse")
        )

    def update(self, xy: np.ndarray, radius_m: float, *, wait: bool = True, cell_m: float = 10.0) -> dict:
        """Hold the tiles within ``radius_m`` of the positions ``xy`` ``(N, 2)`` (reduced to one focus per
        ``cell_m`` cell) within the budget and load those ``prefetch_m`` farther; ``wait``: wait for the
        tiles within the radius that are still loading (else go without them). What it did, for the
        frame log."""
        if self.budget_bytes <= sum(self.derived.values()):  # nothing left for the tiles
            raise self._too_small(self.needed())
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]
        focus = (np.unique(np.floor(xy / cell_m), axis=0) + 0.5) * cell_m
        radius = radius_m + 0.75 * cell_m  # a focus stands for its cell
        self._last = (focus, radius)
        extra = self._extra_xy if self._extra_left > 0 else None
        self._extra_left = max(0, self._extra_left - 1)
        r = self.cache.request(
            focus,
            radius,
            prefetch_m=self.prefetch_m,
            wait=wait,  # the cache also waits while it holds none of the wanted tiles (the first update)
            extra_xy=extra,
        )
        if r.wanted and not self.cache.items and not r.loading:
            need = min(self.cache.sizes[k][1] or self.cache.sizes[k][0] for k in r.wanted)
            tile = ("the smallest tile in range" + (" (coarse level)" if self.cache.use_coarse else ""), need)
            raise self._too_small(self.needed(tile), "holds none of the tiles in range")
        self.in_range = list(r.held)  # the tiles within the radius held now (the likelihood field's)
        self.last_wait = bool(wait)  # ... and whether this update waited for them
        self.updates += 1
        self.loads += len(r.loaded)
        self.left_out_updates += bool(r.left_out)
        self.coarse_updates += bool(r.coarse)
        self.longest_wait_ms = max(self.longest_wait_ms, r.wait_ms)
        self._warn_broken(r)
        return dict(
            map_tiles=len(r.held),
            map_left_out=len(r.left_out),
            map_coarse=len(r.coarse),
            map_mb=self.cache.nbytes / 1e6,
            map_load_ms=r.wait_ms,
        )

    def _warn_broken(self, r) -> None:
        """One line on stderr for each tile found broken at a request (the run goes on without it)."""
        for k in r.broken:
            print(f"warning: {self.cache.broken[k]}; localizing without that tile", file=sys.stderr)

    def consult(self, xy: np.ndarray, *, keep_updates: int = 3) -> np.ndarray:
        """Places to look at without moving there, ``(E, 2)``, best first (the lost detector's rival
        places): their tiles within the last update's radius are loaded in the background in what the
        budget leaves after the particles' tiles and the prefetch ring, and stay wanted for the next
        ``keep_updates`` updates. Returns ``(E,)``: whether all of a place's tiles in range are held now
        (at either level), i.e. whether rays cast from it see what they would see in the whole map. Never
        waits."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if self._last is None or len(xy) == 0:
            return np.zeros(len(xy), bool)
        self._extra_xy, self._extra_left = xy.copy(), int(keep_updates)
        focus, radius = self._last
        r = self.cache.request(focus, radius, prefetch_m=self.prefetch_m, wait=False, extra_xy=xy)
        self.loads += len(r.loaded)
        self._warn_broken(r)
        near = tile_distances(self.store, xy, each=True) <= radius  # (T, E)
        held = np.zeros(len(self.store.entries), bool)
        held[list(self.cache.items)] = True
        held[list(self.cache.broken)] = True  # never to be held: scored without it, as the particles are
        ok = ~(near & ~held[:, None]).any(axis=0)
        self.consulted_places += len(xy)
        self.unscored_places += int((~ok).sum())
        return ok

    def preload(self, xy: np.ndarray, radius_m: float) -> None:
        """Before the first frame: load and hold the tiles for the positions ``xy`` as :meth:`update`
        would, waiting for them; the time goes to ``startup_ms``, not to a frame's wait."""
        t0 = time.perf_counter()
        before = (self.updates, self.longest_wait_ms)
        self.update(xy, radius_m, wait=True)
        self.updates, self.longest_wait_ms = before
        self.startup_ms += (time.perf_counter() - t0) * 1e3

    def close(self) -> None:
        """Stop the background loader."""
        self.cache.close()

    def summary(self) -> dict:
        return {
            "budget_mb": self.budget_bytes / 1e6,
            "tiles_budget_mb": self.cache.budget_bytes / 1e6,
            "derived_mb": {k: v / 1e6 for k, v in self.derived.items()},
            "needed_mb": sum(self.needed().values()) / 1e6,  # what check_budget asks of the budget
            "peak_mb": self.cache.peak_bytes / 1e6,
            "tiles": len(self.store.entries),
            "tile_loads": self.loads,
            "longest_wait_ms": self.longest_wait_ms,
            "startup_load_ms": self.startup_ms,
            "broken_tiles": sorted(self.store.entries[k].file for k in self.cache.broken),
            "updates_with_tiles_left_out": self.left_out_updates,
            "updates_with_coarse_tiles": self.coarse_updates,
            "coarse_level": self.cache.use_coarse,
            "opinion_places": self.consulted_places,
            "opinion_places_not_held": self.unscored_places,
        }

    def background_points(self, max_points: int = 150_000) -> np.ndarray:
        """Non-ground vertices of the whole map, thinned to about ``max_points`` (for the plots), read one
        tile at a time."""
        total = max(1, self.store.n_vertices)
        step = max(1, int(np.ceil(total / max_points)))
        out = []
        for k in range(len(self.store.entries)):
            v, _f, g = self.store.read(k)
            out.append(v[~g][::step])
        return np.concatenate(out) if out else np.zeros((0, 3))
