"""simbed.towngen: seeded towns whose roads, terrain, buildings and parked cars keep their promises."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from rangemcl.errors import InputError
from simbed.towngen import (
    SHIPPED_TOWNS,
    TownInfo,
    generate_town,
    load_town_info,
    parked_variant_bodies,
    use_parked_variant,
)

SCENES = Path(__file__).resolve().parents[2] / "scenes"
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
    seed, size = SHIPPED_TOWNS["town_small"]
    generate_town(seed, size, tmp_path / "town_small.xml")
    for f in ("town_small.xml", "town_small.yaml", "town_small_terrain.bin", "town_small_ground.img"):
        assert (tmp_path / f).read_bytes() == (SCENES / f).read_bytes(), f"{f} is stale: run towngen"


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
