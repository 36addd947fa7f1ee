"""The road network and the ground under it: the road graph (:func:`road_graph`), the natural relief, the
height field that equals the road surface near the roads (:func:`town_terrain`), the road boxes and junction
discs (:func:`road_surfaces`) and the spawn pose (:func:`spawn_pose`)."""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable

import numpy as np

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


def road_graph(rng: np.random.Generator, size_m: float, style: TownStyle) -> tuple[np.ndarray, np.ndarray]:
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
    k = len(nodes)
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
    return nodes, np.array(sorted(edges), dtype=np.int64)


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
