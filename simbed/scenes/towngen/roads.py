"""The road network and the ground under it: the road graph (:func:`road_graph`), the natural relief, the
height field that equals the road surface near the roads (:func:`town_terrain`), the road boxes and junction
discs (:func:`road_surfaces`) and the spawn pose (:func:`spawn_pose`)."""

from __future__ import annotations

import itertools
import math
from collections import defaultdict
from collections.abc import Callable

import numpy as np

from rangemcl.errors import InputError
from simbed.scenes.towngen.geometry import Box
from simbed.scenes.towngen.info import Terrain
from simbed.scenes.towngen.style import TownStyle

# ------------------------------------------------------------------------------------------------ road graph


def _connected(n: int, edges: list[tuple[int, int]]) -> bool:
    adj: dict[int, list[int]] = defaultdict(list)
    for i, j in edges:
        adj[i].append(j)
        adj[j].append(i)
    seen = {0}
    stack = [0]
    while stack:
        for j in adj[stack.pop()]:
            if j not in seen:
                seen.add(j)
                stack.append(j)
    return len(seen) == n


def road_graph(
    rng: np.random.Generator, size_m: float, style: TownStyle
) -> tuple[np.ndarray, np.ndarray, int]:
    """Road nodes ``(K, 2)``, edges ``(E, 2)`` (sorted node index pairs, each a straight road piece) and the
    number of junctions, the nodes before the bend nodes.

    The junctions of ``style.layout`` (:func:`grid_graph` or :func:`organic_graph`), some of their roads
    removed (:func:`remove_roads`: connected, every node of degree >= 2, loops kept), then with
    ``style.bent_road_prob`` > 0 roads bent into pieces (:func:`bend_roads`, whose bend nodes follow the
    junctions). A grid without bends draws from ``rng`` exactly as the shipped towns were drawn.
    """
    if style.layout == "organic":
        nodes, edges = organic_graph(rng, size_m, style)
    else:
        nodes, edges = grid_graph(rng, size_m, style)
    n_junctions = len(nodes)
    if style.bent_road_prob > 0:
        nodes, edges = bend_roads(rng, nodes, edges, style, size_m)
    return nodes, edges, n_junctions


def grid_graph(rng: np.random.Generator, size_m: float, style: TownStyle) -> tuple[np.ndarray, np.ndarray]:
    """A jittered grid of junctions ``block_pitch_m`` apart, some of its roads removed."""
    span = size_m - 2 * style.graph_margin_m
    n = max(2, round(span / style.block_pitch_m) + 1)
    spacing = min(span / (n - 1), style.max_block_pitch_m)
    grid = (np.arange(n) - (n - 1) / 2) * spacing
    gx, gy = np.meshgrid(grid, grid)  # node k = row * n + col, row along y
    nodes = np.stack([gx.ravel(), gy.ravel()], axis=1)
    nodes = nodes + rng.uniform(*style.node_jitter_frac, size=nodes.shape) * spacing
    nodes = np.round(nodes, 3)
    edges = [(r * n + c, r * n + c + 1) for r in range(n) for c in range(n - 1)]
    edges += [(r * n + c, (r + 1) * n + c) for r in range(n - 1) for c in range(n)]
    edges = remove_roads(rng, len(nodes), edges, style)
    return nodes, np.array(sorted(edges), dtype=np.int64)


def remove_roads(
    rng: np.random.Generator, k: int, edges: list[tuple[int, int]], style: TownStyle
) -> list[tuple[int, int]]:
    """``edges`` less ``style.removed_roads_frac`` of them drawn at random, as far as the graph of ``k`` nodes
    stays connected, keeps every node's degree >= 2 and keeps its least number of independent loops."""
    loops = len(edges) - k + 1
    min_loops = min(loops, max(style.min_loops_count, math.floor(loops * style.min_loops_frac)))
    n_remove = int(round(style.removed_roads_frac * len(edges)))
    removed = 0
    candidates = list(edges)
    for idx in rng.permutation(len(edges)).tolist():
        if removed >= n_remove or len(edges) - 1 - k + 1 < min_loops:
            break
        e = candidates[idx]
        trial = [f for f in edges if f != e]
        deg = np.bincount(np.array(trial).ravel(), minlength=k)
        if deg.min() >= 2 and _connected(k, trial):
            edges = trial
            removed += 1
    return edges


# ------------------------------------------------------------------------------------------ organic layout


def organic_graph(rng: np.random.Generator, size_m: float, style: TownStyle) -> tuple[np.ndarray, np.ndarray]:
    """Scattered junctions (:func:`poisson_disc`) joined by their Delaunay triangulation less the roads that
    are too long (``max_road_length_m``), leave a node at a sharp angle (``min_road_angle_deg``) or come too
    near another road (``road_clearance_m``); nodes left with fewer than two roads go, the largest connected
    part stays, then roads are removed as on the grid (:func:`remove_roads`). Where fewer than three roads
    are left (a small town), junctions are drawn again, each time 3 % closer together."""
    half = size_m / 2 - style.graph_margin_m
    for k in range(_ORGANIC_TRIES):
        spacing = style.junction_spacing_m * (1.0 - 0.03 * k)
        points = poisson_disc(rng, half, spacing, style.junction_candidates_count)
        points = np.round(points, 3)
        nodes, edges = _planar_roads(points, style) if len(points) >= 3 else (points, [])
        if len(edges) >= 3:
            break
    else:
        raise InputError(
            f"a {size_m:g} m town has no room for an organic road network with junctions "
            f"{style.junction_spacing_m:g} m apart; make the town larger or junction_spacing_m smaller"
        )
    edges = remove_roads(rng, len(nodes), edges, style)
    return nodes, np.array(sorted(edges), dtype=np.int64)


_ORGANIC_TRIES = 20  # fresh junction samples before a town too small for its spacing is refused


def poisson_disc(rng: np.random.Generator, half: float, spacing: float, per_cell: int) -> np.ndarray:
    """Points ``(K, 2)`` in ``[-half, half]²``, pairwise at least ``spacing`` apart (dart throwing:
    ``per_cell`` uniform candidates per ``spacing``² of area, each kept if it keeps the spacing)."""
    n = max(1, math.ceil(per_cell * (2 * half) ** 2 / spacing**2))
    cand = rng.uniform(-half, half, size=(n, 2))  # (N, 2)
    cell = spacing / math.sqrt(2)  # at most one kept point per cell
    buckets: dict[tuple[int, int], np.ndarray] = {}
    kept = []
    for p in cand:
        ci, cj = int((p[0] + half) // cell), int((p[1] + half) // cell)
        near = [
            buckets[(ci + di, cj + dj)]
            for di in range(-2, 3)
            for dj in range(-2, 3)
            if (ci + di, cj + dj) in buckets
        ]
        if all(float(np.hypot(*(p - q))) >= spacing for q in near):
            buckets[(ci, cj)] = p
            kept.append(p)
    return np.array(kept).reshape(-1, 2)


def _planar_roads(points: np.ndarray, style: TownStyle) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The Delaunay roads between ``points`` that keep the organic layout's rules, on the nodes they keep."""
    from scipy.spatial import Delaunay

    try:
        tri = Delaunay(points)
    except Exception:  # scipy's QhullError: all points on a line
        return points, []
    sides = {(min(p, q), max(p, q)) for tri_nodes in tri.simplices.tolist() for p, q in _sides(tri_nodes)}
    edges = [e for e in sorted(sides) if _length(points, e) <= style.max_road_length_m]
    min_angle = math.radians(style.min_road_angle_deg)
    while True:  # drop the longer road of every pair too sharp at a node or too near, until none is left
        bad = _sharp_pairs(points, edges, min_angle) + _near_pairs(points, edges, style.road_clearance_m)
        drop = {max(e, f, key=lambda g: (_length(points, g), g)) for e, f in bad}
        if not drop:
            break
        edges = [e for e in edges if e not in drop]
    while True:  # no dead ends
        deg = np.bincount(np.array(edges, dtype=np.int64).ravel(), minlength=len(points))
        if not edges or deg[np.array(edges).ravel()].min() >= 2:
            break
        edges = [(i, j) for i, j in edges if deg[i] >= 2 and deg[j] >= 2]
    if not edges:
        return points, []
    part = _largest_part(len(points), edges)
    index = {old: new for new, old in enumerate(part)}
    return points[part], [(index[i], index[j]) for i, j in edges if i in index]


def _sides(tri_nodes: list[int]) -> list[tuple[int, int]]:
    a, b, c = tri_nodes
    return [(a, b), (b, c), (a, c)]


def _length(nodes: np.ndarray, e: tuple[int, int]) -> float:
    return float(np.linalg.norm(nodes[e[1]] - nodes[e[0]]))


def _largest_part(n: int, edges: list[tuple[int, int]]) -> list[int]:
    """The sorted nodes of the largest connected part of the graph that ``edges`` make (ties: lowest node)."""
    adj: dict[int, list[int]] = defaultdict(list)
    for i, j in edges:
        adj[i].append(j)
        adj[j].append(i)
    best: list[int] = []
    seen: set[int] = set()
    for start in sorted(adj):
        if start in seen:
            continue
        part, stack = {start}, [start]
        while stack:
            for j in adj[stack.pop()]:
                if j not in part:
                    part.add(j)
                    stack.append(j)
        seen |= part
        if len(part) > len(best):
            best = sorted(part)
    return best


def _sharp_pairs(nodes: np.ndarray, edges: list[tuple[int, int]], min_angle: float):
    """Pairs of edges that leave a common node at an angle below ``min_angle`` (radians)."""
    out = []
    at: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for e in edges:
        at[e[0]].append(e)
        at[e[1]].append(e)
    for k, es in at.items():
        for e, f in itertools.combinations(es, 2):
            if _angle_at(nodes, k, e, f) < min_angle:
                out.append((e, f))
    return out


def _angle_at(nodes: np.ndarray, k: int, e: tuple[int, int], f: tuple[int, int]) -> float:
    u = nodes[e[0] + e[1] - k] - nodes[k]
    v = nodes[f[0] + f[1] - k] - nodes[k]
    c = float(u @ v) / max(float(np.linalg.norm(u) * np.linalg.norm(v)), 1e-12)
    return math.acos(min(1.0, max(-1.0, c)))


def _near_pairs(nodes: np.ndarray, edges: list[tuple[int, int]], clearance: float):
    """Pairs of edges that share no node and come closer than ``clearance``."""
    if len(edges) < 2:
        return []
    e = np.array(edges)
    a, b = nodes[e[:, 0]], nodes[e[:, 1]]
    out = []
    for i in range(len(edges) - 1):
        d = segment_distances(a[i], b[i], a[i + 1 :], b[i + 1 :])
        shared = (e[i + 1 :, :, None] == e[i][None, None, :]).any(axis=(1, 2))
        for j in np.flatnonzero((d < clearance) & ~shared):
            out.append((edges[i], edges[i + 1 + int(j)]))
    return out


def segment_distances(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances ``(E,)`` between segment p-q ``(2,)`` and segments a-b ``(E, 2)`` (0 where they cross)."""

    def point_seg(x, s, t):  # (E,) distance from points x to segments s-t, all (E, 2)
        st = t - s
        w = np.clip(((x - s) * st).sum(-1) / np.maximum((st * st).sum(-1), 1e-12), 0.0, 1.0)
        return np.linalg.norm(x - (s + w[:, None] * st), axis=-1)

    pp, qq = np.broadcast_to(p, a.shape), np.broadcast_to(q, a.shape)
    ends = [point_seg(pp, a, b), point_seg(qq, a, b), point_seg(a, pp, qq), point_seg(b, pp, qq)]
    d = np.minimum.reduce(ends)

    def cross(o, x, y):  # (E,) z of (x - o) × (y - o)
        ox, oy = x - o, y - o
        return ox[..., 0] * oy[..., 1] - ox[..., 1] * oy[..., 0]

    d1, d2 = cross(a, b, pp), cross(a, b, qq)
    d3, d4 = cross(pp, qq, a), cross(pp, qq, b)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    return np.where(crossing, 0.0, d)


# ------------------------------------------------------------------------------------------------ bends


def bend_roads(
    rng: np.random.Generator, nodes: np.ndarray, edges: np.ndarray, style: TownStyle, size_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Bend each road with probability ``style.bent_road_prob``: cut it into pieces of about
    ``bend_piece_m`` joined at new bend nodes (appended after the junctions) displaced sideways along an arc
    or an S of amplitude ``bend_amplitude_frac`` of its length. A bend that would leave a node at an angle
    below ``min_road_angle_deg``, come within ``road_clearance_m`` of a road piece it shares no node with or
    put a bend node nearer the town's border than half ``graph_margin_m`` is tried on the other side, then at
    half the amplitude (both sides), else the road stays straight. Every road draws the same numbers
    whether or not it is bent."""
    pts = list(nodes)
    at: dict[int, set[tuple[int, int]]] = defaultdict(set)  # node -> the pieces that end there
    for i, j in edges.tolist():
        at[i].add((i, j))
        at[j].add((i, j))
    min_angle = math.radians(style.min_road_angle_deg)
    limit = size_m / 2 - style.graph_margin_m / 2
    for i, j in edges.tolist():
        bent = rng.random() < style.bent_road_prob
        piece = rng.uniform(*style.bend_piece_m)
        amp_frac = rng.uniform(*style.bend_amplitude_frac)
        side = 1.0 if rng.random() < 0.5 else -1.0
        s_curve = rng.random() < style.bend_s_curve_prob
        a, b = pts[i], pts[j]
        length = float(np.linalg.norm(b - a))
        count = min(round(length / piece), math.floor(length / style.bend_piece_m[0]))
        if not bent or count < 2:
            continue
        u = (b - a) / length
        n = np.array([-u[1], u[0]])
        t = np.arange(1, count) / count
        shape = np.sin(2 * np.pi * t) if s_curve else np.sin(np.pi * t)
        at[i].discard((i, j))
        at[j].discard((i, j))
        others = sorted(set().union(*at.values()))
        for scale in (1.0, -1.0, 0.5, -0.5):
            offset = side * scale * amp_frac * length * shape  # (count - 1,) sideways, metres
            inner = np.round(a + t[:, None] * (b - a) + offset[:, None] * n, 3)  # (count - 1, 2)
            path = [i, *range(len(pts), len(pts) + len(inner)), j]
            new = [(min(p, q), max(p, q)) for p, q in itertools.pairwise(path)]
            trial = np.array(pts + list(inner))
            if np.abs(inner).max() <= limit and _bend_fits(trial, new, others, at, min_angle, style):
                pts = list(trial)
                break
        else:
            new = [(i, j)]
        for e in new:
            at[e[0]].add(e)
            at[e[1]].add(e)
    segs = sorted(set().union(*at.values()))
    return np.array(pts), np.array(segs, dtype=np.int64)


def _bend_fits(nodes, new, others, at, min_angle: float, style: TownStyle) -> bool:
    """Whether the pieces ``new`` keep ``min_angle`` with every piece that shares a node with them and
    ``road_clearance_m`` from every piece (of ``others`` or ``new``) that shares none; ``at`` maps a node to
    the pieces of ``others`` that end there."""
    for e in new:
        for k in e:
            beside = [f for f in new if f != e and k in f] + list(at.get(k, ()))
            if any(_angle_at(nodes, k, e, f) < min_angle for f in beside):
                return False
    every = np.array(others + new)  # (E, 2)
    a, b = nodes[every[:, 0]], nodes[every[:, 1]]
    for e in new:
        d = segment_distances(nodes[e[0]], nodes[e[1]], a, b)
        shared = (every == e[0]).any(axis=1) | (every == e[1]).any(axis=1)
        if np.any((d < style.road_clearance_m) & ~shared):
            return False
    return True


def node_heights(nodes, edges, natural, max_grade: float, ramp_start_m: float) -> np.ndarray:
    """Node heights: the natural relief, relaxed until every road's grade is at most ``max_grade``."""
    h = natural(nodes[:, 0], nodes[:, 1]).astype(np.float64)
    length = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
    allowed = 0.98 * max_grade * (length - 2 * ramp_start_m)  # 2 % to spare
    for _ in range(10000):
        dh = h[edges[:, 1]] - h[edges[:, 0]]
        excess = np.abs(dh) - allowed
        if excess.max() <= 0:
            break
        fix = np.where(excess > 0, np.sign(dh) * excess / 2 * 1.01, 0.0)
        np.add.at(h, edges[:, 0], fix)
        np.add.at(h, edges[:, 1], -fix)
    return np.round(h, 4)


# -------------------------------------------------------------------------------------------------- terrain


def natural_relief(rng: np.random.Generator, style: TownStyle):
    """A smooth random relief: a sum of long-wavelength plane waves; returns f(x, y) -> z."""
    k = style.relief_waves_count
    wavelength = rng.uniform(*style.relief_wavelength_m, k)
    theta = rng.uniform(0, 2 * np.pi, k)
    phase = rng.uniform(0, 2 * np.pi, k)
    amp = rng.uniform(*style.relief_wave_weight_frac, k)
    kx = 2 * np.pi / wavelength * np.cos(theta)
    ky = 2 * np.pi / wavelength * np.sin(theta)

    def f(x, y):
        x = np.asarray(x, float)[..., None]
        y = np.asarray(y, float)[..., None]
        return (amp * np.sin(kx * x + ky * y + phase)).sum(-1)

    return f


def _road_profile(s, length, ha, hb, ramp_start_m: float):
    """Road surface height at arc length s along an edge: flat near the nodes, one grade between."""
    t = np.clip((s - ramp_start_m) / (length - 2 * ramp_start_m), 0.0, 1.0)
    return ha + (hb - ha) * t


def terrain_grid(xs, ys, nodes, edges, hnode, natural, relief_scale, style: TownStyle) -> np.ndarray:
    flat = style.flat_half_width_m
    a = nodes[edges[:, 0]]
    b = nodes[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    u = (b - a) / length[:, None]
    ha, hb = hnode[edges[:, 0]], hnode[edges[:, 1]]
    out = np.empty((len(ys), len(xs)))
    for r, y in enumerate(ys):
        p = np.stack([xs, np.full_like(xs, y)], axis=1)  # (N, 2)
        rel = p[:, None, :] - a[None, :, :]  # (N, E, 2)
        s = (rel * u[None]).sum(-1)
        lat = np.abs(rel[..., 0] * u[None, :, 1] - rel[..., 1] * u[None, :, 0])
        in_span = (s >= 0) & (s <= length[None])
        dseg = np.where(
            in_span,
            lat,
            np.minimum(np.linalg.norm(rel, axis=-1), np.linalg.norm(p[:, None, :] - b[None], axis=-1)),
        )
        prof = _road_profile(s, length[None], ha[None], hb[None], style.ramp_start_m)
        cand = np.where(in_span & (lat <= flat), prof, -np.inf).max(axis=1)
        dnode = np.linalg.norm(p[:, None, :] - nodes[None], axis=-1)
        cand = np.maximum(cand, np.where(dnode <= flat, hnode[None], -np.inf).max(axis=1))
        nearest = dseg.argmin(axis=1)
        dist = dseg[np.arange(len(p)), nearest]
        road = np.where(np.isfinite(cand), cand, prof[np.arange(len(p)), nearest])
        t = np.clip((dist - flat) / style.relief_blend_m, 0.0, 1.0)
        w = t * t * (3 - 2 * t)
        nat = natural(p[:, 0], p[:, 1]) * relief_scale
        out[r] = road + w * (nat - road)
    return out


# ------------------------------------------------------------------------------------------------ the town


def town_terrain(
    rng: np.random.Generator, size_m: float, nodes, edges, style: TownStyle, file: str
) -> tuple[Terrain, np.ndarray, Callable]:
    """The town's height field (written to ``file``), drawing the natural relief from ``rng``.

    Returns the :class:`Terrain`, the node heights (the relief at the nodes, relaxed until every road keeps
    ``style.max_grade_m_per_m``) and the natural relief ``f(x, y) -> z``, scaled to
    ``style.relief_peak_to_peak_m``.
    """
    relief = natural_relief(rng, style)
    fine = size_m <= style.fine_max_size_m
    cell = style.terrain_cell_m if fine else style.coarse_terrain_cell_m
    n = round(size_m / cell) + 1
    xs = np.linspace(-size_m / 2, size_m / 2, n)
    probe = relief(*np.meshgrid(xs[::4], xs[::4]))
    relief_scale = style.relief_peak_to_peak_m / float(probe.max() - probe.min())

    def natural(x, y):
        return relief(x, y) * relief_scale

    hnode = node_heights(nodes, edges, natural, style.max_grade_m_per_m, style.ramp_start_m)
    grid = terrain_grid(xs, xs, nodes, edges, hnode, relief, relief_scale, style)
    gmin, gmax = float(grid.min()), float(grid.max())
    data = ((grid - gmin) / (gmax - gmin)).astype(np.float32)
    data = np.clip(data, 0.0, 1.0)
    data[np.unravel_index(np.argmin(grid), grid.shape)] = 0.0
    data[np.unravel_index(np.argmax(grid), grid.shape)] = 1.0
    terrain = Terrain(
        center=(0.0, 0.0),
        half_size=(size_m / 2, size_m / 2),
        z_min=round(gmin, 6),
        z_range=round(gmax - gmin, 6),
        data=data,
        file=file,
    )
    return terrain, hnode, natural


def road_surfaces(
    nodes, edges, hnode, style: TownStyle
) -> tuple[list[Box], list[tuple[str, np.ndarray, float]]]:
    """One tilted box per road (its ramp between the flat ends), one disc per junction (name, xy, height)."""
    road_boxes = []
    a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
    lengths = np.linalg.norm(b - a, axis=1)
    for e, (i, j) in enumerate(edges):
        u = (b[e] - a[e]) / lengths[e]
        run = lengths[e] - 2 * style.ramp_start_m
        dh = float(hnode[j] - hnode[i])
        pitch = -math.atan2(dh, run)  # positive pitch about y tips the nose down
        mid = (a[e] + b[e]) / 2
        top = (hnode[i] + hnode[j]) / 2
        # box centre = top-surface centre minus half the thickness along the tilted normal
        nrm = np.array([-math.sin(-pitch) * u[0], -math.sin(-pitch) * u[1], math.cos(pitch)])
        c = np.array([mid[0], mid[1], top]) - nrm * style.road_thickness_m / 2
        road_boxes.append(
            Box(
                f"road_{e}",
                (float(c[0]), float(c[1]), float(c[2])),
                (math.hypot(run, dh) / 2, style.road_width_m / 2, style.road_thickness_m / 2),
                math.atan2(u[1], u[0]),
                "road",
                pitch,
            )
        )
    junctions = [(f"junction_{k}", nodes[k], float(hnode[k])) for k in range(len(nodes))]
    return road_boxes, junctions


def spawn_pose(rng: np.random.Generator, nodes, edges, style: TownStyle) -> tuple[float, float, float]:
    """(x, y, yaw): the middle of a random road's right-hand lane, heading along the road."""
    a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
    lengths = np.linalg.norm(b - a, axis=1)
    e0 = int(rng.integers(len(edges)))
    u0 = (b[e0] - a[e0]) / lengths[e0]
    p0 = a[e0] + u0 * lengths[e0] / 2 - np.array([-u0[1], u0[0]]) * style.lane_width_m / 2
    return (round(float(p0[0]), 4), round(float(p0[1]), 4), round(math.atan2(u0[1], u0[0]), 6))
