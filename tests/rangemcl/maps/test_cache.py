"""The tile cache: never more than its budget in measured bytes, evicts the farthest tiles
first, holds the nearest wanted tiles, reports what did not fit."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.maps.cache import TileCache, tile_distances
from rangemcl.maps.meshmap import MeshMap
from rangemcl.maps.store import TileStore


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 5 x 5 grid of 20 m tiles, each a ground patch of the same triangle count."""
    parts = []
    for i in range(5):
        for j in range(5):
            parts.append(
                meshgen.grid_patch((20.0 * i + 0.5, 20.0 * j + 0.5, 0.0), (19.0, 0, 0), (0, 19.0, 0), 6, 6)
            )
    v, f = meshgen.merge(parts)
    d = tmp_path_factory.mktemp("cache") / "map"
    MeshMap.from_mesh(v, f, tile_size_m=20.0).save(d)
    s = TileStore.open(d)
    assert len(s.entries) == 25
    return s


def test_tile_distances_are_box_distances(store):
    d = tile_distances(store, [[10.0, 10.0]])
    k = [e.ij for e in store.entries].index((0, 0))
    assert d[k] == 0.0
    b = store.entries[[e.ij for e in store.entries].index((2, 0))].bounds
    assert d[[e.ij for e in store.entries].index((2, 0))] == pytest.approx(b[0] - 10.0)


def test_the_budget_holds_and_the_farthest_go_first(store):
    one = sum(a.nbytes for a in store.read(0))
    cache = TileCache(store, budget_bytes=5 * one)
    for x in np.linspace(-10.0, 110.0, 25):
        focus = [[x, 50.0]]
        r = cache.request(focus, radius_m=25.0)
        dist = tile_distances(store, focus)
        # measured: the bytes of the arrays held
        held_bytes = sum(sum(a.nbytes for a in item) for item in cache.items.values())
        assert held_bytes == cache.nbytes <= cache.budget_bytes
        assert sorted(r.held) == sorted(cache.items) or set(r.held) <= set(cache.items)
        # evictions at this request: tiles no longer wanted first, each group farthest first
        gone = [k for k in r.evicted if k not in r.wanted]
        assert r.evicted[: len(gone)] == gone
        ev = [dist[k] for k in gone]
        assert ev == sorted(ev, reverse=True)
        # what was left out lies no nearer than anything held of the wanted
        if r.left_out and r.held:
            assert min(dist[k] for k in r.left_out) >= max(dist[k] for k in r.held)
        assert r.wanted == sorted(r.wanted, key=lambda k: dist[k])
        assert len(r.held) == min(5, len(r.wanted))
    assert cache.peak_bytes <= cache.budget_bytes


def test_a_wanted_tile_is_not_read_again(store):
    reads = []

    def read(s, k, coarse):
        reads.append(k)
        return s.read(k, coarse=coarse)

    cache = TileCache(store, budget_bytes=10**9, read=read)
    first = cache.request([[50.0, 50.0]], 15.0)
    again = cache.request([[50.0, 50.0]], 15.0)
    assert first.loaded and not again.loaded and sorted(reads) == sorted(first.loaded)
    assert again.held == first.held
    with pytest.raises(ValueError):
        TileCache(store, 0)


def test_tiles_in_a_caster_leave_it_when_evicted(store):
    """With :func:`caster_tiles` the cache's tiles are meshes of a RayCaster: an evicted tile is taken out
    of the scene (rays pass where it was), a held one is hit."""
    from rangemcl.maps.cache import caster_tiles
    from rangemcl.raycast import RayCaster

    caster = RayCaster("cpu", threads=1)
    kind = caster_tiles(caster)
    one = kind.size_of(store.entries[0])
    cache = TileCache(store, budget_bytes=2 * one, kind=kind)
    down = np.array([[0.0, 0.0, -1.0]])

    def hit_at(x, y):
        return bool(np.isfinite(caster.cast(np.array([[x, y, 5.0]]), down, 10.0).ranges[0]))

    r = cache.request([[10.0, 10.0]], 0.0)  # tile (0, 0) only
    assert r.held and hit_at(10.0, 10.0) and not hit_at(90.0, 90.0)
    r = cache.request([[90.0, 90.0]], 0.0)
    assert hit_at(90.0, 90.0) and hit_at(10.0, 10.0)  # both fit
    cache.request([[50.0, 50.0]], 0.0)  # a third tile: the farthest of the others goes
    assert hit_at(50.0, 50.0) and hit_at(10.0, 10.0) != hit_at(90.0, 90.0)
    assert len(caster.live_handles) == len(cache.items) == 2


def slow_cache(store, tiles: int, delay_s: float):
    """A background cache whose disk takes ``delay_s`` a tile, with room for ``tiles`` tiles of ``store``;
    also the tiles' (i, j) in index order."""
    import time

    def slow(s, k, coarse):
        time.sleep(delay_s)
        return s.read(k, coarse=coarse)

    one = store.entries[0].vertices * 25 + store.entries[0].triangles * 12
    cache = TileCache(store, budget_bytes=tiles * one, read=slow, background=True)
    return cache, one, [e.ij for e in store.entries]


def test_the_background_loader_does_not_block_a_request(store):
    """A slow disk (0.3 s a tile): a request that must not wait returns at once with what is held and
    reports the rest as left out and loading (unless it holds none of its tiles); the tiles enter at a
    later request; ``wait`` blocks until they are in. The budget counts the tiles being loaded."""
    import time

    cache, one, ij = slow_cache(store, 3, 0.3)
    try:
        # nothing held yet: even a request that need not wait waits (a scene without its tiles is worse)
        r = cache.request([[10.0, 10.0]], 5.0, wait=False)
        assert r.held == r.wanted == [ij.index((0, 0))] and r.wait_ms >= 250.0
        # the car moves on: the new tile loads in the background, the request returns at once
        t0 = time.perf_counter()
        r = cache.request([[25.0, 10.0]], 10.0, wait=False)
        assert time.perf_counter() - t0 < 0.1
        assert r.wanted == [ij.index((1, 0)), ij.index((0, 0))] and r.held == [ij.index((0, 0))]
        assert r.left_out == r.loading == [ij.index((1, 0))] and r.wait_ms == 0.0
        assert cache.reserved_bytes == 2 * one <= cache.budget_bytes
        time.sleep(0.5)
        r = cache.request([[25.0, 10.0]], 10.0, wait=False)
        assert r.held == r.wanted and r.loaded == [ij.index((1, 0))] and not r.left_out
        # elsewhere, waiting: the request returns with the tiles held, the wait measured
        r = cache.request([[90.0, 90.0]], 5.0, wait=True)
        assert r.held == r.wanted and r.wait_ms >= 250.0
        assert r.evicted == [] and len(cache.items) == 3
        # ahead of the car: the tiles within the prefetch ring load without being waited for, the three
        # held (no longer wanted) make room
        r = cache.request([[50.0, 50.0]], 1.0, prefetch_m=15.0, wait=True)
        assert set(r.evicted) == {ij.index((0, 0)), ij.index((1, 0)), ij.index((4, 4))}
        assert r.wanted == [ij.index((2, 2))] and r.held == r.wanted and len(r.loading) == 2
        assert cache.peak_bytes <= cache.budget_bytes
    finally:
        cache.close()


def test_extra_places_take_what_the_car_leaves_and_are_never_waited_for(store):
    """The lost detector's rival places (``extra_xy``): their tiles load in the background after the
    wanted tiles and the prefetch ring, at most two at a time, best place first, within what the budget
    leaves; a request never waits for them and never evicts a wanted tile for them; once no request
    names them they are the first to go."""
    import time

    from rangemcl.maps.cache import EXTRA_LOADS

    cache, _one, ij = slow_cache(store, 6, 0.2)
    try:
        car = [[10.0, 10.0]]  # tile (0, 0); the prefetch ring adds (1, 0), (0, 1) and (1, 1)
        cache.request(car, 5.0, prefetch_m=12.0, wait=True)
        places = [[90.0, 90.0], [90.0, 10.0], [10.0, 90.0], [50.0, 50.0]]  # (4,4), (4,0), (0,4), (2,2)
        t0 = time.perf_counter()
        r = cache.request(car, 5.0, prefetch_m=12.0, wait=False, extra_xy=places)
        assert time.perf_counter() - t0 < 0.1 and r.wait_ms == 0.0
        assert r.extra == [ij.index(c) for c in [(4, 4), (4, 0), (0, 4), (2, 2)]]
        assert r.held == [ij.index((0, 0))] and not r.evicted
        extra_loading = [k for k in r.loading if k in r.extra]
        assert len(extra_loading) <= EXTRA_LOADS
        deadline = time.perf_counter() + 5.0
        while time.perf_counter() < deadline:
            r = cache.request(car, 5.0, prefetch_m=12.0, wait=False, extra_xy=places)
            assert ij.index((0, 0)) in cache.items  # the car's tile stays
            assert sum(k in r.extra for k in r.loading) <= EXTRA_LOADS
            if not r.loading:
                break
            time.sleep(0.05)
        # the budget of 6 tiles: the car's 4, then the two best places
        held = {ij[k] for k in cache.items}
        assert held == {(0, 0), (1, 0), (0, 1), (1, 1), (4, 4), (4, 0)}
        assert cache.peak_bytes <= cache.budget_bytes
        # the car drives on: the places no longer named leave first, the car's new tiles come in
        r = cache.request([[50.0, 10.0]], 5.0, prefetch_m=0.0, wait=True)
        assert r.evicted == [ij.index((4, 4))]  # the farthest of the tiles no longer named
        assert r.held == r.wanted == [ij.index((2, 0))]
    finally:
        cache.close()


def test_a_broken_tile_is_reported_once_and_left_out(store, tmp_path):
    """A truncated tile file: the request names it (``broken``, the error line names the file), goes on
    with the other tiles, and never reads it again."""
    import shutil

    from rangemcl.maps.store import TileStore as Store

    d = tmp_path / "map"
    shutil.copytree(store.map_dir, d)
    k = [e.ij for e in store.entries].index((1, 1))
    p = d / store.entries[k].file
    p.write_bytes(p.read_bytes()[:-10])
    cache = TileCache(Store.open(d), budget_bytes=10**9, background=True)
    try:
        r = cache.request([[30.0, 30.0]], 15.0)
        assert r.broken == [k] and k in r.left_out and len(r.held) == len(r.wanted) - 1
        assert store.entries[k].file in cache.broken[k] and "truncated" in cache.broken[k]
        r = cache.request([[30.0, 30.0]], 15.0)
        assert r.broken == [] and not r.loading and k in r.left_out
    finally:
        cache.close()


@pytest.fixture(scope="module")
def wavy(tmp_path_factory):
    """A 5 x 5 grid of 20 m tiles of a wavy surface (z = 0.5 sin(x/3) cos(y/4), 2 x 1,600 triangles a
    tile), with its coarse level."""
    from rangemcl.maps.coarse import add_coarse_level

    v, f = meshgen.grid_patch((0.0, 0.0, 0.0), (100.0, 0, 0), (0, 100.0, 0), 200, 200)
    v = v.copy()
    v[:, 2] = 0.5 * np.sin(v[:, 0] / 3.0) * np.cos(v[:, 1] / 4.0)
    d = tmp_path_factory.mktemp("wavy") / "map"
    MeshMap.from_mesh(v, f, np.ones(len(v), bool), tile_size_m=20.0).save(d)
    report = add_coarse_level(d)
    assert report["tiles"] == 25 and 0.04 < report["coarse_share"] < 0.06
    return TileStore.open(d), v, f


def test_the_coarse_level_keeps_each_tiles_footprint(wavy):
    """Decimated to 5 %, a tile still covers its square (its border stays: a vertical ray anywhere in the
    map, seams included, hits), and its surface stays near the full one (median a few cm here)."""
    from rangemcl.maps.coarse import decimate_tile
    from rangemcl.raycast import RayCaster

    store, v, f = wavy
    for e in store.entries:
        assert e.coarse.bounds[:2] == pytest.approx(e.bounds[:2], abs=0.01) and e.coarse.bounds[
            3:5
        ] == pytest.approx(e.bounds[3:5], abs=0.01)
    coarse, full = RayCaster("cpu", 1), RayCaster("cpu", 1)
    for k in range(len(store.entries)):
        cv, cf, cg = store.read(k, coarse=True)
        assert cg.all()
        coarse.add_mesh(cv, cf)
    full.add_mesh(v, f)
    rng = np.random.default_rng(0)
    xy = np.concatenate(
        [rng.uniform(0.1, 99.9, (2000, 2)), np.c_[np.full(200, 40.0), rng.uniform(0.1, 99.9, 200)]]
    )
    origins = np.c_[xy, np.full(len(xy), 5.0)]
    down = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    rc, rf = coarse.cast(origins, down, 10.0).ranges, full.cast(origins, down, 10.0).ranges
    assert np.isfinite(rc).all() and np.isfinite(rf).all()
    assert np.median(np.abs(rc - rf)) < 0.05
    again = decimate_tile(*store.read(3))
    assert all(np.array_equal(a, b) for a, b in zip(again, store.read(3, coarse=True), strict=True))


def test_where_the_budget_is_short_the_farther_tiles_are_coarse(wavy):
    """Every wanted tile is held, the nearest at full resolution and the farther ones at the coarse level,
    within the budget; with room for all, all are full."""
    from rangemcl.maps.cache import COARSE

    store, _v, _f = wavy
    focus = [[50.0, 50.0]]
    dist = tile_distances(store, focus)
    near = [k for k in np.argsort(dist, kind="stable") if dist[k] <= 25.0]
    full = sum(25 * store.entries[k].vertices + 12 * store.entries[k].triangles for k in near)
    cache = TileCache(store, budget_bytes=full // 3)
    r = cache.request(focus, 25.0)
    assert r.held == r.wanted and not r.left_out and len(r.wanted) == len(near) == 9
    assert 0 < len(r.coarse) < len(r.held) and cache.nbytes <= cache.budget_bytes
    held_full = [k for k in r.held if cache.levels[k] != COARSE]
    assert max(dist[k] for k in held_full) <= min(dist[k] for k in r.coarse)
    big = TileCache(store, budget_bytes=10 * full)
    r = big.request(focus, 25.0)
    assert r.held == r.wanted and r.coarse == []
    none = TileCache(store, budget_bytes=10 * full, coarse=False)
    assert (
        none.request(focus, 25.0).coarse == []
        and TileCache(store, full // 3, coarse=False).request(focus, 25.0).left_out
    )


def test_a_budget_of_one_tile_swaps_by_waiting(store):
    """Room for one tile only and the car crosses into the next: the held tile is evicted for the nearer
    one, and that request waits for it rather than leaving the scene empty."""
    one = store.entries[0].vertices * 25 + store.entries[0].triangles * 12
    ij = [e.ij for e in store.entries]
    cache = TileCache(store, budget_bytes=one, background=True)
    try:
        cache.request([[15.0, 10.0]], 10.0, wait=False)
        assert list(cache.items) == [ij.index((0, 0))]
        r = cache.request([[25.0, 10.0]], 10.0, wait=False)
        assert r.evicted == [ij.index((0, 0))] and r.held == [ij.index((1, 0))] and r.wait_ms > 0
    finally:
        cache.close()


_RESIDENT_PROBE = r"""
import re, sys
import numpy as np
from rangemcl.maps.cache import TileCache, caster_tiles
from rangemcl.common.heap import return_freed_memory
from rangemcl.maps.store import TileStore
from rangemcl.raycast import RayCaster

def resident():
    return int(re.search(r"VmRSS:\s+(\d+)", open("/proc/self/status").read()).group(1)) * 1024

return_freed_memory()  # as the localizer's map view does
store = TileStore.open(sys.argv[1])
caster = RayCaster("cpu", threads=1)
cache = TileCache(store, budget_bytes=10**10, kind=caster_tiles(caster), background=True)
before = resident()
cache.request([[100.0, 100.0]], 500.0, wait=True)
assert len(cache.items) == len(store.entries), (len(cache.items), len(store.entries))
print(resident() - before, cache.nbytes)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_tiles_take_the_memory_the_budget_counts_them_at(tmp_path):
    """What a tile costs in the budget (:func:`caster_tiles`: the BVH's estimate) is what the process's
    resident size grows by when tiles are loaded as the localizer loads them (a background thread, one
    tile after another), measured in a fresh process: at most 15 % more. With the read arrays and the
    checks' temporaries left in the heap under the next BVH, and the face map of every triangle kept, the
    tiles of town_large took 1.25x their estimate."""
    parts = []
    for i in range(4):
        for j in range(4):  # 16 tiles of about 80,000 triangles, a wavy patch each
            corner = (50.0 * i + 0.5, 50.0 * j + 0.5, 0.0)
            v, f = meshgen.grid_patch(corner, (49.0, 0, 0), (0, 49.0, 0), 200, 200)
            v[:, 2] = np.sin(v[:, 0] * 0.7) * np.cos(v[:, 1] * 0.3)
            parts.append((v, f))
    v, f = meshgen.merge(parts)
    MeshMap.from_mesh(v, f, tile_size_m=50.0).save(tmp_path / "map")
    out = subprocess.run(
        [sys.executable, "-c", _RESIDENT_PROBE, str(tmp_path / "map")], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    grown, counted = map(int, out.stdout.split())
    assert counted > 50e6  # enough triangles that the process's own noise does not matter
    assert grown <= 1.15 * counted, f"resident {grown / 1e6:.1f} MB, counted {counted / 1e6:.1f} MB"
