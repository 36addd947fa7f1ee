"""Ground simplification of a map mesh (the paper's step after Poisson: about 50 % fewer triangles).

The ground is the largest and flattest part of a street map and Poisson tessellates it as finely as the
facades. :func:`simplify_ground` coarsens the ground part only:

1. **Vertex clustering** of the ground vertices in ``voxel_m`` cells: all ground vertices of one cell merge
   into one vertex at their mean position; faces are re-indexed to the merged vertices. Non-ground
   vertices are never moved or merged. The cells are ``voxel_m × voxel_m`` columns in xy aligned to the
   world origin (so tiles simplified separately use the same cells); inside a column, ground vertices are
   split into separate clusters wherever their sorted heights leave a gap larger than ``voxel_m``
   (stacked ground: a bridge over a road, a ramp over a floor). A fixed 3D voxel grid is not used because
   it cuts flat ground that crosses a voxel boundary in z (z = 0 in the world frame, say) into two
   clusters per column whose means nearly coincide in xy, which folds the surface into slivers.
2. **Smoothing** (paper Eq. 3): each ground vertex becomes the average of itself and its ground
   neighbours along mesh edges, ``smooth_iterations`` times (all vertices updated at once from the
   previous positions). Non-ground vertices neither move nor pull. On a plane the average stays on the
   plane; on a curved ground it moves a vertex by about ``curvature · voxel_m² / 2``.
3. **Removal of invalid faces**: degenerate faces (two or three of their vertices merged, or zero area),
   duplicated faces (the same three vertices in any order: two fine triangles can collapse onto one),
   and faces that join ground and non-ground vertices and have an edge longer than
   ``max_edge_factor · voxel_m`` (merging and smoothing move ground vertices by up to about a cell, so
   such a face is a stretched sliver across a wall foot rather than a surface anyone scanned); then
   unreferenced vertices.

The output lists the non-ground vertices first, in their input order, then the ground vertices.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import sparse

from rangemcl.errors import InputError
from rangemcl.mapping.poisson import clean_faces


def _check_mesh(vertices, faces, is_ground) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    g = np.asarray(is_ground)
    if v.ndim != 2 or v.shape[1] != 3 or not np.issubdtype(v.dtype, np.number):
        raise InputError(f"vertices: expected a numeric array of shape (V, 3), got {v.shape} {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise InputError(f"vertices: {int((~np.isfinite(v)).any(axis=1).sum())} vertices are not finite")
    if f.size == 0:
        f = np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected shape (F, 3), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"faces: expected integer vertex indices, got {f.dtype}")
    f = f.astype(np.int64)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"faces: indices must lie in [0, {len(v) - 1}], got [{f.min()}, {f.max()}]")
    if g.shape != (len(v),):
        raise InputError(f"is_ground: expected shape ({len(v)},) (one flag per vertex), got {g.shape}")
    if g.dtype != bool:
        if not np.issubdtype(g.dtype, np.number) or not np.isin(g, (0, 1)).all():
            raise InputError("is_ground: expected booleans (or 0/1)")
        g = g.astype(bool)
    return v, f, g


def _ground_clusters(xyz: np.ndarray, voxel_m: float) -> tuple[np.ndarray, int]:
    """Cluster id of each point: same xy column of side voxel_m, and no height gap > voxel_m between."""
    cell = np.floor(xyz[:, :2] / voxel_m).astype(np.int64)
    order = np.lexsort((xyz[:, 2], cell[:, 1], cell[:, 0]))
    cs, zs = cell[order], xyz[order, 2]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (cs[1:] != cs[:-1]).any(axis=1) | (np.diff(zs) > voxel_m)
    ids = np.empty(len(order), dtype=np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids, int(new.sum())


def simplify_ground(
    vertices,
    faces,
    is_ground,
    *,
    voxel_m: float = 1.0,
    smooth_iterations: int = 1,
    max_edge_factor: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Coarsen the ground part of a mesh: vertex clustering, Eq. 3 smoothing, removal of invalid faces.

    Args:
        vertices: ``(V, 3)`` metres. faces: ``(F, 3)`` vertex indices. is_ground: ``(V,)`` bool per vertex
            (e.g. from :func:`rangemcl.mapping.poisson.transfer_labels`).
        voxel_m: side of the clustering cells (the paper's 1 m).
        smooth_iterations: rounds of Eq. 3 averaging (0 skips it).
        max_edge_factor: faces that mix ground and non-ground vertices are removed when an edge is longer
            than ``max_edge_factor · voxel_m`` after merging and smoothing.

    Returns:
        ``(vertices (V', 3) float64, faces (F', 3) int32, is_ground (V',) bool, stats)``. Non-ground
        vertices come first in their input order, then the merged ground vertices; faces keep their input
        order. ``stats`` holds triangle counts before and after (all, and ground triangles, i.e. those with
        three ground vertices), vertex counts, the faces removed by each rule and the seconds spent. An
        empty mesh gives an empty mesh.

    Raises:
        InputError: shapes or dtypes that do not fit, non-finite vertices, out-of-range indices, a
            non-positive voxel size, a negative iteration count.
    """
    t0 = time.perf_counter()
    v, f, g = _check_mesh(vertices, faces, is_ground)
    voxel_m = float(voxel_m)
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise InputError(f"voxel_m must be a positive number, got {voxel_m!r}")
    if isinstance(smooth_iterations, bool) or not isinstance(smooth_iterations, int | np.integer):
        raise InputError(f"smooth_iterations must be an integer >= 0, got {smooth_iterations!r}")
    if smooth_iterations < 0:
        raise InputError(f"smooth_iterations must be an integer >= 0, got {smooth_iterations!r}")
    max_edge_factor = float(max_edge_factor)
    if not max_edge_factor > 0:
        raise InputError(f"max_edge_factor must be a positive number, got {max_edge_factor!r}")

    stats: dict = {
        "triangles_before": len(f),
        "ground_triangles_before": int(g[f].all(axis=1).sum()) if len(f) else 0,
        "vertices_before": len(v),
        "ground_vertices_before": int(g.sum()),
        "removed_degenerate": 0,
        "removed_duplicated": 0,
        "removed_long_edges": 0,
    }

    # (1) vertex clustering of the referenced ground vertices; non-ground vertices keep their own index
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    ground = np.flatnonzero(g & used)
    non_ground = np.flatnonzero(~g)
    cluster, n_clusters = _ground_clusters(v[ground], voxel_m)
    counts = np.bincount(cluster, minlength=n_clusters).astype(np.float64)
    means = np.zeros((n_clusters, 3))
    for k in range(3):
        means[:, k] = np.bincount(cluster, v[ground, k], n_clusters)[:n_clusters] / counts
    new_index = np.full(len(v), -1, dtype=np.int64)
    new_index[non_ground] = np.arange(len(non_ground))
    new_index[ground] = len(non_ground) + cluster
    v2 = np.concatenate([v[non_ground], means])
    g2 = np.concatenate([np.zeros(len(non_ground), dtype=bool), np.ones(n_clusters, dtype=bool)])
    f2 = new_index[f]
    merged = (f2[:, 0] == f2[:, 1]) | (f2[:, 1] == f2[:, 2]) | (f2[:, 0] == f2[:, 2])
    stats["removed_degenerate"] += int(merged.sum())
    f2 = f2[~merged]

    # (2) Eq. 3: average each ground vertex with its ground neighbours, Jacobi style
    if smooth_iterations > 0 and len(f2) and n_clusters:
        i = np.concatenate([f2[:, 0], f2[:, 1], f2[:, 2]])
        j = np.concatenate([f2[:, 1], f2[:, 2], f2[:, 0]])
        both = g2[i] & g2[j]
        i, j = i[both], j[both]
        adj = sparse.coo_matrix(
            (np.ones(2 * len(i)), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(len(v2), len(v2))
        ).tocsr()
        adj.sum_duplicates()
        adj.data[:] = 1.0
        degree = np.asarray(adj.sum(axis=1)).ravel()
        rows = np.flatnonzero(g2)
        adj_g = adj[rows]
        for _ in range(int(smooth_iterations)):
            v2[rows] = (v2[rows] + adj_g @ v2) / (1.0 + degree[rows, None])

    # (3) faces across the ground/non-ground boundary stretched by the merge
    if len(f2):
        mixed = g2[f2].any(axis=1) & ~g2[f2].all(axis=1)
        p = v2[f2]
        longest = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).max(axis=1)
        long_faces = mixed & (longest > max_edge_factor * voxel_m)
        stats["removed_long_edges"] = int(long_faces.sum())
        f2 = f2[~long_faces]

    if len(f2):
        v3, f3, kept, counts_clean = clean_faces(v2, f2)
        g3 = g2[kept]
        stats["removed_degenerate"] += counts_clean["degenerate"]
        stats["removed_duplicated"] = counts_clean["duplicated"]
    else:
        v3, f3, g3 = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=bool)

    stats["triangles_after"] = len(f3)
    stats["ground_triangles_after"] = int(g3[f3].all(axis=1).sum()) if len(f3) else 0
    stats["vertices_after"] = len(v3)
    stats["ground_vertices_after"] = int(g3.sum())
    stats["seconds"] = time.perf_counter() - t0
    return v3, f3.astype(np.int32), g3, stats
