"""How good a map is against the true surface: accuracy (how far the map lies from the truth) and
completeness (how much of the visible truth the map covers).

Distances are unsigned point-to-triangle-mesh distances from Open3D's ``RaycastingScene`` (Embree). It
works in float32, so every mesh and point set is first shifted by the centre of the mesh's bounding box:
millimetre precision holds for maps in large (e.g. UTM) coordinates too.
"""

from __future__ import annotations

import math

import numpy as np

from rangemcl.errors import InputError

MAX_SURFACE_SAMPLES = 2_000_000  # the sample spacing is widened beyond this many points on a surface


def surface_distances(points, truth_vertices, truth_faces) -> np.ndarray:
    """Unsigned distance ``(N,)`` float64 of each point ``(N, 3)`` to the triangle mesh."""
    import open3d as o3d

    p = _points(points, "points")
    v = _points(truth_vertices, "mesh vertices")
    f = np.asarray(truth_faces)
    if len(v) == 0 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InputError(f"mesh: needs vertices and (F, 3) triangles, got {len(v)} vertices, faces {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"mesh: face indices out of range 0..{len(v) - 1}")
    if len(p) == 0:
        return np.zeros(0)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((v - centre).astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32))
    )
    out = np.empty(len(p))
    chunk = 1_000_000  # bounds Open3D's temporary memory
    for s in range(0, len(p), chunk):
        q = o3d.core.Tensor((p[s : s + chunk] - centre).astype(np.float32))
        out[s : s + chunk] = scene.compute_distance(q).numpy()
    return out


def sample_surface(vertices, faces, spacing_m: float, seed: int = 0, max_points: int = MAX_SURFACE_SAMPLES):
    """Points drawn uniformly by area on the triangles, about one per ``spacing_m``² (at most
    ``max_points``). Returns ``(points (N, 3) float64, spacing actually used)``."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces, np.int64)]  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    if total <= 0:
        return np.zeros((0, 3)), float(spacing_m)
    n = math.ceil(total / spacing_m**2)
    if n > max_points:
        n = max_points
        spacing_m = math.sqrt(total / n)
    rng = np.random.default_rng(seed)
    k = rng.choice(len(area), size=n, p=area / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)  # uniform on the triangle: (1 - √r1) a + √r1 (1 - r2) b + √r1 r2 c
    a, b, c = tri[k, 0], tri[k, 1], tri[k, 2]
    pts = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return pts, float(spacing_m)


def map_quality(
    m_vertices,
    m_faces,
    truth_vertices,
    truth_faces,
    *,
    reference_points=None,
    tolerance_m: float = 0.2,
    sample_spacing_m: float = 0.25,
    seed: int = 0,
) -> dict:
    """Accuracy and completeness of a map mesh against the true mesh, as a plain dict.

    Accuracy, from the map to the truth, two ways: ``vertex_dist_*_m`` over the map vertices that some
    triangle uses (what a vertex-based comparison sees; dense where the mesh is fine), and
    ``surface_dist_*_m`` over points sampled uniformly on the map's triangles (weighted by area, so big
    wrong triangles count for their size); each with ``median``, ``p90``, ``max``, ``mean``, and
    ``surface_within_tolerance_share`` (precision at ``tolerance_m``).

    Completeness: the share of reference points within ``tolerance_m`` of the map surface. Reference
    points are the parts of the true surface the drive could see (e.g. noise-free LiDAR hits, world
    frame); when None, points sampled on the whole truth — which includes surfaces no sensor saw (box
    bottoms, ground under buildings), so completeness then reads low. Non-finite reference points are
    dropped (counted in ``reference_points_dropped_n``).
    """
    mv = _points(m_vertices, "map vertices")
    mf = np.asarray(m_faces, np.int64)
    tv = _points(truth_vertices, "truth vertices")
    tf = np.asarray(truth_faces, np.int64)
    if not (math.isfinite(tolerance_m) and tolerance_m >= 0):
        raise InputError(f"map quality: tolerance_m must be >= 0, got {tolerance_m}")
    if not (math.isfinite(sample_spacing_m) and sample_spacing_m > 0):
        raise InputError(f"map quality: sample_spacing_m must be positive, got {sample_spacing_m}")
    used = np.unique(mf.reshape(-1)) if mf.size else np.zeros(0, np.int64)
    if len(used) == 0:
        raise InputError("map quality: the map has no triangles")
    vertex_d = surface_distances(mv[used], tv, tf)
    samples, spacing = sample_surface(mv, mf, sample_spacing_m, seed)
    surface_d = surface_distances(samples, tv, tf)

    if reference_points is None:
        ref, ref_spacing = sample_surface(tv, tf, sample_spacing_m, seed + 1)
        dropped = 0
    else:
        ref = np.asarray(reference_points, np.float64).reshape(-1, 3)
        keep = np.isfinite(ref).all(axis=1)
        dropped = int((~keep).sum())
        ref, ref_spacing = ref[keep], math.nan
    ref_d = surface_distances(ref, mv, mf)

    out: dict = {}
    out.update(_stats("vertex_dist", vertex_d))
    out.update(_stats("surface_dist", surface_d))
    out["surface_within_tolerance_share"] = _share(surface_d, tolerance_m)
    out["completeness"] = _share(ref_d, tolerance_m)
    out["tolerance_m"] = float(tolerance_m)
    out["surface_sample_spacing_m"] = spacing
    out["reference_sample_spacing_m"] = ref_spacing  # NaN: the caller's reference points
    out["map_vertices_n"] = len(vertex_d)
    out["map_surface_samples_n"] = len(surface_d)
    out["reference_points_n"] = len(ref_d)
    out["reference_points_dropped_n"] = dropped
    return out


def _stats(prefix: str, d: np.ndarray) -> dict:
    if len(d) == 0:
        return {f"{prefix}_{k}_m": math.nan for k in ("median", "p90", "max", "mean")}
    return {
        f"{prefix}_median_m": float(np.median(d)),
        f"{prefix}_p90_m": float(np.percentile(d, 90)),
        f"{prefix}_max_m": float(d.max()),
        f"{prefix}_mean_m": float(d.mean()),
    }


def _share(d: np.ndarray, tol: float) -> float:
    return float(np.mean(d <= tol)) if len(d) else math.nan


def _points(x, what: str) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.size == 0:
        return np.zeros((0, 3))
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{what}: expected shape (N, 3), got {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{what}: {int((~np.isfinite(a).all(axis=1)).sum())} points are NaN or infinite")
    return a
