"""Routes on a road graph: coverage, lane geometry, and bad input."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from rangemcl.errors import InputError
from simbed.scenes.routes import (
    RoadGraph,
    covering_walk,
    distance_to_roads,
    lane_polyline,
    make_route,
    random_walk,
)


def grid_graph(n: int = 3, spacing: float = 60.0) -> RoadGraph:
    nodes = np.array([(i * spacing, j * spacing) for i in range(n) for j in range(n)], float)
    edges = []
    for i in range(n):
        for j in range(n):
            k = i * n + j
            if i + 1 < n:
                edges.append((k, k + n))
            if j + 1 < n:
                edges.append((k, k + 1))
    return RoadGraph(nodes, np.array(edges))


def test_covering_walk_drives_every_road_and_closes():
    g = grid_graph(4)
    walk = covering_walk(g, start=0)
    driven = {frozenset(p) for p in pairwise(walk)}
    assert driven == {frozenset(map(int, e)) for e in g.edges}
    assert walk[0] == walk[-1] == 0
    edges = {frozenset(map(int, e)) for e in g.edges}
    assert all(frozenset(p) in edges for p in pairwise(walk))  # only real roads


def test_random_walk_follows_roads_without_u_turns():
    g = grid_graph(4)
    walk = random_walk(g, np.random.default_rng(5), 40)
    edges = {frozenset(map(int, e)) for e in g.edges}
    assert all(frozenset(p) in edges for p in pairwise(walk))
    assert all(a != c for a, c in zip(walk[:-2], walk[2:], strict=True))  # every node here has degree >= 2


def test_lane_polyline_stays_in_the_right_lane_and_is_smooth():
    g = grid_graph(3)
    walk = covering_walk(g, start=0)
    offset = 1.75
    poly = lane_polyline(g, walk, offset, corner_radius_m=7.0, step_m=0.5)
    steps = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    assert steps.max() <= 0.5 + 1e-6  # continuous, resampled
    # every point is about one lane offset from a road centre line (fillets cut corners, U-turns cross)
    d = distance_to_roads(poly, g)
    assert np.median(d) == pytest.approx(offset, abs=1e-6)
    assert d.max() <= 7.0
    # heading changes smoothly: no kink sharper than the fillets allow at 0.5 m steps
    heading = np.unwrap(np.arctan2(np.diff(poly[:, 1]), np.diff(poly[:, 0])))
    assert np.abs(np.diff(heading)).max() < 0.5 / 1.75 + 0.05


def test_right_hand_lane():
    g = RoadGraph(np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([[0, 1]]))
    poly = lane_polyline(g, [0, 1], 1.75)
    assert np.allclose(poly[:, 1], -1.75)  # driving +x, the right lane is at -y


def test_named_routes_and_errors(tmp_path):
    g = grid_graph(3)
    mapping = make_route("mapping", g, 3.5, 8.0)
    test = make_route("test", g, 3.5, 8.0)
    assert mapping.length_m > 0.9 * 12 * 60  # covers all 12 roads
    assert not np.array_equal(test.points[:20], mapping.points[:20])
    assert make_route("test-3", g, 3.5, 8.0).walk != make_route("test-4", g, 3.5, 8.0).walk
    with pytest.raises(InputError, match="unknown route 'loop'"):
        make_route("loop", g, 3.5, 8.0)
    with pytest.raises(InputError, match="test-N"):
        make_route("test-x", g, 3.5, 8.0)
    good = tmp_path / "ok.txt"
    good.write_text("# x y\n0 1\n30, -2\n60 0\n")
    lane = make_route(str(good), g, 3.5, 8.0).points  # the file is the lane, resampled, corners rounded
    assert np.allclose(lane[0], (0, 1)) and np.allclose(lane[-1], (60, 0))
    assert np.linalg.norm(np.diff(lane, axis=0), axis=1).max() <= 0.5 + 1e-9
    assert np.linalg.norm(lane - np.array([30.0, -2.0]), axis=1).min() < 0.3  # points 0.5 m apart
    off = tmp_path / "off.txt"
    off.write_text("0 0\n30 30\n")
    with pytest.raises(InputError, match=r"off.txt: waypoint 2 .* off the road network"):
        make_route(str(off), g, 3.5, 8.0)
    bad = tmp_path / "bad.csv"
    bad.write_text("0 0\nzero one\n")
    with pytest.raises(InputError, match=r"bad.csv:2"):
        make_route(str(bad), g, 3.5, 8.0)
    with pytest.raises(InputError, match="cannot read"):
        make_route(str(tmp_path / "missing.csv"), g, 3.5, 8.0)
