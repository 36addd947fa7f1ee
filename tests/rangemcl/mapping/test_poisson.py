"""Tests of the Poisson map meshing (``rangemcl.mapping.poisson``) against independent references.

The reference geometry is analytic: scans of a sphere made with a ray–sphere intersection written here, a
planar square, and distances to them computed from their formulas, never by the code under test.
Depths 7–8 and clouds of a few ten thousand points keep each reconstruction around a second.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rangemcl.errors import InputError
from rangemcl.mapping.poisson import MIN_POINTS, clean_faces, poisson_mesh, transfer_labels

SPHERE_C = np.array([0.7, -1.2, 0.4])
SPHERE_R = 3.0
SPHERE_DEPTH = 8
# The reconstruction cube is 1.1 × the points' 6 m bounding cube, so the finest cell at depth 8 is
# 6.6 m / 2**8 = 2.6 cm. Iso-vertices lie on cell edges where the fitted indicator crosses its iso-value;
# with exact samples they fall within a fraction of a cell of the surface (4 mm measured), so 2 cm
# (about 3/4 of a cell) bounds every vertex with room for the 3 mm range noise below.
SPHERE_TOL = 0.02
COVER_TOL = 0.05  # a point of the true sphere is covered if a mesh vertex lies this close
COVER_FRACTION = 0.95


def scan_sphere(rng, n_rays: int = 5000, noise: float = 0.003) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals of the sphere seen from 6 sensors 10 m from its centre (±x, ±y, ±z).

    Each sensor casts ``n_rays`` random rays into the cone that holds the sphere; the first intersection
    of each ray with the sphere (solved in closed form) plus Gaussian range noise is a point; its normal
    is the analytic sphere normal there (outward, hence toward the sensor on the visible side).
    """
    dist = 10.0
    half_angle = np.arcsin(SPHERE_R / dist)
    points = []
    for axis in np.concatenate([np.eye(3), -np.eye(3)]):
        sensor = SPHERE_C + dist * axis
        fwd = -axis
        side = np.cross(fwd, [0.3, 0.5, 0.8])
        side /= np.linalg.norm(side)
        up = np.cross(fwd, side)
        cos_t = rng.uniform(np.cos(half_angle), 1.0, n_rays)
        phi = rng.uniform(0.0, 2 * np.pi, n_rays)
        sin_t = np.sqrt(1.0 - cos_t**2)
        dirs = cos_t[:, None] * fwd + sin_t[:, None] * (
            np.cos(phi)[:, None] * side + np.sin(phi)[:, None] * up
        )
        oc = sensor - SPHERE_C
        b = dirs @ oc
        disc = b * b - (oc @ oc - SPHERE_R**2)
        hit = disc > 0
        t = -b[hit] - np.sqrt(disc[hit]) + rng.normal(0.0, noise, int(hit.sum()))
        points.append(sensor + t[:, None] * dirs[hit])
    p = np.concatenate(points)
    n = p - SPHERE_C
    return p, n / np.linalg.norm(n, axis=1, keepdims=True)


def sphere_surface_samples(rng, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return SPHERE_C + SPHERE_R * d / np.linalg.norm(d, axis=1, keepdims=True)


def triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    p = v[f]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def assert_clean(v: np.ndarray, f: np.ndarray) -> None:
    """Valid index range, every vertex used, no repeated index, no duplicated triangle."""
    assert v.dtype == np.float64 and v.shape[1] == 3
    assert f.dtype == np.int32 and f.shape[1] == 3
    assert f.min() >= 0 and f.max() < len(v)
    assert np.array_equal(np.unique(f), np.arange(len(v))), "unreferenced vertices remain"
    assert not ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).any()
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f), "duplicated triangles remain"
    assert (triangle_areas(v, f) > 0).all()


# ---------------------------------------------------------------------- sphere
@pytest.fixture(scope="module")
def sphere_cloud():
    return scan_sphere(np.random.default_rng(1))


@pytest.fixture(scope="module")
def sphere_default(sphere_cloud):
    """Reconstruction with the default trimming (density quantile 0.1, support 0.5 m)."""
    return (sphere_cloud[0], *poisson_mesh(*sphere_cloud, depth=SPHERE_DEPTH))


@pytest.fixture(scope="module")
def sphere_support_only(sphere_cloud):
    """Reconstruction trimmed by support only."""
    return (sphere_cloud[0], *poisson_mesh(*sphere_cloud, depth=SPHERE_DEPTH, density_quantile=0.0))


@pytest.mark.parametrize("mesh", ["sphere_default", "sphere_support_only"])
def test_sphere_vertices_lie_on_the_true_sphere(mesh, request):
    _, v, f, _ = request.getfixturevalue(mesh)
    assert len(f) > 1000
    err = np.abs(np.linalg.norm(v - SPHERE_C, axis=1) - SPHERE_R)
    assert err.max() < SPHERE_TOL, f"worst vertex {err.max() * 100:.2f} cm off the sphere"


def test_sphere_is_covered(sphere_support_only):
    # Coverage is checked with the support trim only. The density trim removes a fixed fraction of the
    # vertices whatever they are; on a closed, evenly scanned object there is no invented surface to
    # remove, so the 0.1 quantile cuts holes in real surface: measured here, 95.3 % of the sphere within
    # 5 cm and holes up to 17 cm at depth 8, 87 % with twice the rays. In street maps the lowest
    # densities sit on invented surface instead (see the module notes of rangemcl.mapping.poisson).
    _, v, _, _ = sphere_support_only
    samples = sphere_surface_samples(np.random.default_rng(2), 20000)
    # the distance to the nearest vertex bounds the distance to the mesh from above
    nearest, _ = cKDTree(v).query(samples)
    covered = (nearest <= COVER_TOL).mean()
    assert covered >= COVER_FRACTION, f"only {covered:.1%} of the sphere lies within 5 cm of the mesh"


def test_sphere_mesh_is_clean_and_outward(sphere_default):
    p, v, f, stats = sphere_default
    assert_clean(v, f)
    # winding: face normals point away from the centre (the side the normals said was outside)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = (normal * (tri.mean(1) - SPHERE_C)).sum(1) > 0
    assert outward.mean() > 0.99
    assert stats["input_points"] == len(p)
    assert stats["raw_triangles"] >= stats["triangles_after_density"] >= stats["triangles_after_support"]
    assert stats["triangles_after_support"] >= stats["triangles_after_crop"] >= stats["triangles"] == len(f)
    assert stats["vertices"] == len(v)
    assert stats["seconds"] >= stats["seconds_poisson"] > 0
    assert stats["peak_rss_mb"] > 0


# ---------------------------------------------------------------------- open plane: trimming
SQUARE_M = 10.0
SUPPORT_M = 0.25


@pytest.fixture(scope="module")
def square_cloud():
    """20k points on the square [0, 10] × [0, 10] at z = 0 seen from above (normals +z)."""
    rng = np.random.default_rng(3)
    n = 20000
    p = np.column_stack([rng.uniform(0.0, SQUARE_M, (n, 2)), np.zeros(n)])
    return p, np.tile([0.0, 0.0, 1.0], (n, 1))


def distance_to_square(v: np.ndarray) -> np.ndarray:
    """Exact distance from points to the filled square [0, S]² in the plane z = 0."""
    dxy = np.maximum(0.0, np.maximum(-v[:, :2], v[:, :2] - SQUARE_M))
    return np.sqrt((dxy**2).sum(1) + v[:, 2] ** 2)


TRIM_KW = dict(depth=7, density_quantile=0.0, max_support_m=SUPPORT_M, n_threads=1)  # 1 thread: deterministic


@pytest.fixture(scope="module")
def square_trimmed(square_cloud):
    return poisson_mesh(*square_cloud, **TRIM_KW)


def test_trimming_removes_invented_surface(square_cloud, square_trimmed):
    p, n = square_cloud
    # untrimmed: Open3D continues the open sheet to the walls of its reconstruction cube (1.1 × the
    # bounding cube), i.e. about 0.5 m of surface beyond each edge of the square that nothing saw
    raw_v, raw_f, _ = poisson_mesh(p, n, depth=7, density_quantile=0.0, max_support_m=np.inf, n_threads=1)
    assert distance_to_square(raw_v).max() > 2 * SUPPORT_M
    assert triangle_areas(raw_v, raw_f).sum() > 1.15 * SQUARE_M**2

    v, f, stats = square_trimmed
    assert_clean(v, f)
    # every point lies in the square, so a vertex within SUPPORT_M of a point lies within SUPPORT_M of it
    assert distance_to_square(v).max() <= SUPPORT_M + 1e-9
    area = triangle_areas(v, f).sum()
    assert abs(area - SQUARE_M**2) <= 0.1 * SQUARE_M**2, (
        f"area {area:.1f} m² for a {SQUARE_M**2:.0f} m² square"
    )
    assert stats["triangles_after_support"] < stats["triangles_after_density"]


def test_density_quantile_removes_that_fraction_of_vertices(square_cloud):
    # The density trim is relative (the reference code's 0.1 quantile): on a cloud that fills its cube it
    # removes real surface too, which is why the support trim exists.
    p, n = square_cloud
    v, f, stats = poisson_mesh(p, n, depth=7, density_quantile=0.1, max_support_m=np.inf, n_threads=1)
    assert stats["density_threshold"] is not None
    assert stats["triangles_after_density"] < stats["raw_triangles"]
    assert 0.75 * stats["raw_vertices"] < len(v) <= 0.9 * stats["raw_vertices"] + 1
    assert_clean(v, f)


def test_crop_keeps_centroids_in_the_half_open_box_and_tiles_partition(square_cloud, square_trimmed):
    p, n = square_cloud
    v, f, _ = square_trimmed
    full = np.sort(np.round(v[f].mean(1), 9).view("f8,f8,f8").ravel())
    parts = []
    for box in [(-1.0, -1.0, 4.0, 11.0), (4.0, -1.0, 11.0, 11.0)]:
        cv, cf, stats = poisson_mesh(p, n, crop=box, **TRIM_KW)
        assert_clean(cv, cf)
        c = cv[cf].mean(1)
        assert ((c[:, 0] >= box[0]) & (c[:, 0] < box[2]) & (c[:, 1] >= box[1]) & (c[:, 1] < box[3])).all()
        assert stats["triangles_after_crop"] < stats["triangles_after_support"]
        parts.append(np.round(c, 9).view("f8,f8,f8").ravel())
    # boxes that tile the plane keep every triangle exactly once
    assert np.array_equal(np.sort(np.concatenate(parts)), full)


# ---------------------------------------------------------------------- small and bad input
def test_fewer_than_min_points_give_an_empty_mesh():
    rng = np.random.default_rng(4)
    p = rng.normal(size=(MIN_POINTS - 1, 3))
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    v, f, stats = poisson_mesh(p, n, depth=7)
    assert v.shape == (0, 3) and f.shape == (0, 3) and f.dtype == np.int32
    assert "skipped" in stats and stats["input_points"] == MIN_POINTS - 1


def _good():
    p = np.random.default_rng(5).normal(size=(200, 3))
    return p, p / np.linalg.norm(p, axis=1, keepdims=True)


def _with(array, row, value):
    a = array.copy()
    a[row] = value
    return a


P, N = _good()


@pytest.mark.parametrize(
    ("points", "normals", "kwargs", "match"),
    [
        (np.zeros((0, 3)), np.zeros((0, 3)), {}, "empty"),
        (P[:, :2], N, {}, "shape"),
        (P, N[:-1], {}, "rows"),
        (_with(P, 7, [np.nan, 0, 0]), N, {}, r"points\[7\]"),
        (P, _with(N, 3, [0, np.inf, 0]), {}, r"normals\[3\]"),
        (P, _with(N, 11, [0, 0, 1.5]), {}, r"normals\[11\] has length 1.5"),
        (P, N * 0.5, {}, "unit"),
        (P, N, {"depth": 0}, "depth"),
        (P, N, {"depth": 9.5}, "depth"),
        (P, N, {"density_quantile": 1.0}, "density_quantile"),
        (P, N, {"max_support_m": 0.0}, "max_support_m"),
        (P, N, {"scale": 0.9}, "scale"),
        (P, N, {"crop": (0, 0, 1)}, "crop"),
        (P, N, {"crop": (1, 0, 0, 1)}, "crop"),
    ],
)
def test_bad_input_raises_input_error(points, normals, kwargs, match):
    with pytest.raises(InputError, match=match) as err:
        poisson_mesh(points, normals, **kwargs)
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------------- labels and cleaning
def test_transfer_labels_takes_the_nearest_point_within_range():
    rng = np.random.default_rng(6)
    p = rng.uniform(0.0, 10.0, (500, 3))
    labels = rng.random(500) < 0.5
    v = np.concatenate([rng.uniform(0.0, 10.0, (300, 3)), [[50.0, 50.0, 50.0]]])
    got = transfer_labels(v, p, labels, max_distance_m=1.0)
    d = np.linalg.norm(v[:, None] - p[None], axis=2)  # brute force reference
    expected = np.where(d.min(1) <= 1.0, labels[d.argmin(1)], False)
    assert got.dtype == bool and np.array_equal(got, expected)
    assert not got[-1]
    assert np.array_equal(transfer_labels(v, p, labels.astype(int)), got)
    with pytest.raises(InputError, match="point_labels"):
        transfer_labels(v, p, labels[:-1])
    with pytest.raises(InputError, match="point_labels"):
        transfer_labels(v, p, np.full(500, 2))


def test_clean_faces_removes_degenerate_duplicated_and_unreferenced():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [9, 9, 9], [1, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [2, 1, 0], [0, 1, 3], [0, 0, 2], [1, 5, 2], [5, 2, 1]])
    cv, cf, kept, counts = clean_faces(v, f)
    # [2,1,0] duplicates [0,1,2]; [0,1,3] is collinear; [0,0,2] repeats; [5,2,1] duplicates [1,5,2]
    assert counts == {"degenerate": 2, "duplicated": 2, "unreferenced_vertices": 2}
    assert np.array_equal(kept, [0, 1, 2, 5])
    assert np.array_equal(cv[cf], v[np.array([[0, 1, 2], [1, 5, 2]])])
