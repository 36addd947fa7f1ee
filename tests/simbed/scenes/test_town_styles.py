"""The town generator's named styles (grid, suburb, mixed): road networks that keep their promises
(connected, no dead ends, loops, no crossings, roads apart), suburbs that wind off the grid, routes that keep
to the asphalt and clear of what stands beside it, the style in the sidecar, the same bytes for the same
seed, and a car that drives a suburb."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from rangemcl.datasets.kitti import load_sequence
from rangemcl.errors import InputError
from simbed.record import record
from simbed.scenes.routes import RoadGraph, distance_to_roads, make_route
from simbed.scenes.towngen import (
    DEFAULT_STYLE,
    TOWN_STYLES,
    TownStyle,
    generate_town,
    load_town_info,
    town_style,
)
from simbed.scenes.towngen.roads import road_graph

SCENES = Path(__file__).resolve().parents[3] / "scenes"
CASES = [(name, size, seed) for name in TOWN_STYLES for size in (200.0, 400.0) for seed in (1, 2)]


@pytest.fixture(scope="module")
def graphs() -> dict[tuple[str, float, int], tuple[np.ndarray, np.ndarray, int]]:
    """The road graph of every case: nodes (K, 2), edges (E, 2), the number of junctions (bends follow)."""
    return {case: road_graph(np.random.default_rng(case[2]), case[1], TOWN_STYLES[case[0]]) for case in CASES}


@pytest.fixture(scope="module")
def towns(tmp_path_factory) -> dict[str, tuple[object, mujoco.MjModel, mujoco.MjData]]:
    """A small town of each style: its TownInfo, model and data (after mj_forward)."""
    out = {}
    for name in TOWN_STYLES:
        xml = tmp_path_factory.mktemp(name) / f"{name}.xml"
        info = generate_town(3, 200.0, xml, style=name)
        m = mujoco.MjModel.from_xml_path(str(xml))
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        out[name] = (info, m, d)
    return out


# --------------------------------------------------------------------------------------------- helpers


def _points_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) distances from points (P, 2) to the segment a-b."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _samples(a: np.ndarray, b: np.ndarray, step_m: float = 0.5) -> np.ndarray:
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / step_m)) + 1)
    return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)


def _components(k: int, edges: np.ndarray) -> int:
    parent = list(range(k))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in edges:
        parent[root(int(i))] = root(int(j))
    return len({root(i) for i in range(k)})


def _roads_between_junctions(nodes: np.ndarray, edges: np.ndarray, n_junctions: int) -> list[list[int]]:
    """Node paths from junction to junction through bend nodes (index >= n_junctions)."""
    adj: dict[int, list[int]] = {i: [] for i in range(len(nodes))}
    for i, j in edges.tolist():
        adj[i].append(j)
        adj[j].append(i)
    roads, used = [], set()
    for start in range(n_junctions):
        for nxt in adj[start]:
            if frozenset((start, nxt)) in used:
                continue
            path = [start, nxt]
            used.add(frozenset((start, nxt)))
            while path[-1] >= n_junctions:
                here = path[-1]
                step = next(v for v in adj[here] if v != path[-2])
                used.add(frozenset((here, step)))
                path.append(step)
            roads.append(path)
    return roads


def _footprints(m: mujoco.MjModel, d: mujoco.MjData, pattern: str):
    """(name, centre xy, yaw, half sizes) of the geoms whose names match: boxes, and cylinders as squares."""
    rx = re.compile(pattern)
    out = []
    for g in range(m.ngeom):
        if rx.fullmatch(m.geom(g).name):
            rot = d.geom_xmat[g].reshape(3, 3)
            box = m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
            half = m.geom_size[g, :2] if box else np.full(2, m.geom_size[g, 0])
            out.append((m.geom(g).name, d.geom_xpos[g, :2].copy(), np.arctan2(rot[1, 0], rot[0, 0]), half))
    return out


def _rect_distance(p: np.ndarray, centre, yaw: float, half) -> np.ndarray:
    """(P,) distances from points (P, 2) to an oriented rectangle (negative inside)."""
    q = p - centre
    c, s = np.cos(yaw), np.sin(yaw)
    lx = np.abs(q[:, 0] * c + q[:, 1] * s) - half[0]
    ly = np.abs(-q[:, 0] * s + q[:, 1] * c) - half[1]
    outside = np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))
    return outside + np.minimum(np.maximum(lx, ly), 0.0)


# -------------------------------------------------------------------------------------------- the roads


@pytest.mark.parametrize("case", CASES, ids=[f"{n}-{s:.0f}m-seed{r}" for n, s, r in CASES])
def test_road_network_connected_no_dead_ends_loops_no_crossings(graphs, case):
    name, size, _ = case
    nodes, edges, n_junctions = graphs[case]
    style = TOWN_STYLES[name]
    k = len(nodes)
    assert _components(k, edges) == 1
    assert np.bincount(edges.ravel(), minlength=k).min() >= 2
    assert len(edges) - k + 1 >= 2  # independent loops
    assert len({tuple(e) for e in edges.tolist()}) == len(edges) and np.all(edges[:, 0] < edges[:, 1])
    assert np.all(np.abs(nodes) < size / 2 - 10.0)
    assert n_junctions <= k and (name != "grid" or n_junctions == k)
    # no two centre lines cross or come within a road width of each other, away from the nodes they share:
    # pieces that share no node keep the width everywhere; pieces that meet keep it beyond two disc radii
    width, keep_off = style.road_width_m, 2 * style.junction_radius_m
    lengths = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
    assert lengths.min() > 2 * style.ramp_start_m  # every road box has a ramp between its flat ends
    for (e, (i, j)), (f, (p, q)) in itertools.combinations(enumerate(edges.tolist()), 2):
        shared = {i, j} & {p, q}
        pts = _samples(nodes[i], nodes[j])
        if shared:
            (node,) = shared
            pts = pts[np.linalg.norm(pts - nodes[node], axis=1) > keep_off]
        if len(pts):
            d = _points_to_segment(pts, nodes[p], nodes[q]).min()
            assert d >= width, (name, e, f, d)


def test_suburb_is_no_grid_and_its_roads_wind(graphs):
    def axis_clustering(nodes, roads) -> float:
        """|mean of exp(4 i theta)| over the junction-to-junction chords: 1 on two right-angled axes."""
        chords = np.array([nodes[r[-1]] - nodes[r[0]] for r in roads])
        theta = np.arctan2(chords[:, 1], chords[:, 0])
        return float(np.abs(np.exp(4j * theta).mean()))

    for size, seed in itertools.product((200.0, 400.0), (1, 2)):
        nodes, edges, nj = graphs[("suburb", size, seed)]
        roads = _roads_between_junctions(nodes, edges, nj)
        pieces = sorted(tuple(sorted(p)) for r in roads for p in itertools.pairwise(r))
        assert pieces == sorted(map(tuple, edges.tolist()))  # the roads cover every piece once
        path = np.array(
            [sum(np.linalg.norm(nodes[b] - nodes[a]) for a, b in itertools.pairwise(r)) for r in roads]
        )
        chord = np.array([np.linalg.norm(nodes[r[-1]] - nodes[r[0]]) for r in roads])
        assert (path / chord).max() > 1.02, (size, seed)  # some road is longer than the straight line
        assert np.mean([len(r) > 2 for r in roads]) >= 0.5, (size, seed)  # most roads have bends
        if size == 400.0:  # enough roads for their directions to say something
            assert axis_clustering(nodes, roads) < 0.5, (size, seed)
            grid_nodes, grid_edges, gj = graphs[("grid", size, seed)]
            assert axis_clustering(grid_nodes, _roads_between_junctions(grid_nodes, grid_edges, gj)) > 0.8
    # mixed: the grid's junctions, some of its roads bent
    nodes, edges, nj = graphs[("mixed", 400.0, 1)]
    grid_nodes, _, _ = graphs[("grid", 400.0, 1)]
    np.testing.assert_array_equal(nodes[:nj], grid_nodes)
    roads = _roads_between_junctions(nodes, edges, nj)
    assert 0.15 <= np.mean([len(r) > 2 for r in roads]) <= 0.6


@pytest.mark.parametrize("case", CASES, ids=[f"{n}-{s:.0f}m-seed{r}" for n, s, r in CASES])
def test_routes_cover_the_roads_and_keep_to_the_asphalt(graphs, case):
    name, _, _ = case
    nodes, edges, _ = graphs[case]
    style = TOWN_STYLES[name]
    graph = RoadGraph(nodes, edges)
    mapping = make_route("mapping", graph, style.lane_width_m, style.road_width_m)
    driven = {frozenset(p) for p in itertools.pairwise(mapping.walk)}
    assert driven == {frozenset(e) for e in edges.tolist()} and mapping.walk[0] == mapping.walk[-1]
    assert all(frozenset(p) in driven for p in itertools.pairwise(make_route("test", graph, 3.5, 8.0).walk))
    for route in (mapping, make_route("test", graph, style.lane_width_m, style.road_width_m)):
        p = route.points
        to_road = distance_to_roads(p, graph)
        to_node = np.linalg.norm(p[:, None] - nodes[None], axis=-1).min(axis=1)
        on_asphalt = (to_road <= style.road_width_m / 2) | (to_node <= style.junction_radius_m)
        # a sharp turn's fillet (7 m radius) cuts the corner over the parking strip, next to the junction
        strip = style.parking_offset_m + style.parking_paint_beyond_m
        corner = (to_road <= strip) & (to_node <= 2 * style.junction_radius_m)
        assert np.all(on_asphalt | corner), (route.name, p[~(on_asphalt | corner)][:3])
        assert np.mean(on_asphalt) > 0.97
        assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() < 1.0  # no jumps


def test_routes_keep_clear_of_what_stands_beside_the_road(towns):
    for name, (info, m, d) in towns.items():
        graph = RoadGraph(info.nodes, info.edges)
        obstacles = _footprints(
            m, d, r"(pole_\d+|tree_\d+_trunk|parked_v\d+_\d+_body|bldg_\d+_[ab]|wall_\d+)"
        )
        assert len(obstacles) > 50, name
        for route_name in ("mapping", "test", "test-2"):
            pts = make_route(route_name, graph, info.lane_width_m, info.road_width_m).points
            nearest = min(_rect_distance(pts, c, yaw, half).min() for _, c, yaw, half in obstacles)
            assert nearest > 1.5, (name, route_name, nearest)  # the car is 1.8 m wide


# -------------------------------------------------------------------------------------- what each style is


def test_named_styles_differ_as_they_say(towns):
    assert TOWN_STYLES["grid"] is DEFAULT_STYLE and town_style("suburb") is TOWN_STYLES["suburb"]
    suburb, mixed = TOWN_STYLES["suburb"], TOWN_STYLES["mixed"]
    assert suburb.layout == "organic" and mixed.layout == "grid" and DEFAULT_STYLE.bent_road_prob == 0.0
    assert 0.0 < mixed.bent_road_prob < 1.0 and suburb.bent_road_prob > mixed.bent_road_prob
    assert suburb.building_height_m[1] <= 10.0 and suburb.parked_car_prob < DEFAULT_STYLE.parked_car_prob

    def heights(m, d, pattern):
        out = []
        for g in range(m.ngeom):
            if re.fullmatch(pattern, m.geom(g).name):
                out.append((np.linalg.norm(d.geom_xpos[g, :2]), d.geom_xpos[g, 2] + m.geom_size[g, 2]))
        return np.array(out)  # (N, 2): distance from the centre, top height

    info, m, d = towns["suburb"]
    top = heights(m, d, r"bldg_\d+_a")
    assert len(top) >= 10 and top[:, 1].max() <= 10.0 + 1.5  # low houses (tops over gentle relief)

    def trees(m):
        return sum(re.fullmatch(r"tree_\d+_trunk", m.geom(g).name) is not None for g in range(m.ngeom))

    assert trees(m) > 1.5 * trees(towns["grid"][1])  # more trees, and bigger ones
    assert TOWN_STYLES["suburb"].block_tree_crown_radius_m[1] > DEFAULT_STYLE.block_tree_crown_radius_m[1]
    info, m, d = towns["mixed"]
    top = heights(m, d, r"bldg_\d+_a")
    lo, hi = mixed.building_height_m
    r = np.clip(top[:, 0] - 30.0, 0.0, None) / (info.size_m / 2)  # a lot's front lies up to ~30 m nearer
    allowed = lo + (hi - lo) * (1.0 - (1.0 - mixed.building_height_outskirts_frac) * np.clip(r, 0.0, 1.0))
    assert np.all(top[:, 1] <= allowed + 1.5), top[top[:, 1] > allowed + 1.5]
    assert top[top[:, 0] > 80.0, 1].max() < top[top[:, 0] < 50.0, 1].max()  # taller in the centre


def test_sidecar_names_the_style_and_the_same_seed_writes_the_same_bytes(tmp_path, towns):
    files = ("t.xml", "t.yaml", "t_terrain.bin", "t_ground.img")
    generate_town(5, 150.0, tmp_path / "a" / "t.xml", style="suburb")
    generate_town(5, 150.0, tmp_path / "b" / "t.xml", style=TOWN_STYLES["suburb"])
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    doc = yaml.safe_load((tmp_path / "a" / "t.yaml").read_text())
    assert doc["style"] == "suburb" and load_town_info(tmp_path / "a" / "t.yaml").style == "suburb"
    assert "style='suburb'" in (tmp_path / "a" / "t.xml").read_text().splitlines()[1]
    assert towns["mixed"][0].style == "mixed" and towns["grid"][0].style == "grid"
    # the grid's sidecar is as it always was (no style key) and reads as grid, as older sidecars do
    assert "style" not in yaml.safe_load((SCENES / "town_small.yaml").read_text())
    assert load_town_info(SCENES / "town_small.yaml").style == "grid"
    info = generate_town(5, 120.0, tmp_path / "d" / "t.xml", style=TownStyle(removed_roads_frac=0.1))
    assert info.style == "custom" and load_town_info(tmp_path / "d" / "t.yaml").style == "custom"
    text = (tmp_path / "a" / "t.yaml").read_text().replace("style: suburb", "style: [1]")
    (tmp_path / "a" / "t.yaml").write_text(text)
    with pytest.raises(InputError, match=r"t\.yaml: style must be"):
        load_town_info(tmp_path / "a" / "t.yaml")


def test_bad_style_is_one_line_naming_the_choices(tmp_path):
    for bad in ("hex", "Grid", ""):
        with pytest.raises(InputError) as exc:
            generate_town(1, 200.0, tmp_path / "t.xml", style=bad)
        msg = str(exc.value)
        assert "\n" not in msg and "grid, suburb, mixed" in msg and repr(bad) in msg
    assert not (tmp_path / "t.xml").exists()
    with pytest.raises(InputError) as exc:
        TownStyle(layout="hexagonal")
    assert str(exc.value) == "TownStyle.layout must be one of 'grid', 'organic', got 'hexagonal'"
    for field, value in (
        ("bent_road_prob", 1.5),
        ("bend_piece_m", (0.0, 30.0)),
        ("junction_spacing_m", -1.0),
    ):
        with pytest.raises(InputError, match=rf"^TownStyle\.{field} "):
            TownStyle(**{field: value})


def test_a_car_drives_a_suburb(tmp_path, towns):
    info, _, _ = towns["suburb"]
    out = tmp_path / "run"
    summary = record(str(info.xml_path), "test", "vlp-16", out, frames=25, actors=2, variant=1, seed=3,
                     progress=False)  # fmt: skip
    assert summary.frames == 25 and summary.stuck_at is None and summary.distance_driven_m > 5.0
    seq = load_sequence(out, require_poses=True)
    assert len(seq) == 25 and seq.meta["route"] == "test"
    graph = RoadGraph(info.nodes, info.edges)
    assert distance_to_roads(seq.poses[:, :2, 3], graph).max() < info.road_width_m / 2
