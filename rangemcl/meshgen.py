"""Triangle meshes of simple shapes and of a synthetic town, for tests, benchmarks and the sample sweep.

Every function returns ``(vertices, faces)``: vertices ``(V, 3)`` float64 in metres, faces ``(F, 3)``
int32 with counter-clockwise winding seen from outside (normals point out of solids, up for ground).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def grid_patch(origin, edge_u, edge_v, nu: int, nv: int) -> Mesh:
    """A planar parallelogram ``origin + s·edge_u + t·edge_v`` split into ``nu × nv`` quads.

    The face normal is ``edge_u × edge_v``.
    """
    origin, edge_u, edge_v = (np.asarray(a, dtype=np.float64) for a in (origin, edge_u, edge_v))
    s = np.linspace(0.0, 1.0, nu + 1)
    t = np.linspace(0.0, 1.0, nv + 1)
    ss, tt = np.meshgrid(s, t, indexing="ij")  # (nu+1, nv+1)
    vertices = origin + ss[..., None] * edge_u + tt[..., None] * edge_v
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices.reshape(-1, 3), faces.astype(np.int32)


def merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes into one (faces re-indexed)."""
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32)
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)])
    return vertices, faces.astype(np.int32)


def transform(mesh: Mesh, T: np.ndarray) -> Mesh:
    """Apply a 4×4 homogeneous transform to a mesh's vertices."""
    v, f = mesh
    return v @ T[:3, :3].T + T[:3, 3], f


def box(size, center=(0.0, 0.0, 0.0), yaw: float = 0.0, cell_m: float | None = None) -> Mesh:
    """An oriented box of edge lengths ``size`` (x, y, z) centred at ``center``, rotated by ``yaw`` about z.

    Each face is split into quads no larger than ``cell_m`` (one quad per face when None).
    """
    sx, sy, sz = (float(s) for s in size)
    h = np.array([sx, sy, sz]) / 2.0

    def n(length: float) -> int:
        return 1 if cell_m is None else max(1, int(np.ceil(length / cell_m)))

    ex, ey, ez = np.array([sx, 0, 0.0]), np.array([0, sy, 0.0]), np.array([0, 0, sz])
    faces_spec = [  # origin corner, edge_u, edge_v with edge_u × edge_v pointing outward
        ((-h[0], -h[1], -h[2]), ey, ex, n(sy), n(sx)),  # bottom, -z
        ((-h[0], -h[1], h[2]), ex, ey, n(sx), n(sy)),  # top, +z
        ((-h[0], -h[1], -h[2]), ex, ez, n(sx), n(sz)),  # -y
        ((-h[0], h[1], -h[2]), ez, ex, n(sz), n(sx)),  # +y
        ((-h[0], -h[1], -h[2]), ez, ey, n(sz), n(sy)),  # -x
        ((h[0], -h[1], -h[2]), ey, ez, n(sy), n(sz)),  # +x
    ]
    mesh = merge([grid_patch(o, u, v, nu, nv) for o, u, v, nu, nv in faces_spec])
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = center
    return transform(mesh, T)


def uv_sphere(radius: float, center=(0.0, 0.0, 0.0), n_lat: int = 16, n_lon: int = 32) -> Mesh:
    """A closed UV sphere with ``n_lat`` latitude bands and ``n_lon`` longitude segments."""
    lat = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")  # (n_lat-1, n_lon)
    ring = np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], -1).reshape(-1, 3)
    vertices = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]]) * radius + np.asarray(center, float)
    top, bottom = 0, len(vertices) - 1
    faces = []
    for j in range(n_lon):
        k = (j + 1) % n_lon
        faces.append((top, 1 + j, 1 + k))
        base = 1 + (n_lat - 2) * n_lon
        faces.append((bottom, base + k, base + j))
    for i in range(n_lat - 2):
        for j in range(n_lon):
            k = (j + 1) % n_lon
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + k
            c, d = a + n_lon, b + n_lon
            faces += [(a, c, d), (a, d, b)]
    return vertices, np.asarray(faces, dtype=np.int32)


def cylinder(radius: float, height: float, center=(0.0, 0.0, 0.0), segments: int = 16) -> Mesh:
    """A closed vertical cylinder (z axis) with ``segments`` sides, centred at ``center``."""
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(segments)], 1)
    half_height = np.array([0.0, 0.0, height / 2])
    lo, hi = ring - half_height, ring + half_height
    caps = np.array([[0, 0, -height / 2], [0, 0, height / 2]])
    vertices = np.concatenate([lo, hi, caps]) + np.asarray(center, float)
    cb, ct = 2 * segments, 2 * segments + 1
    faces = []
    for j in range(segments):
        k = (j + 1) % segments
        faces += [
            (j, k, segments + k),
            (j, segments + k, segments + j),
            (cb, k, j),
            (ct, segments + j, segments + k),
        ]
    return vertices, np.asarray(faces, dtype=np.int32)


@dataclass
class TownMesh:
    """A synthetic town as separate parts (ground tiles, buildings, poles) plus its road centre lines."""

    parts: list[tuple[str, np.ndarray, np.ndarray]]  # (name, vertices (V, 3), faces (F, 3))
    road_xy: np.ndarray  # (R,) positions of the grid roads along x and along y, metres
    size_m: float

    def merged(self) -> Mesh:
        return merge([(v, f) for _, v, f in self.parts])

    def ground_height(self, x, y):
        return town_ground_height(x, y)


def town_ground_height(x, y):
    """Mild terrain relief of the synthetic town (metres): about ±0.6 m over tens of metres."""
    return 0.35 * np.sin(np.asarray(x) / 31.0) * np.cos(np.asarray(y) / 23.0) + 0.25 * np.sin(
        (np.asarray(x) + np.asarray(y)) / 47.0
    )


def town(
    seed: int = 0,
    size_m: float = 200.0,
    n_buildings: int = 80,
    n_poles: int = 120,
    ground_cell_m: float = 1.0,
    facade_cell_m: float = 1.0,
    ground_tile_m: float = 20.0,
    block_m: float = 50.0,
    road_width_m: float = 10.0,
) -> TownMesh:
    """A town-like scene: relief ground on a square of ``size_m``, roads on a ``block_m`` grid, boxy
    buildings of varied footprint, height and heading inside the blocks, and poles along the roads.

    The ground is split into ``ground_tile_m`` square parts (so engines that cull per geometry see tiles).
    With the defaults it has about 250k triangles.
    """
    rng = np.random.default_rng(seed)
    half = size_m / 2.0
    parts: list[tuple[str, np.ndarray, np.ndarray]] = []
    n_tiles = max(1, round(size_m / ground_tile_m))
    tile = size_m / n_tiles
    cells = max(1, round(tile / ground_cell_m))
    for i in range(n_tiles):
        for j in range(n_tiles):
            x0, y0 = -half + i * tile, -half + j * tile
            v, f = grid_patch((x0, y0, 0.0), (tile, 0, 0), (0, tile, 0), cells, cells)
            v[:, 2] = town_ground_height(v[:, 0], v[:, 1])
            parts.append((f"ground_{i}_{j}", v, f))

    roads = np.arange(-half + block_m / 2, half, block_m)  # road centre lines, both axes
    placed = 0
    attempts = 0
    footprints: list[tuple[float, float, float, float]] = []  # (x, y, half-extent x, half-extent y)
    while placed < n_buildings and attempts < 200 * n_buildings:
        attempts += 1
        sx, sy = rng.uniform(6.0, 20.0, size=2)
        height = float(rng.choice([rng.uniform(4.0, 10.0), rng.uniform(10.0, 30.0)]))
        yaw = float(rng.choice([0.0, rng.uniform(-0.4, 0.4)]))
        x, y = rng.uniform(-half + 5, half - 5, size=2)
        c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
        hx, hy = 0.5 * (c * sx + s * sy), 0.5 * (s * sx + c * sy)  # axis-aligned half extents
        if (np.abs(roads - x) < road_width_m / 2 + hx + 1.0).any():
            continue
        if (np.abs(roads - y) < road_width_m / 2 + hy + 1.0).any():
            continue
        if any(
            abs(x - fx) < hx + fx_h + 1.5 and abs(y - fy) < hy + fy_h + 1.5
            for fx, fy, fx_h, fy_h in footprints
        ):
            continue
        base = float(town_ground_height(x, y)) - 1.0  # sunk into the relief so no gap shows under walls
        v, f = box((sx, sy, height + 1.0), (x, y, base + (height + 1.0) / 2), yaw, cell_m=facade_cell_m)
        parts.append((f"building_{placed}", v, f))
        footprints.append((x, y, hx, hy))
        placed += 1

    for k in range(n_poles):
        along = rng.uniform(-half + 2, half - 2)
        road = rng.choice(roads)
        side = rng.choice([-1.0, 1.0]) * (road_width_m / 2 + 0.6)
        x, y = (along, road + side) if k % 2 == 0 else (road + side, along)
        z0 = float(town_ground_height(x, y)) - 0.3
        v, f = cylinder(0.15, 6.3, (x, y, z0 + 3.15), segments=12)
        parts.append((f"pole_{k}", v, f))
    return TownMesh(parts=parts, road_xy=roads, size_m=size_m)
