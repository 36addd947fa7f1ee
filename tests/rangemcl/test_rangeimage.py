"""Range-image projection and back-projection, by properties on random clouds and by Eq. 1 itself."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rangemcl.errors import InputError
from rangemcl.rangeimage import RangeImageGeometry, azimuth_to_column, column_azimuth_rad, point_directions
from rangemcl.sensors import load_spec, preset_names


def eq1_pixel(points: np.ndarray, h: int, w: int, up_deg: float, down_deg: float):
    """Paper Eq. 1 written out independently: (row, col) as floats before flooring."""
    r = np.linalg.norm(points, axis=1)
    u = 0.5 * (1 - np.arctan2(points[:, 1], points[:, 0]) / np.pi) * w
    fov = np.deg2rad(up_deg - down_deg)
    v = (1 - (np.arcsin(points[:, 2] / r) + abs(np.deg2rad(down_deg))) / fov) * h
    return v, u


@pytest.mark.parametrize("name", preset_names())
def test_spec_grid_round_trip_by_angles(name):
    """Ranges → vertex map → projection by angles alone gives back every pixel and its range."""
    spec = load_spec(name)
    geo = RangeImageGeometry.for_spec(spec)
    assert geo.shape == (spec.beams, spec.columns)
    rng = np.random.default_rng(7)
    ranges = rng.uniform(1.0, spec.max_range_m, geo.shape).astype(np.float32)
    ranges[rng.random(geo.shape) < 0.3] = 0.0
    vertices = geo.back_project(ranges)
    valid = ranges > 0
    points = vertices[valid]  # (N, 3)
    image = geo.project(points)
    assert np.array_equal(image.valid, valid)
    np.testing.assert_allclose(image.ranges, ranges, rtol=0, atol=2e-4 + 2e-6 * spec.max_range_m)
    rows, cols = np.nonzero(valid)
    assert np.array_equal(image.rows, rows) and np.array_equal(image.cols, cols)
    assert np.array_equal(image.index[valid], np.arange(len(points)))


@pytest.mark.parametrize("name", ["os1-64", "vlp-16"])
def test_spec_grid_given_pixels(name):
    """With ring and column given (our own sensors), projection places each point in its own pixel."""
    spec = load_spec(name)
    geo = RangeImageGeometry.for_spec(spec)
    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.5, 50.0, geo.shape)
    rows, cols = np.indices(geo.shape)
    points = geo.back_project(ranges).reshape(-1, 3)
    ring = geo.row_beam[rows.ravel()]
    image = geo.project(points, rows=spec.row_of_beam[ring], cols=cols.ravel())
    np.testing.assert_allclose(image.ranges, ranges, atol=1e-4)
    assert np.array_equal(image.index.ravel(), np.arange(points.shape[0]))


def test_spec_rows_sorted_highest_first():
    for name in preset_names():
        geo = RangeImageGeometry.for_spec(load_spec(name))
        assert np.all(np.diff(geo.row_elevation_rad) <= 0)
        assert geo.directions[0, :, 2].mean() >= geo.directions[-1, :, 2].mean()


def test_columns_follow_eq1():
    w = 1024
    az = column_azimuth_rad(w)
    assert np.array_equal(azimuth_to_column(az, w), np.arange(w))  # pixel centres round trip
    forward = azimuth_to_column(np.array([0.0]), w)[0]
    assert forward == w // 2  # column W/2 looks forward
    left = azimuth_to_column(np.array([np.pi / 2]), w)[0]
    assert left == w // 4  # +y (left) is a quarter turn before forward
    assert azimuth_to_column(np.array([np.pi]), w)[0] == 0
    assert azimuth_to_column(np.array([-np.pi + 1e-9]), w)[0] == w - 1


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(8, 128),
    w=st.sampled_from([360, 512, 1024, 2048]),
    up=st.floats(2.0, 25.0),
    down=st.floats(-30.0, -2.0),
)
def test_eq1_projection_matches_formula(seed, h, w, up, down):
    rng = np.random.default_rng(seed)
    n = 3000
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.deg2rad(rng.uniform(down - 3, up + 3, n))  # some points outside the FOV
    r = rng.uniform(0.5, 80.0, n)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    geo = RangeImageGeometry.for_fov(h, w, up, down)
    image = geo.project(pts)
    v, u = eq1_pixel(pts, h, w, up, down)
    inside = (v >= 0) & (v <= h)
    # away from pixel borders, rows and columns are the floors of Eq. 1 (borders: float rounding decides)
    clear = inside & (np.abs(v - np.round(v)) > 1e-6) & (np.abs(u - np.round(u)) > 1e-6)
    assert np.array_equal(image.rows[clear], np.minimum(np.floor(v[clear]), h - 1))
    assert np.array_equal(image.cols[clear], np.floor(u[clear]).astype(int) % w)
    assert np.all(image.rows[~inside] == -1)
    # closest point wins each pixel
    for row, col in zip(*np.nonzero(image.valid), strict=True):
        members = (image.rows == row) & (image.cols == col)
        assert image.ranges[row, col] == pytest.approx(r[members].min(), abs=1e-4)
        assert r[image.index[row, col]] == r[members].min()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_eq1_back_projection_within_half_a_pixel(seed):
    h, w, up, down = 64, 1024, 3.0, -25.0
    rng = np.random.default_rng(seed)
    n = 2000
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.deg2rad(rng.uniform(down, up, n))
    r = rng.uniform(1.0, 80.0, n)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    geo = RangeImageGeometry.for_fov(h, w, up, down)
    image = geo.project(pts)
    vertices = geo.back_project(image.ranges)
    won = image.index[image.valid]
    got = vertices[image.valid]
    d_true, r_true = point_directions(pts[won])
    d_got, r_got = point_directions(got)
    np.testing.assert_allclose(r_got, r_true, rtol=1e-5)
    half_pixel = 0.5 * np.hypot(2 * np.pi / w, np.deg2rad(up - down) / h)
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", d_true, d_got), -1, 1))
    assert angle.max() <= half_pixel * 1.001


def test_projection_drops_bad_points():
    geo = RangeImageGeometry.for_fov(16, 64, 15.0, -15.0)
    pts = np.array([[np.nan, 0, 0], [0, 0, 0], [10, 0, 0], [10, 0, 50], [np.inf, 1, 1]])
    image = geo.project(pts)
    assert image.rows.tolist() == [-1, -1, image.rows[2], -1, -1]
    assert image.rows[2] >= 0 and image.valid.sum() == 1
    assert image.ranges[image.valid][0] == pytest.approx(10.0)


def test_bad_shapes_are_input_errors():
    geo = RangeImageGeometry.for_fov(16, 64, 15.0, -15.0)
    with pytest.raises(InputError, match="shape"):
        geo.project(np.zeros((5, 2)))
    with pytest.raises(InputError, match="shape"):
        geo.back_project(np.zeros((15, 64)))
    with pytest.raises(InputError, match="fov"):
        RangeImageGeometry.for_fov(16, 64, -15.0, 15.0)
    with pytest.raises(InputError, match="rows/cols"):
        geo.project(np.ones((3, 3)), rows=np.zeros(2, int), cols=np.zeros(3, int))


def test_back_projection_of_empty_pixels_is_zero():
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16"))
    vertices = geo.back_project(np.zeros(geo.shape))
    assert not vertices.any()


def test_point_directions_unit_and_range():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(100, 3)) * 20
    origin = np.array([1.0, -2.0, 0.5])
    d, r = point_directions(pts, origin)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(origin + d * r[:, None], pts, atol=1e-9)
    d0, r0 = point_directions(np.zeros((1, 3)))
    assert r0[0] == 0 and not d0.any()
