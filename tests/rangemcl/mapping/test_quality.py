"""Map quality (``rangemcl.mapping.quality``) against analytic answers: distances to a plane and a box,
a map equal to the truth, shifted by 0.1 m, and missing half of the surface."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.mapping.quality import map_quality, sample_surface, surface_distances


def plane(n: int = 20, step: float = 1.0, z: float = 0.0, origin=(0.0, 0.0)):
    """Square ``[0, n·step]²`` at height ``z`` (shifted by ``origin``), two triangles per cell."""
    xs = origin[0] + np.arange(n + 1) * step
    ys = origin[1] + np.arange(n + 1) * step
    X, Y = np.meshgrid(xs, ys)
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    f = np.array(
        [
            [0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6],
            [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
            [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5],
        ]
    )  # fmt: skip
    return v, f


def box_distance(p, lo, hi):
    """Exact distance from points to the surface of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    outside = np.linalg.norm(p - np.clip(p, lo, hi), axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    is_in = np.all((p > lo) & (p < hi), axis=1)
    return np.where(is_in, inside, outside)


def test_distances_to_a_plane_and_a_box():
    rng = np.random.default_rng(0)
    v, f = plane(10, 2.0)  # [0, 20]²
    p = np.column_stack([rng.uniform(-5, 25, 500), rng.uniform(-5, 25, 500), rng.uniform(-3, 3, 500)])
    dx = np.maximum(np.maximum(-p[:, 0], p[:, 0] - 20), 0)
    dy = np.maximum(np.maximum(-p[:, 1], p[:, 1] - 20), 0)
    np.testing.assert_allclose(surface_distances(p, v, f), np.sqrt(dx**2 + dy**2 + p[:, 2] ** 2), atol=1e-5)

    lo, hi = [1.0, -2.0, 0.5], [3.0, 1.0, 4.0]
    bv, bf = box(lo, hi)
    q = rng.uniform(-2, 6, (500, 3))
    np.testing.assert_allclose(surface_distances(q, bv, bf), box_distance(q, lo, hi), atol=1e-5)
    assert surface_distances(np.zeros((0, 3)), bv, bf).shape == (0,)


def test_distances_keep_precision_far_from_the_origin():
    utm = (512_345.0, 5_612_345.0)
    v, f = plane(10, 2.0, z=250.0, origin=utm)
    rng = np.random.default_rng(1)
    h = rng.uniform(-0.3, 0.3, 200)
    p = np.column_stack([utm[0] + rng.uniform(0, 20, 200), utm[1] + rng.uniform(0, 20, 200), 250.0 + h])
    np.testing.assert_allclose(surface_distances(p, v, f), np.abs(h), atol=1e-4)


def scene():
    """Ground 20 m × 20 m at 1 m triangles plus a box standing on it."""
    pv, pf = plane(20, 1.0)
    bv, bf = box([5.0, 5.0, 0.0], [8.0, 7.0, 3.0])
    return np.vstack([pv, bv]), np.vstack([pf, bf + len(pv)])


def test_a_map_equal_to_the_truth_is_perfect():
    v, f = scene()
    q = map_quality(v, f, v, f)
    for key in ("vertex_dist", "surface_dist"):
        for stat in ("median", "p90", "max", "mean"):
            assert q[f"{key}_{stat}_m"] < 1e-5
    assert q["completeness"] == 1.0 and q["surface_within_tolerance_share"] == 1.0
    assert q["map_vertices_n"] == len(v)
    # about one sample per 0.25² m² of the area (400 m² ground + 42 m² of box)
    assert q["map_surface_samples_n"] == math.ceil(442.0 / 0.25**2)
    assert q["reference_points_n"] == q["map_surface_samples_n"]
    for key, value in q.items():
        assert isinstance(value, float | int), key
        assert key.endswith(("_m", "_n", "_share", "completeness")), key


def test_a_map_shifted_by_10_cm():
    v, f = plane(20, 1.0)
    shifted = v + np.array([0.0, 0.0, 0.1])
    q = map_quality(shifted, f, v, f)
    for key in ("vertex_dist", "surface_dist"):
        for stat in ("median", "p90", "max", "mean"):
            assert q[f"{key}_{stat}_m"] == pytest.approx(0.1, abs=1e-5)
    assert q["completeness"] == 1.0  # within 0.2 m
    q = map_quality(shifted, f, v, f, tolerance_m=0.05)
    assert q["completeness"] == 0.0 and q["surface_within_tolerance_share"] == 0.0

    # a box grown by 10 cm on every side: every map vertex (a corner) is 0.1·√3 from the true box,
    # points on its faces 0.1 m (inside the true face's outline) up to 0.1·√3 (over a corner)
    bv, bf = box([0, 0, 0], [4, 4, 4])
    gv, gf = box([-0.1] * 3, [4.1] * 3)
    q = map_quality(gv, gf, bv, bf)
    assert q["vertex_dist_median_m"] == pytest.approx(0.1 * math.sqrt(3), abs=1e-5)
    assert q["surface_dist_median_m"] == pytest.approx(0.1, abs=1e-5)
    assert 0.1 - 1e-5 < q["surface_dist_max_m"] <= 0.1 * math.sqrt(3) + 1e-5


def test_a_map_missing_half_the_surface():
    v, f = plane(20, 1.0)  # [0, 20]²
    centroid_x = v[f].mean(axis=1)[:, 0]
    half = f[centroid_x < 10.0]
    # reference points on a 0.1 m grid: those with x <= 10 + tolerance are covered, exactly
    g = np.arange(200) * 0.1 + 0.05
    X, Y = np.meshgrid(g, g)
    ref = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    ref = np.vstack([ref, [[np.nan, 0.0, 0.0]]])
    q = map_quality(v, half, v, f, reference_points=ref)
    assert q["completeness"] == pytest.approx(np.mean(g <= 10.2), abs=1e-12)  # 0.51
    assert q["reference_points_n"] == 200 * 200 and q["reference_points_dropped_n"] == 1
    assert math.isnan(q["reference_sample_spacing_m"])
    assert q["vertex_dist_max_m"] < 1e-5  # what is there is right
    assert q["map_vertices_n"] == 11 * 21  # only the vertices the kept triangles use
    # reference sampled on the truth: about the same
    q = map_quality(v, half, v, f)
    assert q["completeness"] == pytest.approx(0.51, abs=0.02)


def test_sample_surface_is_uniform_and_capped():
    v, f = plane(4, 1.0)  # 16 m²
    pts, spacing = sample_surface(v, f, 0.1, seed=3)
    assert len(pts) == 1600 and spacing == 0.1
    assert np.all((pts[:, :2] >= 0) & (pts[:, :2] <= 4)) and np.all(pts[:, 2] == 0)
    counts = np.histogram2d(pts[:, 0], pts[:, 1], bins=2, range=[[0, 4], [0, 4]])[0]
    assert np.all(np.abs(counts - 400) < 4 * math.sqrt(400))  # each quarter holds about a quarter
    pts2, spacing2 = sample_surface(v, f, 0.1, seed=3, max_points=100)
    assert len(pts2) == 100 and spacing2 == pytest.approx(0.4)
    np.testing.assert_array_equal(sample_surface(v, f, 0.1, seed=3)[0], pts)  # seeded


def test_bad_inputs():
    v, f = plane(2)
    with pytest.raises(InputError, match="points"):
        surface_distances(np.zeros((3, 2)), v, f)
    with pytest.raises(InputError, match="NaN"):
        surface_distances([[np.nan, 0, 0]], v, f)
    with pytest.raises(InputError, match="out of range"):
        surface_distances([[0, 0, 0]], v, f + 100)
    with pytest.raises(InputError, match="no triangles"):
        map_quality(v, np.zeros((0, 3), int), v, f)
    with pytest.raises(InputError, match="tolerance_m"):
        map_quality(v, f, v, f, tolerance_m=-1.0)
