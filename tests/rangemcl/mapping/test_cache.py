"""The tile cache (issue 17): never more than its budget in measured bytes, evicts the farthest tiles
first, holds the nearest wanted tiles, reports what did not fit."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.mapping.cache import TileCache, tile_distances
from rangemcl.mapping.meshmap import MeshMap
from rangemcl.mapping.store import TileStore


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
        held_bytes = sum(sum(a.nbytes for a in item) for item, _n in cache.items.values())
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

    def read(s, k):
        reads.append(k)
        return s.read(k)

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
    from rangemcl.mapping.cache import caster_tiles
    from rangemcl.raycast import RayCaster

    caster = RayCaster("cpu", threads=1)
    prepare, release = caster_tiles(caster)
    one = prepare(*store.read(0))[1]
    release(0)
    cache = TileCache(store, budget_bytes=2 * one, prepare=prepare, release=release)
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
