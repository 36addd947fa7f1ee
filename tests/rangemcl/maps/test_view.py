"""The localizer within a memory budget (``--map-memory``): with room for every tile it gives the
whole map's results exactly; with less it holds no more than the budget and logs what it left out; a
slow disk does not hold up a tracking step; a map of format 1 is refused with the command that fixes it."""

from __future__ import annotations

import csv
import json
import time

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.localization import LocalizerSettings
from rangemcl.localization.pipeline import RunOptions, localize_sequence
from rangemcl.maps.meshmap import MeshMap


@pytest.fixture(scope="module")
def tiled(small_town_map):
    """The small town's map cut into 10 m tiles (about 25 tiles), with its mapping drive."""
    root, map_dir = small_town_map
    m = MeshMap.load(map_dir)
    t = MeshMap.from_mesh(m.vertices, m.faces, m.is_ground, tile_size_m=10.0, meta=m.meta)
    t.drive_xy = m.drive_xy
    t.save(root / "map10")
    assert len(t.tiles) >= 12
    return root / "map_run", root / "map10"


def settings(max_range_m: float | None = None) -> LocalizerSettings:
    s = LocalizerSettings()
    s.observation.rays = 200
    if max_range_m is not None:
        s.observation.max_range_m = max_range_m
    return s


def frames(out) -> list[dict]:
    with (out / "frames.csv").open() as fh:
        return list(csv.DictReader(fh))


def run(seq, map_dir, out, s, **opts):
    options = RunOptions(mode="tracking", seed=0, threads=2, plots=False, frames=40, **opts)
    return localize_sequence(seq, map_dir, out, s, options)


def test_with_room_for_every_tile_the_results_are_the_whole_maps(tiled, tmp_path):
    seq, map_dir = tiled
    run(seq, map_dir, tmp_path / "whole", settings())
    summary = run(seq, map_dir, tmp_path / "view", settings(), map_memory_mb=1000.0)
    assert (tmp_path / "view" / "estimate_kitti.txt").read_bytes() == (
        tmp_path / "whole" / "estimate_kitti.txt"
    ).read_bytes()
    rows = [r for r in frames(tmp_path / "view") if int(r["map_tiles"]) >= 0]  # the updates
    assert len(rows) > 10 and all(int(r["map_left_out"]) == 0 for r in rows)
    assert int(rows[0]["map_tiles"]) > 0 and float(rows[0]["map_mb"]) > 0
    assert all(int(r["map_tiles"]) == -1 for r in frames(tmp_path / "whole"))
    mem = summary["map_memory"]
    assert mem["peak_mb"] <= 1000.0 and mem["tile_loads"] >= int(rows[0]["map_tiles"])


def test_a_small_budget_holds_and_says_what_it_left_out(tiled, tmp_path):
    seq, map_dir = tiled
    whole = run(seq, map_dir, tmp_path / "whole", settings(20.0))
    held = [int(r["map_tiles"]) for r in frames(tmp_path / "whole")]
    assert set(held) == {-1}
    from rangemcl.maps.store import TileStore

    store = TileStore.open(map_dir)
    one = 62 * max(e.triangles for e in store.entries) + 12 * max(e.vertices for e in store.entries)
    budget_mb = 6 * one / 1e6
    summary = run(seq, map_dir, tmp_path / "small", settings(20.0), map_memory_mb=budget_mb)
    rows = frames(tmp_path / "small")
    assert all(float(r["map_mb"]) <= budget_mb + 1e-9 for r in rows if r["map_mb"] != "nan")
    assert summary["map_memory"]["peak_mb"] <= budget_mb
    assert any(int(r["map_left_out"]) > 0 for r in rows)
    assert summary["map_memory"]["updates_with_tiles_left_out"] > 0
    m = json.loads((tmp_path / "small" / "metrics.json").read_text())
    assert m["success"] and whole["frames"] == summary["frames"]


def test_with_a_coarse_level_the_farther_tiles_come_coarse(tiled, tmp_path):
    """The same short budget over the map with a coarse level (``rangemcl map-coarse``): the farther tiles
    are held coarse instead of left out (fewer than half the left-out tiles of the map without), and the
    track stays within 5 cm of the whole map's RMSE."""
    import shutil

    from rangemcl.maps.coarse import add_coarse_level
    from rangemcl.maps.store import TileStore

    seq, map_dir = tiled
    coarse_dir = tmp_path / "map10c"
    shutil.copytree(map_dir, coarse_dir)
    add_coarse_level(coarse_dir)
    store = TileStore.open(coarse_dir)
    one = 62 * max(e.triangles for e in store.entries) + 12 * max(e.vertices for e in store.entries)
    budget_mb = 6 * one / 1e6
    run(seq, map_dir, tmp_path / "whole", settings(20.0))
    summary = run(seq, coarse_dir, tmp_path / "coarse", settings(20.0), map_memory_mb=budget_mb)
    run(seq, map_dir, tmp_path / "fine", settings(20.0), map_memory_mb=budget_mb)
    rows = [r for r in frames(tmp_path / "coarse") if int(r["map_tiles"]) >= 0]
    fine = [r for r in frames(tmp_path / "fine") if int(r["map_tiles"]) >= 0]
    assert any(int(r["map_coarse"]) > 0 for r in rows) and all(int(r["map_coarse"]) == 0 for r in fine)
    left_out = sum(int(r["map_left_out"]) for r in rows)
    assert left_out < sum(int(r["map_left_out"]) for r in fine) / 2
    assert sum(int(r["map_tiles"]) for r in rows) > sum(int(r["map_tiles"]) for r in fine)
    assert summary["map_memory"]["peak_mb"] <= budget_mb and summary["map_memory"]["coarse_level"]
    whole = json.loads((tmp_path / "whole" / "metrics.json").read_text())
    m = json.loads((tmp_path / "coarse" / "metrics.json").read_text())
    assert m["success"] and m["location_rmse_m"] < whole["location_rmse_m"] + 0.05


def test_a_slow_disk_does_not_hold_up_a_tracking_step(tiled, tmp_path, monkeypatch):
    """Each tile takes 0.15 s to read: the tiles around the start pose are loaded before the first frame
    (the run's start-up), and no update waits (0 ms): one goes on with what is loaded and logs the tiles
    still loading as left out."""
    from rangemcl.maps.store import TileStore

    read = TileStore.read

    def slow(self, k, **kw):
        time.sleep(0.15)
        return read(self, k, **kw)

    monkeypatch.setattr(TileStore, "read", slow)
    run(*tiled, tmp_path / "slow", settings(15.0), map_memory_mb=1000.0)
    rows = [r for r in frames(tmp_path / "slow") if r["map_load_ms"] != "nan"]
    assert all(float(r["map_load_ms"]) == 0.0 for r in rows)
    assert any(int(r["map_left_out"]) > 0 for r in rows)
    memory = json.loads((tmp_path / "slow" / "summary.json").read_text())["map_memory"]
    assert memory["startup_load_ms"] >= 150.0 and memory["longest_wait_ms"] == 0.0
    est = np.loadtxt(tmp_path / "slow" / "estimate_kitti.txt")
    assert np.isfinite(est).all() and len(est) == 40


def test_a_map_of_format_1_is_refused_with_the_fix(small_town_map, tmp_path, save_v1):
    from rangemcl.maps.view import MapView
    from rangemcl.raycast import RayCaster

    _, map_dir = small_town_map
    save_v1(MeshMap.load(map_dir), tmp_path / "v1")
    with pytest.raises(InputError, match="rangemcl map-upgrade"):
        MapView(tmp_path / "v1", 100.0, RayCaster("cpu", 1))
    with pytest.raises(InputError, match="--map-memory"):
        MapView(map_dir, -1.0, RayCaster("cpu", 1))
    # the ground grid and the mapping drive count against the budget: one line with what it needs in all
    with pytest.raises(InputError, match=r"0.01 MB is too small for this run: it needs .* \(ground grid"):
        MapView(map_dir, 0.01, RayCaster("cpu", 1)).check_budget()
    derived = MapView(map_dir, 100.0, RayCaster("cpu", 1)).derived
    assert derived["ground grid"] > 0
    # a budget below the nearest tile: one line saying what it takes, not an empty scene
    view = MapView(map_dir, sum(derived.values()) / 1e6 + 0.01, RayCaster("cpu", 1), coarse=False)
    with pytest.raises(InputError, match=r"holds none of the tiles in range.*rangemcl map-coarse"):
        view.update(view.drive_xy[:1], 40.0)
    view.close()


def test_the_default_is_sized_from_the_machine(tiled, monkeypatch):
    """No budget given: the whole map when it takes under a quarter of the memory available, else a view
    within that quarter; a budget in the settings (the config's ``map_memory_mb``) is a view."""
    from rangemcl.maps import view
    from rangemcl.maps.store import TileStore

    _, map_dir = tiled
    m, caster = view.open_map(map_dir)
    assert isinstance(m, MeshMap) and caster is None
    need = TileStore.open(map_dir).n_triangles * view.WHOLE_MAP_BYTES_PER_TRIANGLE
    monkeypatch.setattr(view, "available_memory_bytes", lambda: int(2 * need))
    m, caster = view.open_map(map_dir)
    try:
        assert isinstance(m, view.MapView) and m.budget_bytes == pytest.approx(need / 2, rel=1e-6)
        assert caster is m.caster
    finally:
        m.close()
    s = LocalizerSettings()
    s.map_memory_mb = 0.0
    with pytest.raises(InputError, match="map_memory_mb"):
        s.check()


def test_the_agent_takes_the_budget_from_its_settings(tiled):
    from rangemcl.maps.view import MapView
    from rangemcl.rangeimage import RangeImageGeometry
    from rangemcl.sensors import load_spec
    from simbed.trials.agents import MCLAgent

    _, map_dir = tiled
    s = settings()
    s.map_memory_mb = 5.0
    agent = MCLAgent(map_dir, RangeImageGeometry.for_spec(load_spec("os1-64")), settings=s, threads=1)
    assert isinstance(agent.map, MapView) and agent.map.budget_bytes == 5_000_000
    agent.map.close()


def test_what_the_filter_derives_from_the_map_counts_against_the_budget(tiled, tmp_path):
    """The ground grid, the mapping drive, the drivable area's cells and the place prior's profiles are
    held whole: each is counted against ``--map-memory`` under its name, and the tiles get what is left."""
    import shutil

    from rangemcl.localization import build_localizer, map_place_prior
    from rangemcl.maps.view import open_map

    _, source = tiled
    map_dir = shutil.copytree(source, tmp_path / "map")
    s = settings()
    map_place_prior(map_dir, s, threads=1)  # stored with the map, as build-map does
    view, caster = open_map(map_dir, 5.0, threads=1)
    loc = build_localizer(view, s, rng=np.random.default_rng(0), caster=caster, threads=1)
    loc.spread(500)
    d = view.derived
    assert {"ground grid", "mapping drive", "drivable area", "place prior"} <= set(d)
    assert d["place prior"] == loc.prior.nbytes > 0 and d["drivable area"] > 0
    assert view.cache.budget_bytes == 5_000_000 - sum(d.values())
    assert 0 < view.cache.peak_bytes <= view.cache.budget_bytes
    assert view.summary()["derived_mb"]["place prior"] == pytest.approx(loc.prior.nbytes / 1e6)
    view.close()


def test_the_likelihood_field_is_made_tile_by_tile_within_the_budget(tiled, tmp_path, monkeypatch):
    """The likelihood-field baseline over a map within a budget: the surface voxels of the held tiles,
    one k-d tree a tile, give the distances of the whole map's field (a few voxels differ where the
    random samples fell otherwise), and a tracking run gives, bit for bit, the run over the whole map
    with the same voxels in one tree; the voxels' bytes are counted in the budget."""
    import rangemcl.localization.models as models
    from rangemcl.localization.models import (
        FIELD_BYTES_PER_VOXEL,
        LikelihoodFieldModel,
        TiledLikelihoodFieldModel,
        tile_surface_voxels,
    )
    from rangemcl.maps.view import MapView
    from rangemcl.raycast import RayCaster

    monkeypatch.setenv("RANGEMCL_CACHE_DIR", str(tmp_path / "cache"))
    seq, map_dir = tiled
    whole_map = MeshMap.load(map_dir)
    whole = LikelihoodFieldModel(models.cached_surface_voxels(whole_map, 0.2), voxel_m=0.2)
    view = MapView(map_dir, 1000.0, RayCaster(threads=2), background=False)
    try:
        x0, y0, _z0, x1, y1, _z1 = view.extent
        view.update(np.array([[0.5 * (x0 + x1), 0.5 * (y0 + y1)]]), 2.0 * max(x1 - x0, y1 - y0))
        field = TiledLikelihoodFieldModel(view, voxel_m=0.2)
        field.sync()
        assert len(field._trees) == len(view.cache.items) > 10
        assert view.derived["likelihood field"] == FIELD_BYTES_PER_VOXEL * field.voxels
        assert view.cache.budget_bytes == view.budget_bytes - sum(view.derived.values())
        rng = np.random.default_rng(3)
        v = whole_map.vertices
        pts = v[rng.integers(0, len(v), 4000)] + rng.normal(0, 0.3, (4000, 3))
        a, b = whole.distances(pts), field.distances(pts)
        assert np.median(np.abs(a - b)) == 0.0 and np.quantile(np.abs(a - b), 0.99) <= 0.2
        assert abs(field.voxels - whole.voxels) <= 0.05 * whole.voxels  # (border voxels in two tiles)
        union = np.vstack([tile_surface_voxels(view.store, k, False, 0.2) for k in range(len(view.tiles))])
    finally:
        view.close()
    s = settings(20.0)
    s.observation.model = "likelihood_field"
    s.observation.field_voxel_m = 0.2
    summary = run(seq, map_dir, tmp_path / "view", s, map_memory_mb=1000.0)
    monkeypatch.setattr(models, "cached_surface_voxels", lambda m, voxel_m, seed=0: union)
    run(seq, map_dir, tmp_path / "whole", s)
    assert (tmp_path / "view" / "estimate_kitti.txt").read_bytes() == (
        tmp_path / "whole" / "estimate_kitti.txt"
    ).read_bytes()
    m = json.loads((tmp_path / "view" / "metrics.json").read_text())
    assert m["success"] and m["location_rmse_m"] < 0.1
    assert summary["map_memory"]["derived_mb"]["likelihood field"] > 0


def test_a_budget_too_small_for_the_likelihood_field_is_one_clear_line(tiled, tmp_path, monkeypatch):
    """The voxels take about 4x the tiles' bytes: a budget that holds the tiles in range but not their
    voxels as well is refused with the size it needs, instead of evicting the tiles the field follows."""
    from rangemcl.localization.models import TiledLikelihoodFieldModel
    from rangemcl.maps.view import MapView
    from rangemcl.raycast import RayCaster

    monkeypatch.setenv("RANGEMCL_CACHE_DIR", str(tmp_path / "cache"))
    _seq, map_dir = tiled
    probe = MapView(map_dir, 1000.0, RayCaster(threads=2), background=False)
    x0, y0, _z0, x1, y1, _z1 = probe.extent
    centre = np.array([[0.5 * (x0 + x1), 0.5 * (y0 + y1)]])
    probe.update(centre, 15.0)
    field = TiledLikelihoodFieldModel(probe, voxel_m=0.2)
    field.sync()
    tiles = probe.cache.nbytes
    others = sum(v for k, v in probe.derived.items() if k != "likelihood field")
    probe.close()
    assert field.nbytes > tiles  # the voxels outweigh the BVHs
    view = MapView(
        map_dir, (others + tiles + 0.5 * field.nbytes) / 1e6, RayCaster(threads=2), background=False
    )
    try:
        view.update(centre, 15.0)
        with pytest.raises(InputError, match=r"too small for the likelihood field.*give at least"):
            TiledLikelihoodFieldModel(view, voxel_m=0.2).sync()
    finally:
        view.close()


def test_a_slow_likelihood_field_tree_does_not_hold_up_a_tracking_update(tiled, tmp_path, monkeypatch):
    """Each tile's voxels take 0.3 s to make: the first update waits for its trees, a tracking update
    (the view's update without waiting) goes on with the trees that are ready and says how many are
    still being made; they are in at a later update."""
    import rangemcl.localization.models as models
    from rangemcl.maps.view import MapView
    from rangemcl.raycast import RayCaster

    monkeypatch.setenv("RANGEMCL_CACHE_DIR", str(tmp_path / "cache"))
    made = models.tile_surface_voxels

    def slow(*a, **k):
        time.sleep(0.3)
        return made(*a, **k)

    monkeypatch.setattr(models, "tile_surface_voxels", slow)
    _seq, map_dir = tiled
    view = MapView(map_dir, 1000.0, RayCaster(threads=2), background=False)
    field = models.TiledLikelihoodFieldModel(view, voxel_m=0.2)
    try:
        a, b = view.drive_xy[:1], view.drive_xy[-1:]  # the mapping drive's ends, about 40 m apart
        view.update(a, 5.0, wait=False)  # the first: waits all the same
        field.sync()
        first = dict(field._trees)
        assert first and field.building == 0
        view.update(np.vstack([a, b]), 5.0, wait=False)  # the other end's tiles as well
        t0 = time.perf_counter()
        field.sync()
        assert time.perf_counter() - t0 < 0.2 and field.building > 0 and field.updates_without_trees == 1
        assert set(field._trees) == set(first)  # the new tiles' trees are still being made
        time.sleep(0.4 * field.building + 0.5)
        field.sync()
        assert field.building == 0 and set(field._trees) == set(view.in_range)
        view.update(b, 30.0, wait=True)  # a search waits
        field.sync()
        assert field.building == 0 and set(field._trees) == set(view.in_range) > set(first)
    finally:
        field.close()
        view.close()


def test_both_kinds_of_map_follow_the_map_protocol(small_town_map):
    """A whole map and a map within a budget give what :class:`rangemcl.maps.meshmap.Map` promises,
    the same figures where both hold them, and say which they are (``budgeted``)."""
    from rangemcl.maps.meshmap import Map
    from rangemcl.maps.view import open_map

    _, map_dir = small_town_map
    whole, _ = open_map(map_dir)
    view, _ = open_map(map_dir, 100.0)
    try:
        assert isinstance(whole, Map) and isinstance(view, Map)
        assert not whole.budgeted and view.budgeted
        assert whole.n_triangles == view.n_triangles and np.allclose(whole.extent, view.extent)
        assert np.array_equal(whole.tiles, view.tiles) and whole.meta == view.meta
        xy = np.array([[0.0, 0.0], [10.0, -5.0]])
        assert np.array_equal(whole.tile_at(xy[:, 0], xy[:, 1]), view.tile_at(xy[:, 0], xy[:, 1]))
    finally:
        view.close()
