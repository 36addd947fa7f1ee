"""Routes on a town's road network: node walks, drivable lane polylines, and named route generators.

A route is a polyline of lane-centre points (metres, world x/y) that a car drives along. It comes from a
walk over the road graph's nodes: straight segments between junctions, offset into the right-hand lane,
with corners rounded by circular fillets so that a car can follow it at speed.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError


@dataclass(frozen=True)
class RoadGraph:
    """Junction nodes ``(K, 2)`` and two-way straight road edges ``(E, 2)`` (node index pairs)."""

    nodes: np.ndarray
    edges: np.ndarray

    def neighbours(self) -> list[list[int]]:
        adj: list[list[int]] = [[] for _ in range(len(self.nodes))]
        for i, j in self.edges:
            adj[int(i)].append(int(j))
            adj[int(j)].append(int(i))
        return [sorted(a) for a in adj]

    def shortest_path(self, start: int, goal: int, came_from: int | None = None) -> list[int]:
        """Node path from ``start`` to ``goal`` (fewest metres, Dijkstra). With ``came_from``, the path does
        not begin by driving back to that node (no U-turn) unless there is no other way."""
        adj = self.neighbours()
        if came_from is not None and start != goal:
            forward = [v for v in adj[start] if v != came_from]
            if forward:
                try:
                    return self._dijkstra([*adj[:start], forward, *adj[start + 1 :]], start, goal)
                except InputError:
                    pass  # only reachable by turning back
        return self._dijkstra(adj, start, goal)

    def _dijkstra(self, adj: list[list[int]], start: int, goal: int) -> list[int]:
        import heapq

        dist = {start: 0.0}
        prev: dict[int, int] = {}
        heap = [(0.0, start)]
        while heap:
            d, u = heapq.heappop(heap)
            if u == goal:
                break
            if d > dist.get(u, np.inf):
                continue
            for v in adj[u]:
                nd = d + float(np.linalg.norm(self.nodes[u] - self.nodes[v]))
                if nd < dist.get(v, np.inf):
                    dist[v] = nd
                    prev[v] = u
                    heapq.heappush(heap, (nd, v))
        if goal not in dist:
            raise InputError(f"no road connects node {start} to node {goal}")
        path = [goal]
        while path[-1] != start:
            path.append(prev[path[-1]])
        return path[::-1]


def covering_walk(graph: RoadGraph, start: int = 0) -> list[int]:
    """A closed node walk that drives every road at least once (for mapping runs).

    Greedy: keep driving unvisited roads from the current junction (no U-turns when avoidable); when none
    is left here, take the shortest path to the nearest junction that still has one; finally return to the
    start.
    """
    adj = graph.neighbours()
    todo = {frozenset((int(i), int(j))) for i, j in graph.edges}
    walk = [start]
    while todo:
        here = walk[-1]
        fresh = [v for v in adj[here] if frozenset((here, v)) in todo]
        if fresh:
            back = walk[-2] if len(walk) > 1 else None
            nxt = next((v for v in fresh if v != back), fresh[0])
            todo.discard(frozenset((here, nxt)))
            walk.append(nxt)
            continue
        # nearest junction with an undriven road, by breadth-first search over the graph
        seen, queue, found = {here: None}, deque([here]), None
        while queue and found is None:
            u = queue.popleft()
            for v in adj[u]:
                if v not in seen:
                    seen[v] = u
                    if any(frozenset((v, w)) in todo for w in adj[v]):
                        found = v
                        break
                    queue.append(v)
        if found is None:  # the rest is unreachable: the graph is not connected
            break
        path = graph.shortest_path(here, found, came_from=walk[-2] if len(walk) > 1 else None)
        todo.difference_update(frozenset(p) for p in pairwise(path))  # roads driven on the way count too
        walk.extend(path[1:])
    if walk[-1] != start:
        walk.extend(graph.shortest_path(walk[-1], start, came_from=walk[-2] if len(walk) > 1 else None)[1:])
    return walk


def random_walk(
    graph: RoadGraph, rng: np.random.Generator, n_edges: int, start: int | None = None
) -> list[int]:
    """A node walk of ``n_edges`` roads chosen at random at each junction, never turning back if avoidable."""
    adj = graph.neighbours()
    walk = [int(rng.integers(len(graph.nodes))) if start is None else start]
    for _ in range(n_edges):
        here = walk[-1]
        options = [v for v in adj[here] if len(walk) < 2 or v != walk[-2]] or adj[here]
        walk.append(int(rng.choice(options)))
    return walk


def lane_polyline(
    graph: RoadGraph, walk: list[int], lane_offset_m: float, corner_radius_m: float = 7.0, step_m: float = 0.5
) -> np.ndarray:
    """Lane-centre points ``(P, 2)`` along a node walk, ``lane_offset_m`` to the right of travel, with
    every corner rounded by a circular fillet of ``corner_radius_m`` (smaller where the roads are short),
    resampled every ``step_m``. U-turns (a walk that goes back where it came from) become half circles."""
    if len(walk) < 2:
        raise InputError("a route needs at least two junctions")
    pts = graph.nodes[np.asarray(walk)]
    segs = []
    for a, b in pairwise(pts):
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 1e-6:
            continue
        u = d / length
        right = np.array([u[1], -u[0]])
        segs.append((a + right * lane_offset_m, b + right * lane_offset_m, u, length))
    out = [segs[0][0]]
    for k, (a, b, u, length) in enumerate(segs):
        start = out[-1]
        end = b
        if k + 1 < len(segs):
            a2, _, u2, length2 = segs[k + 1]
            cross = u[0] * u2[1] - u[1] * u2[0]
            dot = float(np.clip(u @ u2, -1.0, 1.0))
            turn = np.arctan2(cross, dot)
            if abs(turn) > np.deg2rad(150):  # U-turn: half circle across both lanes
                radius = lane_offset_m
                end = b
                out.extend(_line(start, end, step_m)[1:])
                centre = b - np.array([u[1], -u[0]]) * radius
                out.extend(_arc(centre, end, turn=np.pi, radius=radius, left=True, step_m=step_m)[1:])
                continue
            if abs(turn) > np.deg2rad(5):
                # the two lane lines meet at a corner point; cut back by r·tan(turn/2) on both sides
                corner = _intersect(a, u, a2, u2)
                r = min(corner_radius_m, 0.45 * min(length, length2) / max(np.tan(abs(turn) / 2), 1e-6))
                cut = r * np.tan(abs(turn) / 2)
                p_in = corner - u * cut
                out.extend(_line(start, p_in, step_m)[1:])
                normal = np.array([-u[1], u[0]]) * np.sign(turn)  # toward the turn centre
                centre = p_in + normal * r
                out.extend(_arc(centre, p_in, turn=abs(turn), radius=r, left=turn > 0, step_m=step_m)[1:])
                continue
        out.extend(_line(start, end, step_m)[1:])
    poly = np.asarray(out)
    keep = np.ones(len(poly), bool)
    keep[1:] = np.linalg.norm(np.diff(poly, axis=0), axis=1) > 1e-6
    return poly[keep]


def _line(a: np.ndarray, b: np.ndarray, step_m: float) -> list[np.ndarray]:
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_m)))
    return [a + (b - a) * t for t in np.linspace(0.0, 1.0, n + 1)]


def _arc(centre, start, turn: float, radius: float, left: bool, step_m: float) -> list[np.ndarray]:
    a0 = np.arctan2(start[1] - centre[1], start[0] - centre[0])
    n = max(2, int(np.ceil(turn * radius / step_m)))
    sign = 1.0 if left else -1.0
    angles = a0 + sign * np.linspace(0.0, turn, n + 1)
    return [centre + radius * np.array([np.cos(t), np.sin(t)]) for t in angles]


def _intersect(p, u, q, v) -> np.ndarray:
    """Intersection of lines p + s·u and q + t·v (not parallel)."""
    m = np.array([[u[0], -v[0]], [u[1], -v[1]]])
    s, _ = np.linalg.solve(m, q - p)
    return p + s * u


@dataclass(frozen=True)
class Route:
    """A named lane polyline ``(P, 2)``, the node walk it came from (empty for waypoint files) and the
    speed limit at each point (m/s; NaN or ``None``: the driver's own choice)."""

    name: str
    points: np.ndarray
    walk: tuple[int, ...] = ()
    speeds: np.ndarray | None = None

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def start_pose(self) -> tuple[float, float, float]:
        """(x, y, yaw) of the route's first point, heading along it."""
        d = self.points[min(4, len(self.points) - 1)] - self.points[0]
        return float(self.points[0, 0]), float(self.points[0, 1]), float(np.arctan2(d[1], d[0]))


ROUTE_NAMES = ("mapping", "test", "test-N (N = seed)", "a waypoint file (.csv or .txt: x y per line)")


def make_route(
    name: str, graph: RoadGraph, lane_width_m: float, road_width_m: float, *, test_edges: int = 24
) -> Route:
    """A route by name: ``mapping`` (covers every road, closed loop), ``test`` / ``test-N`` (a random
    walk from another junction, seeded by N, default 1), or a path to a waypoint file (x y per line,
    in metres, which must lie on the road network)."""
    offset = lane_width_m / 2
    if name == "mapping":
        walk = covering_walk(graph, start=0)
        return Route(name, lane_polyline(graph, walk, offset), tuple(walk))
    if name == "test" or name.startswith("test-"):
        try:
            seed = int(name[5:]) if name.startswith("test-") else 1
        except ValueError:
            seed = -1
        if seed < 0:
            raise InputError(f"route {name!r}: expected test-N with an integer N >= 0")
        rng = np.random.default_rng(10_000 + seed)
        start = int(rng.integers(len(graph.nodes)))
        walk = random_walk(graph, rng, test_edges, start=start)
        return Route(name, lane_polyline(graph, walk, offset), tuple(walk))
    if is_waypoint_file(name):
        return waypoint_route(Path(name), graph, road_width_m)
    raise InputError(f"unknown route {name!r}; expected one of: {', '.join(ROUTE_NAMES)}")


def is_waypoint_file(name: str) -> bool:
    """Whether a route name is a waypoint file (rather than ``mapping``, ``test``, ``test-N``)."""
    path = Path(name)
    return path.suffix.lower() in (".csv", ".txt") or path.exists()


def waypoint_route(
    path: Path, graph: RoadGraph | None, road_width_m: float = 0.0, *, loop: bool = False
) -> Route:
    """A route from a waypoint file (:mod:`simbed.scenes.lanes`: the file is the lane, corners rounded, ``x y
    [speed]`` per line). With a road network, every waypoint must lie on a road (within half a road width
    of a road centre line), else an ``InputError`` names it."""
    from simbed.scenes.lanes import lane_from_waypoints, read_waypoints

    wp = read_waypoints(path)
    if graph is not None:
        load_waypoints(wp, graph, road_width_m)
    lane = lane_from_waypoints(wp, loop=loop)
    return Route(path.stem, lane.points, (), lane.speed)


def load_waypoints(wp, graph: RoadGraph, road_width_m: float) -> np.ndarray:
    """The waypoints ``(P, 2)`` of a :class:`simbed.scenes.lanes.Waypoints`, checked to lie on a road (within
    half a road width of a road centre line), else an ``InputError`` names the first that does not."""
    path, pts = wp.path, wp.xy
    dist = distance_to_roads(pts, graph)
    off = np.flatnonzero(dist > road_width_m / 2)
    if len(off):
        k = int(off[0])
        raise InputError(
            f"{path}: waypoint {k + 1} ({pts[k, 0]:.1f}, {pts[k, 1]:.1f}) is {dist[k]:.1f} m from the "
            "nearest "
            f"road centre line, off the road network ({len(off)} such waypoints)"
        )
    return pts


def distance_to_roads(points: np.ndarray, graph: RoadGraph) -> np.ndarray:
    """Distance ``(P,)`` from each point to the nearest road centre line."""
    a = graph.nodes[graph.edges[:, 0]]  # (E, 2)
    b = graph.nodes[graph.edges[:, 1]]
    ab = b - a
    t = np.clip(
        np.einsum("pek,ek->pe", points[:, None, :] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12),
        0.0,
        1.0,
    )
    closest = a[None] + t[..., None] * ab[None]  # (P, E, 2)
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)
