"""simbed.scenes.towngen: seeded towns whose roads, terrain, buildings and parked cars keep their promises."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import math
import re
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml
from PIL import Image

from rangemcl.errors import InputError
from simbed.scenes.towngen import (
    DEFAULT_STYLE,
    SHIPPED_TOWNS,
    TownInfo,
    TownPreset,
    TownStyle,
    generate_preset,
    generate_town,
    load_town_info,
    mjcf,
    parked_variant_bodies,
    use_parked_variant,
)

SCENES = Path(__file__).resolve().parents[3] / "scenes"
SIZE = 150.0  # small towns keep the generator tests fast


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> tuple[TownInfo, mujoco.MjModel]:
    out = tmp_path_factory.mktemp("town") / "t.xml"
    info = generate_town(7, SIZE, out, n_parked_variants=3)
    return info, mujoco.MjModel.from_xml_path(str(out))


@pytest.fixture(scope="module")
def shipped() -> dict[str, tuple[TownInfo, mujoco.MjModel]]:
    return {
        nm: (load_town_info(SCENES / f"{nm}.yaml"), mujoco.MjModel.from_xml_path(str(SCENES / f"{nm}.xml")))
        for nm in SHIPPED_TOWNS
    }


def _all_towns(town, shipped):
    return [("generated", *town)] + [(nm, *v) for nm, v in shipped.items()]


# --------------------------------------------------------------------------------------------- helpers


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, E) distances from points (P, 2) to segments a-b (E, 2)."""
    ab = b - a
    t = np.clip(((p[:, None] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1)[None], 0, 1)
    return np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)


def _yaw(quat) -> float:
    w, x, y, z = quat
    assert abs(x) < 1e-9 and abs(y) < 1e-9  # level objects
    return 2 * math.atan2(z, w)


def _rect_points(center, yaw, half, step=0.2, interior=False) -> np.ndarray:
    """Points on (or in) an oriented rectangle: its boundary sampled every ``step`` metres."""
    hx, hy = half
    if interior:
        gx, gy = np.meshgrid(np.linspace(-hx, hx, 9), np.linspace(-hy, hy, 9))
        local = np.stack([gx.ravel(), gy.ravel()], 1)
    else:
        xs = np.linspace(-hx, hx, max(2, int(2 * hx / step) + 1))
        ys = np.linspace(-hy, hy, max(2, int(2 * hy / step) + 1))
        local = np.concatenate(
            [
                np.c_[xs, np.full_like(xs, -hy)],
                np.c_[xs, np.full_like(xs, hy)],
                np.c_[np.full_like(ys, -hx), ys],
                np.c_[np.full_like(ys, hx), ys],
            ]
        )
    c, s = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(center)[:2]


def _geoms(m: mujoco.MjModel, pattern: str):
    rx = re.compile(pattern)
    for g in range(m.ngeom):
        if rx.fullmatch(m.geom(g).name):
            yield g


def _footprints(m: mujoco.MjModel, pattern: str):
    """(name, centre, yaw, half sizes) of the world-body boxes whose names match ``pattern``."""
    out = []
    for g in _geoms(m, pattern):
        assert m.geom_bodyid[g] == 0 and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
        out.append((m.geom(g).name, m.geom_pos[g][:2], _yaw(m.geom_quat[g]), m.geom_size[g][:2]))
    return out


def _parked(m: mujoco.MjModel):
    """{variant: [(index, centre xy, yaw, (half length, half width), body id)]} from parked_v{k}_{i}."""
    cars: dict[int, list] = {}
    rx = re.compile(r"parked_v(\d+)_(\d+)")
    for b in range(m.nbody):
        match = rx.fullmatch(m.body(b).name)
        if match:
            g = m.geom(f"{m.body(b).name}_body").id
            cars.setdefault(int(match[1]), []).append(
                (int(match[2]), m.body_pos[b], _yaw(m.body_quat[b]), m.geom_size[g][:2], b)
            )
    return cars


# ---------------------------------------------------------------------------------------------- tests


def test_same_seed_same_bytes_other_seed_other_town(tmp_path):
    files = ("t.xml", "t.yaml", "t_terrain.bin", "t_ground.img")
    generate_town(3, SIZE, tmp_path / "a" / "t.xml")
    generate_town(3, SIZE, tmp_path / "b" / "t.xml")
    generate_town(4, SIZE, tmp_path / "c" / "t.xml")
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert (tmp_path / "a" / "t.xml").read_bytes() != (tmp_path / "c" / "t.xml").read_bytes()
    assert (tmp_path / "a" / "t_terrain.bin").read_bytes() != (tmp_path / "c" / "t_terrain.bin").read_bytes()
    assert (tmp_path / "a" / "car.xml").read_bytes() == (SCENES / "car.xml").read_bytes()  # copied alongside


def test_compiles_with_the_car_and_static_world_collides_with_it(town):
    info, m = town
    assert m.opt.timestep == pytest.approx(0.002)
    assert m.joint("car_root").type == mujoco.mjtJoint.mjJNT_FREE
    assert m.camera("overview").id >= 0
    assert m.nu == 4 and m.hfield("terrain").id >= 0
    car = m.body("car").id
    wheel = m.geom("wheel_rl").id
    chassis = m.geom("chassis").id
    for g in range(m.ngeom):
        if m.body_rootid[m.geom_bodyid[g]] == car:
            continue
        assert m.body_jntnum[m.geom_bodyid[g]] == 0  # static
        assert m.geom_group[g] == 0, m.geom(g).name
        for mine in (wheel, chassis):
            assert (m.geom_contype[g] & m.geom_conaffinity[mine]) or (
                m.geom_contype[mine] & m.geom_conaffinity[g]
            ), m.geom(g).name
    assert info.name == "t" and info.parked_variants == 3


def test_road_graph_connected_with_loops_and_no_dead_ends(town, shipped):
    for name, info, _ in _all_towns(town, shipped):
        k, e = len(info.nodes), len(info.edges)
        assert e >= k, name  # at least one loop
        deg = np.bincount(info.edges.ravel(), minlength=k)
        assert deg.min() >= 2, name
        adj = {i: set() for i in range(k)}
        for i, j in info.edges:
            adj[i].add(j)
            adj[j].add(i)
        seen, stack = {0}, [0]
        while stack:
            for j in adj[stack.pop()] - seen:
                seen.add(j)
                stack.append(j)
        assert len(seen) == k, name
        a, b = info.segments()
        lengths = np.linalg.norm(b - a, axis=1)
        assert info.total_length_m == pytest.approx(lengths.sum(), abs=0.01)
        assert lengths.min() > 45 and lengths.max() < 115, name
        assert np.all(np.abs(info.nodes) < info.size_m / 2)
        assert info.road_width_m == 8.0 and info.lane_width_m == 3.5
    small, large = shipped["town_small"][0], shipped["town_large"][0]
    assert len(small.edges) - len(small.nodes) + 1 >= 3  # several independent loops
    assert len(large.edges) - len(large.nodes) + 1 >= 10


def test_buildings_and_walls_stay_off_the_roads_and_each_other(town, shipped):
    for name, info, m in _all_towns(town, shipped):
        a, b = info.segments()
        boxes = _footprints(m, r"(bldg_\d+_[ab]|wall_\d+)")
        assert sum(nm.startswith("bldg") for nm, *_ in boxes) >= 5, name
        for nm, c, yaw, half in boxes:
            d = _seg_dist(_rect_points(c, yaw, half), a, b).min()
            assert d >= info.road_width_m / 2 + 2.0 - 0.15, (name, nm, d)  # >= 2 m beyond the road edge
            assert np.all(np.abs(_rect_points(c, yaw, half)) <= info.size_m / 2)
        if name == "generated":  # pairwise overlap check on the small town
            building = [(re.sub(r"_[ab]$", "", nm), c, yaw, half) for nm, c, yaw, half in boxes]
            for i, (ni, ci, yi, hi) in enumerate(building):
                pts = _rect_points(ci, yi, hi * 0.98, interior=True)
                for nj, cj, yj, hj in building[i + 1 :]:
                    if ni == nj:
                        continue  # the two boxes of one L-shaped building touch
                    cc, ss = math.cos(yj), math.sin(yj)
                    local = (pts - cj) @ np.array([[cc, -ss], [ss, cc]])
                    assert not np.any(np.all(np.abs(local) < hj, axis=1)), (ni, nj)


def test_heights_and_street_furniture(town):
    info, m = town
    for g in _geoms(m, r"bldg_\d+_[ab]"):
        x, y, z = m.geom_pos[g]
        top = z + m.geom_size[g][2]
        assert z - m.geom_size[g][2] < info.ground_height(x, y)  # no floating buildings
        assert 3.5 < top - info.ground_height(x, y) < 31.5
    a, b = info.segments()
    poles = list(_geoms(m, r"pole_\d+"))
    trees = list(_geoms(m, r"tree_\d+_trunk"))
    assert poles and trees and len(list(_geoms(m, r"tree_\d+_crown"))) == len(trees)
    for g in poles:
        assert m.geom_size[g][0] == pytest.approx(0.15) and 5.0 <= 2 * m.geom_size[g][1] - 0.3 <= 8.0
    for g in poles + trees:
        p = m.geom_pos[g][:2]
        assert _seg_dist(p[None], a, b).min() > info.road_width_m / 2 + 1.5  # on sidewalks / blocks
        assert m.geom_pos[g][2] - m.geom_size[g][1] < info.ground_height(*p)  # planted


def test_parked_variants_named_and_beside_the_lanes(town, shipped):
    for name, info, m in _all_towns(town, shipped):
        cars = _parked(m)
        assert sorted(cars) == list(range(info.parked_variants)), name
        a, b = info.segments()
        u = (b - a) / np.linalg.norm(b - a, axis=1)[:, None]
        spots = []
        for k, variant in cars.items():
            assert sorted(i for i, *_ in variant) == list(range(len(variant))), (name, k)
            assert len(variant) >= 5, (name, k)
            for i, c, yaw, half, body in variant:
                assert m.body_jntnum[body] == 0 and m.body_parentid[body] == 0
                assert 2.0 <= half[0] <= 2.5 and 0.85 <= half[1] <= 1.0
                d = _seg_dist(_rect_points(c, yaw, half), a, b).min()
                assert d >= info.lane_width_m, (name, k, i, d)  # not on a driving lane
                dc = _seg_dist(c[None, :2], a, b)[0]
                e = int(dc.argmin())
                assert dc[e] < info.road_width_m / 2 + 2.0, (name, k, i)  # beside a road
                assert abs(math.sin(yaw - math.atan2(u[e, 1], u[e, 0]))) < 0.06  # parallel to it
                assert c[2] == pytest.approx(float(info.ground_height(c[0], c[1])), abs=0.01)
            spots.append({(round(c[0]), round(c[1])) for _, c, *_ in variant})
        for k in range(1, len(spots)):
            assert spots[k] != spots[0] and len(spots[k] - spots[0]) > len(spots[k]) // 3, (name, k)


def test_ground_height_matches_mujoco_rays(town, shipped):
    for name, info, m in _all_towns(town, shipped):
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        terrain = m.geom("terrain").id
        car = m.body("car").id
        rng = np.random.default_rng(1)
        gid = np.zeros(1, np.int32)
        errs, road_errs = [], []
        half = info.size_m / 2
        for _ in range(400):
            x, y = rng.uniform(-half, half, 2)
            dist = mujoco.mj_ray(m, d, np.array([x, y, 100.0]), np.array([0, 0, -1.0]), None, 1, car, gid)
            if gid[0] == terrain:
                errs.append(100.0 - dist - float(info.ground_height(x, y)))
        # road centre lines: the road boxes' tops are the ground there
        a, b = info.segments()
        for _ in range(150):
            e = rng.integers(len(a))
            t = rng.uniform(0.15, 0.85)
            x, y = a[e] + t * (b[e] - a[e])
            dist = mujoco.mj_ray(m, d, np.array([x, y, 100.0]), np.array([0, 0, -1.0]), None, 1, car, gid)
            if m.geom(gid[0]).name.startswith(("road_", "junction_", "terrain")):
                road_errs.append(100.0 - dist - float(info.ground_height(x, y)))
        assert len(errs) > 150 and len(road_errs) > 100, name
        assert np.abs(errs).max() < 0.01, name
        assert np.abs(road_errs).max() < 0.01, name
        # vectorised and smooth; relief of about a metre or so
        g = info.ground_height(np.linspace(-half, half, 50)[:, None], np.linspace(-half, half, 50)[None])
        assert g.shape == (50, 50) and 0.3 < np.ptp(g) < 2.0


def test_road_grades_are_gentle(town, shipped):
    for name, info, _ in _all_towns(town, shipped):
        a, b = info.segments()
        for e in range(len(a)):
            t = np.linspace(0, 1, 60)
            pts = a[e] + t[:, None] * (b[e] - a[e])
            h = info.ground_height(pts[:, 0], pts[:, 1])
            step = np.linalg.norm(b[e] - a[e]) / 59
            assert np.abs(np.diff(h)).max() / step < 0.03, (name, e)


def test_spawn_is_on_a_right_hand_lane_and_the_car_rests_there(town):
    info, m = town
    x, y, yaw = info.spawn
    a, b = info.segments()
    dist = _seg_dist(np.array([[x, y]]), a, b)[0]
    e = int(dist.argmin())
    u = (b[e] - a[e]) / np.linalg.norm(b[e] - a[e])
    assert dist[e] == pytest.approx(info.lane_width_m / 2, abs=0.05)
    assert math.cos(yaw - math.atan2(u[1], u[0])) > 0.999  # heading along the road
    left = np.array([-u[1], u[0]])
    assert np.dot(np.array([x, y]) - a[e], left) < 0  # right of the centre line, right-hand traffic
    d = mujoco.MjData(m)
    adr = m.jnt_qposadr[m.joint("car_root").id]
    dof = m.jnt_dofadr[m.joint("car_root").id]
    # anywhere on the roads (graded too), car_qpos starts the car settled: no drop, no bounce
    rng = np.random.default_rng(3)
    for k in [e, *rng.integers(len(a), size=3)]:
        t = rng.uniform(0.3, 0.7)
        p = a[k] + t * (b[k] - a[k])
        heading = math.atan2(*(b[k] - a[k])[::-1])
        mujoco.mj_resetData(m, d)
        d.qpos[adr : adr + 7] = info.car_qpos(p[0], p[1], heading)
        peak = 0.0
        for _ in range(150):
            mujoco.mj_step(m, d)
            peak = max(peak, abs(d.qvel[dof + 2]))
        assert peak < 0.05, (k, peak)
    d.qpos[adr : adr + 7] = info.spawn_qpos()
    np.testing.assert_allclose(info.spawn_qpos()[:3], [x, y, info.ground_height(x, y)])
    for _ in range(500):
        mujoco.mj_step(m, d)
    assert abs(d.qpos[adr + 2] - info.ground_height(x, y)) < 0.03
    assert np.linalg.norm(d.qpos[adr : adr + 2] - [x, y]) < 0.05


def test_use_parked_variant_keeps_one_set(town):
    _, m0 = town
    m = mujoco.MjModel.from_xml_path(str(town[0].xml_path))
    bodies = parked_variant_bodies(m)
    assert sorted(bodies) == [0, 1, 2]
    use_parked_variant(m, 1)

    def geoms(k):
        return [g for b in bodies[k] for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b])]

    for k in (0, 2):
        assert np.all(m.geom_contype[geoms(k)] == 0) and np.all(m.geom_rgba[geoms(k), 3] == 0)
    np.testing.assert_array_equal(m.geom_contype[geoms(1)], m0.geom_contype[geoms(1)])
    assert np.all(m.geom_rgba[geoms(1), 3] == 1)
    with pytest.raises(InputError, match="variant 7"):
        use_parked_variant(m, 7)


def test_shipped_towns(shipped):
    small, _ = shipped["town_small"]
    large, m_large = shipped["town_large"]
    assert (small.seed, small.size_m, small.name) == (1, 200.0, "town_small")
    assert large.seed == 2 and large.size_m >= 600.0 and large.total_length_m >= 3000.0
    assert np.ptp(large.nodes[:, 0]) > 400 and np.ptp(large.nodes[:, 1]) > 400
    assert (SCENES / "town_large.xml").stat().st_size < 5e6
    assert small.parked_variants == large.parked_variants == 2
    assert m_large.hfield("terrain").nrow[0] >= 200
    doc = yaml.safe_load((SCENES / "town_small.yaml").read_text())
    assert list(doc) == [
        "name",
        "seed",
        "size_m",
        "road_width_m",
        "lane_width_m",
        "roads",
        "terrain",
        "parked_variants",
        "spawn",
    ]
    assert list(doc["roads"]) == ["nodes", "edges", "total_length_m"] and list(doc["spawn"]) == [
        "x",
        "y",
        "yaw",
    ]


def test_shipped_small_town_is_what_the_generator_writes(tmp_path):
    generate_preset(SHIPPED_TOWNS["town_small"], tmp_path / "town_small.xml")
    for f in ("town_small.xml", "town_small.yaml", "town_small_terrain.bin"):
        assert (tmp_path / f).read_bytes() == (SCENES / f).read_bytes(), f"{f} is stale: run towngen"
    # the texture's pixels, not its bytes: PNG bytes depend on the encoder (scenes/ may hold an older one's)
    f = "town_small_ground.img"
    new, old = np.asarray(Image.open(tmp_path / f)), np.asarray(Image.open(SCENES / f))
    assert new.shape == old.shape == (400, 400, 3) and np.array_equal(new, old), f"{f} is stale: run towngen"


# ------------------------------------------------------------------------------------ style and presets


def test_presets_are_town_presets_of_the_default_style():
    expected = {
        "town_small": TownPreset(seed=1, size_m=200.0, n_parked_variants=2, style=TownStyle()),
        "town_medium": TownPreset(seed=3, size_m=300.0, n_parked_variants=2, style=TownStyle()),
        "town_large": TownPreset(seed=2, size_m=600.0, n_parked_variants=2, style=TownStyle()),
    }
    assert expected == SHIPPED_TOWNS
    assert all(p.style is DEFAULT_STYLE for p in SHIPPED_TOWNS.values())
    for name, preset in SHIPPED_TOWNS.items():  # the sidecars in scenes/ say the same
        info = load_town_info(SCENES / f"{name}.yaml")
        assert (info.seed, info.size_m, info.parked_variants) == (
            preset.seed,
            preset.size_m,
            preset.n_parked_variants,
        )
        assert (info.road_width_m, info.lane_width_m) == (
            preset.style.road_width_m,
            preset.style.lane_width_m,
        )
    st = DEFAULT_STYLE  # the values the module docstring promises
    assert (st.road_width_m, st.lane_width_m, st.junction_radius_m, st.ramp_start_m) == (8.0, 3.5, 8.0, 7.5)
    assert st.max_grade_m_per_m == 0.025 and st.relief_peak_to_peak_m == 1.3
    assert (st.flat_half_width_m, st.relief_blend_m, st.building_min_offset_m) == (9.5, 16.0, 9.5)
    assert (st.parking_offset_m, st.pole_offset_m, st.tree_offset_m) == (4.7, 6.6, 7.8)
    assert (st.block_pitch_m, st.max_block_pitch_m, st.node_jitter_frac) == (75.0, 85.0, (-0.12, 0.12))
    assert st.building_height_m == (4.0, 30.0) and st.lot_kind_prob == (0.72, 0.14, 0.14)
    assert (st.parked_car_length_m, st.parked_car_width_m, st.parked_car_height_m) == (
        (4.2, 4.8),
        (1.75, 1.9),
        (1.4, 1.6),
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        st.road_width_m = 9.0  # type: ignore[misc]


def test_every_style_field_has_a_unit_and_a_docstring():
    body = ast.parse(inspect.getsource(TownStyle)).body[0].body
    documented = {
        stmt.target.id
        for stmt, nxt in itertools.pairwise(body)
        if isinstance(stmt, ast.AnnAssign)
        and isinstance(nxt, ast.Expr)
        and isinstance(nxt.value, ast.Constant)
        and isinstance(nxt.value.value, str)
        and nxt.value.value.strip()
    }
    names = [f.name for f in dataclasses.fields(TownStyle)]
    assert set(names) == documented
    unit = re.compile(r".+_(m|m2|deg|m_per_m|count|frac|prob|shape)")
    words = [f.name for f in dataclasses.fields(TownStyle) if f.type == "str"]  # a choice has no unit
    assert words == ["layout"]
    assert [n for n in names if not unit.fullmatch(n) and n not in words] == []


def test_a_custom_style_changes_the_town_as_it_says(tmp_path):
    # 200 m, default style: span 200 - 2 * 25 = 150 m -> round(150 / 75) + 1 = 3 junctions a side, 75 m apart
    default = load_town_info(SCENES / "town_small.yaml")
    assert len(default.nodes) == 9 and len(default.edges) < 12  # roads removed from the 3 x 3 grid
    # bigger blocks and wider roads: round(150 / 150) + 1 = 2 junctions a side, 150 m apart: one square block
    big = dataclasses.replace(
        DEFAULT_STYLE, block_pitch_m=150.0, max_block_pitch_m=160.0, road_width_m=10.0, lane_width_m=4.5
    )
    info = generate_town(1, 200.0, tmp_path / "big.xml", style=big)
    assert len(info.nodes) == 4 and sorted(map(tuple, info.edges)) == [(0, 1), (0, 2), (1, 3), (2, 3)]
    grid = np.array([[-75.0, -75.0], [75.0, -75.0], [-75.0, 75.0], [75.0, 75.0]])
    assert np.abs(info.nodes - grid).max() <= 0.12 * 150.0 + 1e-3
    assert (info.road_width_m, info.lane_width_m) == (10.0, 4.5)
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "big.xml"))
    for e in range(4):
        assert m.geom(f"road_{e}").size[1] == pytest.approx(5.0)  # half the road width
    x, y, _ = info.spawn
    assert _seg_dist(np.array([[x, y]]), *info.segments()).min() == pytest.approx(2.25, abs=0.05)
    header = (tmp_path / "big.xml").read_text().splitlines()[1]
    assert "style=TownStyle(road_width_m=10.0, lane_width_m=4.5, block_pitch_m=150.0" in header
    # no roads removed: the full 3 x 3 grid, 2 * 3 * 2 = 12 roads
    full = generate_town(1, 200.0, tmp_path / "full.xml", style=TownStyle(removed_roads_frac=0.0))
    assert len(full.nodes) == 9 and len(full.edges) == 12
    np.testing.assert_array_equal(full.nodes, default.nodes)  # the same draws up to the removal


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"road_width_m": -8.0}, "road_width_m"),
        ({"lane_width_m": 0.0}, "lane_width_m"),
        ({"wall_thickness_m": -0.3}, "wall_thickness_m"),
        ({"lot_width_m": (24.0, 10.0)}, "lot_width_m"),
        ({"building_height_m": (30.0, 4.0)}, "building_height_m"),
        ({"parked_car_yaw_jitter_deg": (2.0, -2.0)}, "parked_car_yaw_jitter_deg"),
        ({"pole_spacing_m": (-5.0, 38.0)}, "pole_spacing_m"),
        ({"node_jitter_frac": (0.1,)}, "node_jitter_frac"),
        ({"lot_kind_prob": (0.5, 0.2, 0.2)}, "lot_kind_prob"),
        ({"l_shape_prob": 1.5}, "l_shape_prob"),
        ({"relief_waves_count": 0}, "relief_waves_count"),
        ({"pole_radius_m": float("nan")}, "pole_radius_m"),
        ({"tree_gap_m": "wide"}, "tree_gap_m"),
    ],
)
def test_invalid_style_is_one_line_naming_the_field(change, field):
    for make in (lambda: TownStyle(**change), lambda: dataclasses.replace(DEFAULT_STYLE, **change)):
        with pytest.raises(InputError) as exc:
            make()
        msg = str(exc.value)
        assert msg.startswith(f"TownStyle.{field} ") and "\n" not in msg, msg


def test_png_round_trip_through_pillow(tmp_path, town):
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, size=(37, 53, 3), dtype=np.uint8)  # (H, W, 3), odd sizes
    path = tmp_path / "x.img"
    mjcf.write_png(path, img)
    back = Image.open(path)
    assert back.format == "PNG" and back.mode == "RGB"
    np.testing.assert_array_equal(np.asarray(back), img)
    mjcf.write_png(tmp_path / "y.img", img)
    assert (tmp_path / "y.img").read_bytes() == path.read_bytes()  # deterministic
    # the town's texture as MuJoCo decodes it is the array pillow reads back
    info, m = town
    tex = np.asarray(Image.open(info.yaml_path.parent / "t_ground.img"))
    t = m.texture("ground").id
    h, w, c = m.tex_height[t], m.tex_width[t], m.tex_nchannel[t]
    assert tex.shape == (h, w, c) == (300, 300, 3)  # 150 m at 0.5 m per pixel
    np.testing.assert_array_equal(m.tex_data[m.tex_adr[t] : m.tex_adr[t] + h * w * c].reshape(h, w, c), tex)


def _one_line_naming(exc: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(exc.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def test_load_town_info_errors_name_the_file(tmp_path, town):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(InputError) as exc:
        load_town_info(missing)
    assert "not found" in _one_line_naming(exc, missing)

    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(InputError) as exc:
        load_town_info(bad)
    assert "YAML" in _one_line_naming(exc, bad)

    bad.write_text("- a list\n")
    with pytest.raises(InputError) as exc:
        load_town_info(bad)
    assert "mapping" in _one_line_naming(exc, bad)

    info, _ = town
    src = info.yaml_path
    work = tmp_path / "w"
    work.mkdir()
    shutil.copy(src.parent / info.terrain.file, work / info.terrain.file)
    doc = yaml.safe_load(src.read_text())

    def broken(mutate) -> Path:
        d = yaml.safe_load(yaml.safe_dump(doc))
        mutate(d)
        p = work / "t.yaml"
        p.write_text(yaml.safe_dump(d))
        return p

    cases = [
        (lambda d: d.pop("spawn"), "spawn"),
        (lambda d: d["roads"].pop("edges"), "edges"),
        (lambda d: d["roads"].__setitem__("nodes", [[1, 2, 3]]), "roads.nodes"),
        (lambda d: d["roads"].__setitem__("edges", [[0, 999]]), "roads.edges"),
        (lambda d: d.__setitem__("seed", "one"), "seed"),
        (lambda d: d["terrain"].__setitem__("nrow", 3), "terrain file"),
        (lambda d: d["terrain"].__setitem__("hfield_file", "gone.bin"), "gone.bin"),
    ]
    for mutate, word in cases:
        p = broken(mutate)
        with pytest.raises(InputError) as exc:
            load_town_info(p)
        assert word in _one_line_naming(exc, p)
    ok = load_town_info(broken(lambda d: None))
    np.testing.assert_array_equal(ok.edges, info.edges)
    assert ok.ground_height(3.0, -4.0) == info.ground_height(3.0, -4.0)


def test_generate_town_rejects_bad_arguments(tmp_path):
    with pytest.raises(InputError, match="seed"):
        generate_town(-1, SIZE, tmp_path / "t.xml")
    with pytest.raises(InputError, match="size_m"):
        generate_town(1, 20.0, tmp_path / "t.xml")
    with pytest.raises(InputError, match="n_parked_variants"):
        generate_town(1, SIZE, tmp_path / "t.xml", n_parked_variants=-2)
    with pytest.raises(InputError, match="TownStyle"):
        generate_town(1, SIZE, tmp_path / "t.xml", style={"road_width_m": 8.0})


def test_a_town_of_many_bodies_gets_the_arena_its_collision_step_needs():
    """MuJoCo's collision step takes a 2-byte-per-body-pair matrix from the arena: a city's thousands of
    parked-car bodies overflow the default (a 2 km town stopped with "mj_stackAlloc: out of memory").
    The size the generator writes is enough for a scene of that many bodies; small towns keep the default."""
    import mujoco

    from simbed.scenes.towngen.mjcf import arena_size

    assert arena_size(1499) == []
    n = 3000
    bodies = "".join(
        f'<body pos="{i % 60 * 3} {i // 60 * 3} 0.5"><geom type="box" size="0.5 0.5 0.5"/></body>'
        for i in range(n - 1)
    )

    def forward(size_lines: list[str]) -> None:
        xml = f"<mujoco>{''.join(size_lines)}<worldbody>{bodies}</worldbody></mujoco>"
        model = mujoco.MjModel.from_xml_string(xml)
        assert model.nbody == n
        mujoco.mj_forward(model, mujoco.MjData(model))

    forward(arena_size(n))
    with pytest.raises(mujoco.FatalError, match="out of memory"):
        forward(['<size memory="8M"/>'])  # the matrix alone takes 18 MB
