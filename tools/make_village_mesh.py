#!/usr/bin/env python3
"""The source mesh of the example mesh world ``scenes/examples/village``: a hillside village
as one triangle mesh, the kind of file a user brings (a city model, a photogrammetry), made here so that
the example is reproducible and small.

    python tools/make_village_mesh.py scenes/examples/village.ply
    simbed import-scene scenes/examples/village.ply --out scenes/examples/village.xml

Rolling terrain (a 2 m grid, up to about 4 m of relief, a flat band along the village road), houses with
gable roofs, a church with a tower, walls, trees as low cones on trunks; the road is the loop in
``scenes/examples/village_route.txt``. Deterministic (seed 0).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import trimesh

ROUTE = np.array([[-70.0, -55.0], [65.0, -60.0], [72.0, 10.0], [30.0, 62.0], [-55.0, 58.0], [-78.0, 5.0]])
HALF = 110.0


def _distance_to_route(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    p = np.stack([x.ravel(), y.ravel()], axis=1)
    best = np.full(len(p), np.inf)
    for a, b in zip(ROUTE, np.roll(ROUTE, -1, axis=0), strict=True):
        ab = b - a
        t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
        best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
    return best.reshape(x.shape)


def terrain_height(x, y):
    """Rolling hills, flattened within 6 m of the road (the road itself stays gently sloped)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    h = 2.0 * np.sin(x / 37.0) * np.cos(y / 29.0) + 1.5 * np.sin((x + 2 * y) / 53.0) + 0.03 * x
    d = _distance_to_route(x, y)
    road = 0.6 * np.sin(x / 60.0) + 0.02 * x  # the road's own gentle grade
    w = np.clip((d - 6.0) / 10.0, 0.0, 1.0)
    return road * (1 - w) + h * w


def terrain() -> trimesh.Trimesh:
    n = int(2 * HALF / 2.0) + 1
    xs = np.linspace(-HALF, HALF, n)
    gx, gy = np.meshgrid(xs, xs)
    v = np.stack([gx.ravel(), gy.ravel(), terrain_height(gx, gy).ravel()], axis=1)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    return trimesh.Trimesh(v, f, process=False)


def house(x, y, yaw, w, d, h, roof) -> trimesh.Trimesh:
    """A box of w x d footprint and h walls with a gable roof ``roof`` high, standing on the terrain."""
    z0 = float(terrain_height(x, y)) - 0.5  # sunk a little into the slope
    body = trimesh.creation.box(extents=(w, d, h + 0.5))
    body.apply_translation((0, 0, (h + 0.5) / 2))
    ridge = np.array(
        [
            [-w / 2, -d / 2, h + 0.5],
            [w / 2, -d / 2, h + 0.5],
            [w / 2, d / 2, h + 0.5],
            [-w / 2, d / 2, h + 0.5],
            [-w / 2, 0, h + 0.5 + roof],
            [w / 2, 0, h + 0.5 + roof],
        ]
    )
    faces = [[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5], [0, 3, 2], [0, 2, 1]]
    parts = [body, trimesh.Trimesh(ridge, faces, process=False)]
    m = trimesh.util.concatenate(parts)
    m.apply_transform(trimesh.transformations.rotation_matrix(yaw, (0, 0, 1)))
    m.apply_translation((x, y, z0))
    return m


def tree(x, y, rng) -> trimesh.Trimesh:
    z0 = float(terrain_height(x, y))
    h = float(rng.uniform(2.0, 3.5))
    trunk = trimesh.creation.cylinder(radius=0.2, height=h, sections=8)
    trunk.apply_translation((0, 0, h / 2))
    crown = trimesh.creation.cone(
        radius=float(rng.uniform(1.5, 2.5)), height=float(rng.uniform(4, 7)), sections=10
    )
    crown.apply_translation((0, 0, h - 0.3))
    m = trimesh.util.concatenate([trunk, crown])
    m.apply_translation((x, y, z0 - 0.2))
    return m


def village(seed: int = 0) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    parts = [terrain()]
    # houses along the road, 9-16 m from it, facing it
    legs = list(zip(ROUTE, np.roll(ROUTE, -1, axis=0), strict=True))
    for a, b in legs:
        u = (b - a) / np.linalg.norm(b - a)
        nrm = np.array([-u[1], u[0]])
        length = float(np.linalg.norm(b - a))
        for s in np.arange(12.0, length - 12.0, 17.0):
            for side in (-1, 1):
                if rng.random() < 0.25:
                    continue
                off = float(rng.uniform(11, 16))
                x, y = a + u * (s + rng.uniform(-3, 3)) + side * nrm * off
                if abs(x) > HALF - 8 or abs(y) > HALF - 8:
                    continue
                if _distance_to_route(np.array([x]), np.array([y]))[0] < 9.5:
                    continue
                yaw = math.atan2(u[1], u[0]) + (0 if rng.random() < 0.7 else math.pi / 2)
                parts.append(
                    house(
                        x, y, yaw, rng.uniform(7, 12), rng.uniform(6, 9), rng.uniform(3, 6), rng.uniform(2, 4)
                    )
                )
    # the church on the green in the middle, with its tower
    parts.append(house(0.0, 5.0, 0.3, 22, 11, 9, 5))
    tower = trimesh.creation.box(extents=(5, 5, 22))
    tower.apply_translation((-12.5, 1.2, float(terrain_height(-12.5, 1.2)) + 11 - 0.5))
    parts.append(tower)
    # walls of the churchyard
    for x, y, w, d in [(0, -14, 36, 0.5), (0, 24, 36, 0.5), (-18, 5, 0.5, 38), (18, 5, 0.5, 38)]:
        wall = trimesh.creation.box(extents=(w, d, 1.6))
        wall.apply_translation((x, y, float(terrain_height(x, y)) + 0.5))
        parts.append(wall)
    # trees: not within 7 m of the road
    for _ in range(90):
        x, y = rng.uniform(-HALF + 5, HALF - 5, 2)
        if _distance_to_route(np.array([x]), np.array([y]))[0] < 7.5 or (abs(x) < 20 and -16 < y < 26):
            continue
        parts.append(tree(float(x), float(y), rng))
    return trimesh.util.concatenate(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    m = village(args.seed)
    m.export(args.out)
    route = args.out.with_name(args.out.stem + "_route.txt")
    route.write_text(
        "# the village road, a loop (drive it with --loop)\n" + "".join(f"{x:g} {y:g}\n" for x, y in ROUTE)
    )
    print(f"wrote {args.out}: {len(m.faces):,} triangles, {len(m.vertices):,} vertices; {route}")


if __name__ == "__main__":
    main()
