"""Poisson surface reconstruction of an aggregated, oriented point cloud, trimmed to where scans saw surface.

The map builder aggregates all scans in the world frame (points with normals oriented toward the sensor,
i.e. outward of the surfaces) and meshes them with Open3D's screened Poisson reconstruction (Kazhdan and
Hoppe 2013), as the paper and its reference code do. Poisson fits a closed implicit surface to the whole
bounding cube, so it invents surface where no scan looked: sheets that continue open surfaces (the ground)
to the cube's walls, and lids over open space. :func:`poisson_mesh` removes them in
three steps:

1. **density**: vertices whose Poisson density (octree depth of the samples that support them) is below
   the ``density_quantile`` quantile of all vertex densities (the reference code's 0.1). This is relative:
   it always removes that fraction of the vertices, so where the invented surface is small (a cloud that
   fills its bounding cube) it also eats into the sparsest real surface; pass 0 to skip it.
2. **support**: triangles with any vertex farther than ``max_support_m`` from the nearest input point.
   This is absolute and removes everything Poisson made up away from the data, whatever its density.
3. **crop** (optional): triangles whose centroid lies outside an xy box ``(xmin, ymin, xmax, ymax)``,
   half open (``xmin <= x < xmax``), so that adjacent tiles built with a margin and cropped to their own
   boxes share no triangle and miss none.

Then unreferenced vertices, degenerate triangles (a repeated vertex, or zero area by the ray caster's
own criterion) and duplicated triangles (same three vertices in any order) are removed.

Choices a caller must know:

* The density trim removes ``density_quantile`` of the vertices whatever they are. On street scans
  (synthetic town, 300k points, depth 9) the 0.1 quantile removed 4.5 % of the area, almost all of it
  invented: the share of input points with a mesh vertex within 15 cm went from 98.0 % to 97.9 % and the
  share of vertices more than 10 cm off the true surface fell from 5.2 % to 4.3 %. On a closed, evenly
  scanned object it cuts holes instead (tests: a scanned sphere keeps only 95 % of its surface within
  5 cm, with holes up to 17 cm at depth 8).
* With more than one thread Open3D's reconstruction is not bit-reproducible (a few triangles differ from
  run to run); ``n_threads=1`` is, and on the 2-core development machine it was not slower.
* Open3D's PoissonRecon may print a "bad average roots" warning on stderr through its own channel;
  it is harmless and not an error.

Cost (Open3D 0.20 on the 2-core development machine, shared with other jobs; one-off measurements, not
tests): 1 M LiDAR points (64-beam sweeps from 40 poses along the roads of a 100 m synthetic town, cloud
105 m × 104 m × 5 m) at depth 9: 7–10 s in Poisson, 10–13 s for the whole call (the KD-tree support
trim is most of the rest), 0.75 GB peak resident (process total, 0.11 GB of it the loaded points);
depth 10: 28 s / 32 s and 1.45 GB. The cost follows the occupied surface more than the point count
(``DESIGN.md`` quotes 24 s / 1.1 GB at depth 9 for another 1 M-point cloud). Build a large map tile by
tile.
"""

from __future__ import annotations

import resource
import time

import numpy as np
from scipy.spatial import cKDTree

from rangemcl.errors import InputError

MIN_POINTS = 100  # fewer input points than this give an empty mesh (Poisson needs a populated octree)
NORMAL_TOL = 1e-3  # | ‖n‖ − 1 | allowed for a "unit" normal


def _empty_mesh() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((0, 3), dtype=np.float64), np.zeros((0, 3), dtype=np.int32)


def _peak_rss_mb() -> float:
    """The process's resident-set high-water mark so far, MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _as_cloud(name: str, array, n: int | None = None) -> np.ndarray:
    a = np.asarray(array)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise InputError(f"{name}: expected real numbers, got dtype {a.dtype}")
    if n is not None and len(a) != n:
        raise InputError(f"{name}: expected {n} rows (one per point), got {len(a)}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(f"{name}[{int(np.flatnonzero(bad)[0])}] is not finite ({int(bad.sum())} bad rows)")
    return a


def _check_positive(name: str, value, *, allow_inf: bool = False) -> float:
    v = float(value)
    if not (v > 0) or (np.isinf(v) and not allow_inf):
        raise InputError(f"{name} must be a positive number, got {value!r}")
    return v


def _as_crop(crop) -> tuple[float, float, float, float]:
    try:
        box = tuple(float(c) for c in crop)
    except (TypeError, ValueError):
        raise InputError(f"crop must be (xmin, ymin, xmax, ymax), got {crop!r}") from None
    if len(box) != 4 or not np.isfinite(box).all() or box[0] >= box[2] or box[1] >= box[3]:
        raise InputError(
            f"crop must be a finite (xmin, ymin, xmax, ymax) with xmin < xmax, ymin < ymax, got {crop!r}"
        )
    return box  # type: ignore[return-value]


def clean_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Remove degenerate and duplicated triangles, then unreferenced vertices.

    Degenerate: a repeated vertex index, or twice the area ``<= 1e-12 · extent²`` (``extent`` the largest
    side of the vertices' bounding box; :func:`rangemcl.raycast.clean_mesh` drops the same triangles).
    Duplicated: the same three vertex indices in any order or winding; the first one is kept.

    Returns ``(vertices, faces int32, old_index (V',) int64 of each kept vertex, counts dict)``; the kept
    vertices and faces stay in their original order.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    counts = {"degenerate": 0, "duplicated": 0, "unreferenced_vertices": 0}
    if len(f):
        repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        extent = max(float(np.ptp(v[np.unique(f)], axis=0).max()), 1e-9)
        degenerate = repeated | (area2 <= 1e-12 * extent * extent)
        counts["degenerate"] = int(degenerate.sum())
        f = f[~degenerate]
    if len(f):
        _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        counts["duplicated"] = len(f) - len(first)
        f = f[np.sort(first)]
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    old_index = np.flatnonzero(used)
    counts["unreferenced_vertices"] = len(v) - len(old_index)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[old_index] = np.arange(len(old_index))
    return v[old_index], remap[f].astype(np.int32).reshape(-1, 3), old_index, counts


def poisson_mesh(
    points,
    normals,
    *,
    depth: int = 9,
    density_quantile: float = 0.1,
    max_support_m: float = 0.5,
    scale: float = 1.1,
    linear_fit: bool = False,
    crop=None,
    n_threads: int = -1,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mesh an oriented point cloud with Open3D's screened Poisson reconstruction and trim it to the data.

    Args:
        points: ``(N, 3)`` world-frame points, metres.
        normals: ``(N, 3)`` unit normals, oriented toward the sensor that saw each point (outward of the
            surface). Poisson puts the inside of the surface opposite to the normals, so wrongly oriented
            normals give a wrong surface, not an error.
        depth: octree depth; the finest cell is ``scale · (bounding-box diameter) / 2**depth`` (about
            0.2 m for a 100 m tile at depth 9). The octree adapts to the data, so this is an upper bound.
        density_quantile: vertices with a density below this quantile of all densities are removed
            (0 keeps all). See the module notes: it removes that fraction of the vertices whatever they are.
        max_support_m: triangles with a vertex farther than this from every input point are removed
            (``inf`` keeps all).
        scale: ratio of the reconstruction cube's diameter to the points' bounding cube (Open3D's).
        linear_fit: place iso-vertices by linear interpolation (Open3D's option).
        crop: optional ``(xmin, ymin, xmax, ymax)``: keep triangles whose centroid lies in the half-open
            box ``[xmin, xmax) × [ymin, ymax)``.
        n_threads: threads for Open3D and the KD-tree queries; -1 uses all cores. Only 1 gives the same
            mesh on every run.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int32, stats)``. Fewer than :data:`MIN_POINTS` input
        points give an empty mesh (``(0, 3)`` arrays) and ``stats["skipped"]`` says why; the trimming may
        also leave an empty mesh. ``stats`` holds the input point count, the triangle counts after each
        step, the density threshold, the seconds spent and ``peak_rss_mb``, the process's resident-set
        high-water mark after the call (covers this call only if it is the process's largest job).

    Raises:
        InputError: empty input, shapes that differ, a non-finite point or normal, a normal that is not
            unit length, or a bad parameter.
    """
    p = _as_cloud("points", points)
    if len(p) == 0:
        raise InputError("points: the point cloud is empty")
    n = _as_cloud("normals", normals, len(p))
    norm_err = np.abs(np.linalg.norm(n, axis=1) - 1.0)
    bad = norm_err > NORMAL_TOL
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"normals[{i}] has length {np.linalg.norm(n[i]):.6g}, expected unit normals "
            f"({int(bad.sum())} bad rows)"
        )
    if isinstance(depth, bool) or not isinstance(depth, int | np.integer) or not 1 <= depth <= 16:
        raise InputError(f"depth must be an integer in [1, 16], got {depth!r}")
    if not 0.0 <= float(density_quantile) < 1.0:
        raise InputError(f"density_quantile must lie in [0, 1), got {density_quantile!r}")
    max_support_m = _check_positive("max_support_m", max_support_m, allow_inf=True)
    scale = _check_positive("scale", scale)
    if scale < 1.0:
        raise InputError(f"scale must be >= 1 (the cube must hold the points), got {scale!r}")
    box = None if crop is None else _as_crop(crop)
    workers = -1 if n_threads is None or int(n_threads) <= 0 else int(n_threads)
    t_start = time.perf_counter()

    stats: dict = {
        "input_points": len(p),
        "depth": int(depth),
        "raw_vertices": 0,
        "raw_triangles": 0,
        "density_threshold": None,
        "triangles_after_density": 0,
        "triangles_after_support": 0,
        "triangles_after_crop": 0,
        "removed_degenerate": 0,
        "removed_duplicated": 0,
        "vertices": 0,
        "triangles": 0,
        "seconds_poisson": 0.0,
        "seconds": 0.0,
        "peak_rss_mb": 0.0,
    }
    if len(p) < MIN_POINTS:
        v, f = _empty_mesh()
        stats["skipped"] = f"{len(p)} points, fewer than {MIN_POINTS}"
        stats["seconds"] = time.perf_counter() - t_start
        stats["peak_rss_mb"] = _peak_rss_mb()
        return v, f, stats

    t_import = time.perf_counter()
    import open3d as o3d  # here, not at module import: it takes about a second to load

    t_start += time.perf_counter() - t_import  # "seconds" leaves out the first call's import
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    cloud.normals = o3d.utility.Vector3dVector(n)
    t0 = time.perf_counter()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud,
            depth=int(depth),
            scale=float(scale),
            linear_fit=bool(linear_fit),
            n_threads=-1 if workers == -1 else workers,
        )
    stats["seconds_poisson"] = time.perf_counter() - t0
    del cloud
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    density = np.asarray(dens, dtype=np.float64)
    del mesh, dens
    stats["raw_vertices"], stats["raw_triangles"] = len(v), len(f)

    # (1) density: drop vertices below the quantile, and every triangle that uses one
    if len(v) and density_quantile > 0.0:
        threshold = float(np.quantile(density, density_quantile))
        stats["density_threshold"] = threshold
        f = f[(density >= threshold)[f].all(axis=1)]
    stats["triangles_after_density"] = len(f)

    # (2) support: drop triangles with a vertex farther than max_support_m from every input point
    if len(f) and np.isfinite(max_support_m):
        used = np.unique(f)
        dist, _ = cKDTree(p).query(v[used], k=1, distance_upper_bound=max_support_m, workers=workers)
        supported = np.zeros(len(v), dtype=bool)
        supported[used] = dist <= max_support_m
        f = f[supported[f].all(axis=1)]
    stats["triangles_after_support"] = len(f)

    # (3) crop: keep triangles whose centroid lies in [xmin, xmax) × [ymin, ymax)
    if len(f) and box is not None:
        c = v[f].mean(axis=1)
        inside = (c[:, 0] >= box[0]) & (c[:, 0] < box[2]) & (c[:, 1] >= box[1]) & (c[:, 1] < box[3])
        f = f[inside]
    stats["triangles_after_crop"] = len(f)

    if len(f):
        v, f, _, counts = clean_faces(v, f)
        stats["removed_degenerate"], stats["removed_duplicated"] = counts["degenerate"], counts["duplicated"]
    else:
        v, f = _empty_mesh()
    stats["vertices"], stats["triangles"] = len(v), len(f)
    stats["seconds"] = time.perf_counter() - t_start
    stats["peak_rss_mb"] = _peak_rss_mb()
    return v, f.astype(np.int32), stats


def transfer_labels(mesh_vertices, points, point_labels, *, max_distance_m: float = 1.0) -> np.ndarray:
    """Label each mesh vertex with the boolean label of its nearest input point (KD-tree).

    Vertices with no input point within ``max_distance_m`` get ``False``. ``point_labels`` is ``(N,)``
    bool (or 0/1 integers). Returns ``(V,)`` bool. Used to carry the scans' ground labels onto the mesh.
    """
    v = _as_cloud("mesh_vertices", mesh_vertices)
    p = _as_cloud("points", points)
    labels = np.asarray(point_labels)
    if labels.shape != (len(p),):
        raise InputError(f"point_labels: expected shape ({len(p)},), got {labels.shape}")
    if labels.dtype != bool:
        if not np.issubdtype(labels.dtype, np.number) or not np.isin(labels, (0, 1)).all():
            raise InputError("point_labels: expected booleans (or 0/1)")
        labels = labels.astype(bool)
    max_distance_m = _check_positive("max_distance_m", max_distance_m, allow_inf=True)
    out = np.zeros(len(v), dtype=bool)
    if len(v) == 0 or len(p) == 0:
        return out
    _, idx = cKDTree(p).query(v, k=1, distance_upper_bound=max_distance_m, workers=-1)
    found = idx < len(p)  # a miss returns index len(p) and distance inf
    out[found] = labels[idx[found]]
    return out
