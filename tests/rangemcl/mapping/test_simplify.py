"""Tests of the ground simplification (``rangemcl.mapping.simplify``) against independent references.

References are analytic (the ground's height function, a plane), hand-computed averages on a tiny mesh,
and vertical rays cast with the project's ray caster onto the simplified mesh.
"""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.errors import InputError
from rangemcl.mapping.simplify import simplify_ground
from rangemcl.raycast import RayCaster

GROUND_M = 40.0
GROUND_CELLS = 160  # 0.25 m spacing
VOXEL_M = 1.0


def ground_with_building(height_fn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 40 m × 40 m ground grid at 0.25 m with heights ``height_fn(x, y)``, plus a separate box building
    (8 × 6 × 10 m, 1 m facade cells) standing on it; returns vertices, faces, is_ground."""
    gv, gf = meshgen.grid_patch(
        (-GROUND_M / 2, -GROUND_M / 2, 0.0), (GROUND_M, 0, 0), (0, GROUND_M, 0), GROUND_CELLS, GROUND_CELLS
    )
    gv[:, 2] = height_fn(gv[:, 0], gv[:, 1])
    bv, bf = meshgen.box((8.0, 6.0, 10.0), (4.3, -3.1, 5.0), yaw=0.3, cell_m=1.0)
    v, f = meshgen.merge([(gv, gf), (bv, bf)])
    return v, f, np.concatenate([np.ones(len(gv), dtype=bool), np.zeros(len(bv), dtype=bool)])


def assert_valid(v: np.ndarray, f: np.ndarray, g: np.ndarray) -> None:
    assert v.dtype == np.float64 and f.dtype == np.int32 and g.dtype == bool
    assert len(g) == len(v) and f.min() >= 0 and f.max() < len(v)
    assert np.array_equal(np.unique(f), np.arange(len(v))), "unreferenced vertices remain"
    assert not ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).any(), "degenerate faces"
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f), "duplicated faces"
    p = v[f]
    assert (np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1) > 1e-9).all()


def face_keys(v: np.ndarray, f: np.ndarray) -> set:
    """Faces as coordinate triples, rotated to start at the smallest vertex (keeps the winding)."""
    keys = set()
    for tri in np.round(v[f], 9):
        rows = [tuple(r) for r in tri]
        k = rows.index(min(rows))
        keys.add(tuple(rows[k:] + rows[:k]))
    return keys


def up_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    p = v[f]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]


def test_flat_ground_is_coarsened_and_the_building_kept():
    v, f, g = ground_with_building(lambda x, y: np.zeros_like(x))
    v2, f2, g2, stats = simplify_ground(v, f, g, voxel_m=VOXEL_M, smooth_iterations=1)
    assert_valid(v2, f2, g2)
    # measured: 51,200 ground triangles → 3,200 (16× fewer: 16 grid cells of 0.25 m per 1 m column);
    # all triangles 51,952 → 3,952
    assert stats["ground_triangles_before"] == 2 * GROUND_CELLS**2
    ratio = stats["ground_triangles_before"] / stats["ground_triangles_after"]
    assert ratio >= 12, f"ground triangles only {ratio:.1f}× fewer"
    assert stats["triangles_after"] == len(f2) and stats["ground_triangles_after"] == int(g2[f2].all(1).sum())
    # the building is untouched: same vertices in the same order, same faces after re-indexing
    assert np.array_equal(v2[~g2], v[~g])
    non_ground_faces = ~g[f].any(1)
    assert face_keys(v2, f2[~g2[f2].any(1)]) == face_keys(v, f[non_ground_faces])
    assert (~g2[f2].any(1)).sum() == non_ground_faces.sum()
    # Eq. 3 averages of points of the plane stay on the plane; no face flipped
    assert np.abs(v2[g2, 2]).max() <= 1e-12
    ground_faces = f2[g2[f2].all(1)]
    assert (up_normals(v2, ground_faces) > 0).all()
    # the coarse ground still spans the square (smoothing pulls the outer border in by under a cell)
    lo, hi = v2[g2, :2].min(0), v2[g2, :2].max(0)
    assert (lo < -GROUND_M / 2 + VOXEL_M).all() and (hi > GROUND_M / 2 - VOXEL_M).all()


def test_one_cluster_per_column_on_noisy_ground_crossing_zero():
    # Ground with ±5 mm noise around z = 0: a 3D voxel grid would cut every column in two at z = 0.
    rng = np.random.default_rng(0)
    v, f, g = ground_with_building(lambda x, y: rng.normal(0.0, 0.005, x.shape))
    v2, f2, g2, _ = simplify_ground(v, f, g, voxel_m=VOXEL_M)
    assert_valid(v2, f2, g2)
    columns = np.unique(np.floor(v[g, :2] / VOXEL_M), axis=0)
    assert g2.sum() == len(columns)
    assert (up_normals(v2, f2[g2[f2].all(1)]) > 0).all()


@pytest.mark.parametrize(
    ("name", "height_fn", "tol"),
    [
        ("slope", lambda x, y: 0.2 * x - 0.1 * y + 1.0, 1e-9),  # a plane: averages stay on it exactly
        ("sine", lambda x, y: 0.3 * np.sin(x / 10.0), 0.05),
    ],
)
def test_sloped_and_curved_ground_stays_close(name, height_fn, tol):
    v, f, g = ground_with_building(height_fn)
    v2, f2, g2, stats = simplify_ground(v, f, g, voxel_m=VOXEL_M, smooth_iterations=2)
    assert_valid(v2, f2, g2)
    assert stats["ground_triangles_after"] * 12 <= stats["ground_triangles_before"]
    gv = v2[g2]
    assert np.abs(gv[:, 2] - height_fn(gv[:, 0], gv[:, 1])).max() <= tol
    ground_faces = f2[g2[f2].all(1)]
    c = v2[ground_faces].mean(1)
    assert np.abs(c[:, 2] - height_fn(c[:, 0], c[:, 1])).max() <= max(tol, 1e-3)
    assert (up_normals(v2, ground_faces) > 0).all()
    # the simplified surface has no holes and follows the ground everywhere inside the border: vertical
    # rays from above, away from the building, hit it within tol of the true height
    rng = np.random.default_rng(1)
    xy = rng.uniform(-GROUND_M / 2 + 1.5, GROUND_M / 2 - 1.5, (4000, 2))
    xy = xy[np.hypot(xy[:, 0] - 4.3, xy[:, 1] + 3.1) > 6.0]
    caster = RayCaster()
    caster.add_mesh(v2[:, :3], f2[g2[f2].all(1)])
    top = 20.0
    hits = caster.cast(
        np.column_stack([xy, np.full(len(xy), top)]), np.tile([0.0, 0.0, -1.0], (len(xy), 1)), 40.0
    )
    assert hits.hit.all(), f"{(~hits.hit).sum()} vertical rays fell through the simplified ground"
    z = top - hits.ranges.astype(np.float64)
    assert np.abs(z - height_fn(xy[:, 0], xy[:, 1])).max() <= tol + 1e-4  # float32 ranges


def test_eq3_average_on_a_hand_built_fan():
    # centre 0 with ground neighbours 1..4 and one non-ground neighbour 5; a voxel so small that
    # nothing merges, so only Eq. 3 acts: v0' = (v0 + v1 + v2 + v3 + v4) / 5, v5 stays
    v = np.array(
        [[0, 0, 0.0], [1, 0, 0.2], [0, 1, 0.1], [-1, 0, -0.1], [0, -1, 0.4], [1, -1, 2.0]], dtype=float
    )
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5], [0, 5, 1]])
    g = np.array([True, True, True, True, True, False])
    # (max_edge_factor lifted: the faces to vertex 5 are far longer than 3 such voxels)
    v2, f2, g2, stats = simplify_ground(v, f, g, voxel_m=0.01, smooth_iterations=1, max_edge_factor=1e3)
    # output order: non-ground first, then the ground clusters (here one per vertex, sorted by column)
    assert np.array_equal(v2[~g2], v[~g])
    ground_out = {tuple(np.round(p, 12)) for p in v2[g2]}
    nbrs = {0: [1, 2, 3, 4], 1: [0, 2], 2: [0, 1, 3], 3: [0, 2, 4], 4: [0, 3]}  # ground neighbours only
    expected = {tuple(np.round((v[i] + v[n].sum(0)) / (1 + len(n)), 12)) for i, n in nbrs.items()}
    assert ground_out == expected
    assert stats["triangles_after"] == len(f) == len(f2)


def test_stretched_faces_across_the_ground_boundary_are_removed():
    # a ground square (one vertex per 1 m column, so nothing merges) and a non-ground vertex joined to it
    # by a face whose edges are 4.3 m and 4 m long: longer than 3 voxels
    v = np.array([[0, 0, 0], [1.5, 0, 0], [1.5, 1.5, 0], [0, 1.5, 0], [5.5, 1.5, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    g = np.array([True, True, True, True, False])
    v2, f2, g2, stats = simplify_ground(v, f, g, voxel_m=1.0, smooth_iterations=0)
    assert stats["removed_long_edges"] == 1
    assert len(f2) == 2 and g2.all() and np.array_equal(np.sort(v2, axis=0), np.sort(v[:4], axis=0))
    _, f3, _, stats3 = simplify_ground(v, f, g, voxel_m=1.0, smooth_iterations=0, max_edge_factor=5.0)
    assert stats3["removed_long_edges"] == 0 and len(f3) == 3


def test_empty_mesh_gives_empty_mesh():
    v2, f2, g2, stats = simplify_ground(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros(0, bool))
    assert v2.shape == (0, 3) and f2.shape == (0, 3) and g2.shape == (0,)
    assert stats["triangles_after"] == 0


V0, F0 = meshgen.grid_patch((0, 0, 0), (2, 0, 0), (0, 2, 0), 4, 4)
G0 = np.ones(len(V0), dtype=bool)


def _nan_vertex():
    v = V0.copy()
    v[3, 1] = np.nan
    return v


@pytest.mark.parametrize(
    ("vertices", "faces", "is_ground", "kwargs", "match"),
    [
        (V0[:, :2], F0, G0, {}, "vertices"),
        (_nan_vertex(), F0, G0, {}, "not finite"),
        (V0, F0[:, :2], G0, {}, "faces"),
        (V0, F0.astype(float), G0, {}, "integer"),
        (V0, F0 + 100, G0, {}, "indices"),
        (V0, F0, G0[:-1], {}, "is_ground"),
        (V0, F0, np.full(len(V0), 3), {}, "is_ground"),
        (V0, F0, G0, {"voxel_m": 0.0}, "voxel_m"),
        (V0, F0, G0, {"voxel_m": np.nan}, "voxel_m"),
        (V0, F0, G0, {"smooth_iterations": -1}, "smooth_iterations"),
        (V0, F0, G0, {"smooth_iterations": 1.5}, "smooth_iterations"),
        (V0, F0, G0, {"max_edge_factor": 0}, "max_edge_factor"),
    ],
)
def test_bad_input_raises_input_error(vertices, faces, is_ground, kwargs, match):
    with pytest.raises(InputError, match=match) as err:
        simplify_ground(vertices, faces, is_ground, **kwargs)
    assert "\n" not in str(err.value)
