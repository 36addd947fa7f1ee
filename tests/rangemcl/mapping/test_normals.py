"""Range-image normals (paper Eq. 2) against scenes whose surfaces are known analytically.

Every scene is cast here independently of the code under test: a pixel's range is the distance along its
ray (origin and direction from the grid) to a plane, or to the inside of an axis-aligned box by a slab
test. Vertex maps come from ``back_project`` (float32), so "exact" means within 1e-3 rad.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import maximum_filter, minimum_filter

from rangemcl.errors import InputError
from rangemcl.mapping.normals import scan_normals, vertex_map_normals
from rangemcl.rangeimage import RangeImageGeometry, azimuth_to_column
from rangemcl.sensors import load_spec

TOL_RAD = 1e-3


# ------------------------------------------------------------------------------------------- scenes
def plane_ranges(geo: RangeImageGeometry, normal, offset: float, max_range: float = np.inf) -> np.ndarray:
    """Range along each pixel ray to the plane ``normal · x = offset`` (0 where the ray misses it)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    along = geo.directions @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offset - geo.origins @ n) / along
    return np.where(np.isfinite(t) & (t > 0) & (t < max_range), t, 0.0)


def box_from_inside(geo: RangeImageGeometry, lo, hi):
    """Slab test for rays leaving an axis-aligned box around the sensor: range, the hit face's inward
    normal, and a face id (2·axis + 1 for the face on the + side of that axis)."""
    o, d = geo.origins, geo.directions
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axis = np.where(d > 0, (np.asarray(hi) - o) / d, np.where(d < 0, (np.asarray(lo) - o) / d, np.inf))
    axis = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, axis[..., None], -1)[..., 0]
    positive = np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0
    normal = np.zeros(d.shape)
    np.put_along_axis(normal, axis[..., None], np.where(positive, -1.0, 1.0)[..., None], -1)
    return t, normal, 2 * axis + positive


# the six inward face normals by face id
FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.einsum("...i,...i->...", a, b) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.arccos(np.clip(cos, -1.0, 1.0))


def os1() -> RangeImageGeometry:
    return RangeImageGeometry.for_spec(load_spec("os1-64"))


def assert_unit_and_facing(normals, ok, vertices):
    assert normals.dtype == np.float32 and ok.dtype == bool
    np.testing.assert_allclose(np.linalg.norm(normals[ok], axis=-1), 1.0, atol=1e-5)
    assert np.all(normals[~ok] == 0)
    assert np.all(np.einsum("...i,...i->...", normals[ok], vertices[ok]) <= 0)


# ------------------------------------------------------------------------------------------- planes
@pytest.mark.parametrize(
    ("normal", "offset", "max_range"),
    [((0.0, 0.0, 1.0), -1.73, 200.0), ((0.3, -0.2, 0.93), -2.0, 120.0), ((-0.8, 0.5, 0.2), 6.0, 120.0)],
    ids=["ground", "tilted", "steep-wall"],
)
def test_plane_normals_equal_the_plane_normal(normal, offset, max_range):
    geo = os1()
    ranges = plane_ranges(geo, normal, offset, max_range)
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0)
    assert_unit_and_facing(normals, ok, vertices)
    n = np.asarray(normal) / np.linalg.norm(normal)
    toward_sensor = n if offset < 0 else -n  # the sensor (origin) lies on the side normal·x > offset
    assert angle(normals[ok], toward_sensor).max() < TOL_RAD
    # every pixel within 30 m has a normal; farther ones may be dropped only at grazing incidence
    hit = ranges > 0
    assert np.all(ok[hit & (ranges < 30.0)])
    grazing = np.degrees(np.arcsin(np.abs(geo.directions @ n)))
    assert np.all(grazing[hit & ~ok] < 10.0)


def test_plane_normals_without_edge_limit_cover_every_return():
    geo = os1()
    ranges = plane_ranges(geo, (0.3, -0.2, 0.93), -2.0, 120.0)
    normals, ok = vertex_map_normals(geo.back_project(ranges), ranges > 0, max_edge_m=None)
    # all but pixels near the 120 m cut (whose row neighbours miss the plane) have normals
    assert ok[(ranges > 0) & (ranges < 50.0)].all()
    assert ok.sum() > 0.99 * (ranges > 0).sum()
    assert angle(normals[ok], (0.3, -0.2, 0.93)).max() < TOL_RAD


# ------------------------------------------------------------------------------------------- box
def face_band(geo: RangeImageGeometry, face: np.ndarray):
    """Per pixel: whether its 3×3 neighbourhood (in azimuth order, i.e. destaggered) spans several faces,
    and which faces it contains ``(H, W, 6)``."""
    h, w = geo.shape
    d = geo.directions
    col = azimuth_to_column(np.arctan2(d[..., 1], d[..., 0]), w)
    rows = np.arange(h)[:, None]
    by_azimuth = np.full((h, w), -1)
    by_azimuth[rows, col] = face
    assert np.all(by_azimuth >= 0)  # one pixel per (row, azimuth column)
    present = np.stack(
        [maximum_filter((by_azimuth == f).astype(np.uint8), 3, mode="wrap")[rows, col] > 0 for f in range(6)],
        axis=-1,
    )
    return present.sum(axis=-1) > 1, present


@pytest.mark.parametrize("grid", ["eq1", "os1-64"])
def test_box_faces_get_their_normals(grid):
    """Box around the sensor. Pixels whose 3×3 neighbourhood lies on one face get that face's normal
    exactly. Pixels in the band along the box edges (neighbourhood on two faces) are checked loosely: all
    are unit and face the sensor, and at least 90 % have exactly the normal of a face in their
    neighbourhood (measured: 94 % on the Eq. 1 grid, 96 % on os1-64). The rest are stencils that cannot
    stay on one face — the image's bottom row under a wall, whose only row neighbour is on the wall — or
    pixels within about a centimetre of the crease."""
    geo = RangeImageGeometry.for_fov(64, 1024, 16.6, -16.6) if grid == "eq1" else os1()
    ranges, face_normal, face = box_from_inside(geo, (-4.0, -3.0, -1.73), (6.0, 5.0, 2.5))
    vertices = geo.back_project(ranges)
    if grid == "eq1":
        normals, ok = vertex_map_normals(vertices, ranges > 0)
    else:  # staggered beams: through scan_normals, which destaggers the rows
        rows, cols = np.indices(geo.shape)
        n, v = scan_normals(vertices.reshape(-1, 3), geo, rows.ravel(), cols.ravel())
        normals, ok = n.reshape(vertices.shape), v.reshape(geo.shape)
    assert_unit_and_facing(normals, ok, vertices)
    edge, present = face_band(geo, face)
    inside = ~edge
    assert np.all(ok[inside])
    assert angle(normals[inside], face_normal[inside]).max() < TOL_RAD
    cos = normals @ FACE_NORMALS.T  # (H, W, 6)
    one_face = np.any(present & (cos > np.cos(TOL_RAD)), axis=-1)
    band = edge & ok
    assert band.sum() > 1000
    assert one_face[band].mean() > 0.90


def test_box_staggered_raw_grid_is_exact_inside_faces():
    """Straight on the staggered os1-64 vertex map (no destaggering) interiors are still exact: the row
    neighbours are off in azimuth but on the same plane."""
    geo = os1()
    ranges, face_normal, face = box_from_inside(geo, (-4.0, -3.0, -1.73), (6.0, 5.0, 2.5))
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0)
    assert_unit_and_facing(normals, ok, vertices)
    far_from_edges = minimum_filter(face, (5, 41), mode="wrap") == maximum_filter(face, (5, 41), mode="wrap")
    assert angle(normals[far_from_edges], face_normal[far_from_edges]).max() < TOL_RAD


# ------------------------------------------------------------------------------------------- wrap-around
def test_seam_column_uses_the_wrapped_neighbour():
    """A plane behind the sensor spans the seam (columns W−1 and 0 look along −x)."""
    geo = RangeImageGeometry.for_fov(16, 360, 15.0, -25.0)
    w = geo.shape[1]
    ranges = plane_ranges(geo, (1.0, 0.2, 0.1), -5.0)
    vertices = geo.back_project(ranges)
    valid = ranges > 0
    assert valid[:, [0, w - 1]].all()
    expected = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    normals, ok = vertex_map_normals(vertices, valid)
    assert ok[:, [0, w - 1]].all()
    assert angle(normals[ok], expected).max() < TOL_RAD

    # take away the seam column's backward neighbour: only the wrapped forward one is left
    cut = valid.copy()
    cut[:, w - 2] = False
    for crease_tol_deg in (1.0, None):
        normals, ok = vertex_map_normals(vertices, cut, crease_tol_deg=crease_tol_deg)
        assert ok[:, w - 1].all()
        assert angle(normals[:, w - 1], expected).max() < TOL_RAD
        _, ok_nowrap = vertex_map_normals(vertices, cut, wrap_columns=False, crease_tol_deg=crease_tol_deg)
        assert not ok_nowrap[:, w - 1].any()
        assert ok_nowrap[:, 0].all()  # column 0 has column 1


def test_seam_crease_is_resolved_across_the_wrap():
    """Two planes meeting exactly at the seam: each seam column keeps its own plane's normal."""
    geo = RangeImageGeometry.for_fov(16, 360, 15.0, -25.0)
    w = geo.shape[1]
    left = np.array([1.0, -0.6, 0.0])  # seen by columns 0.. (azimuth just below +π, y > 0)
    right = np.array([1.0, 0.6, 0.0])  # seen by columns ..W−1 (y < 0)
    r_left = plane_ranges(geo, left, -5.0)
    r_right = plane_ranges(geo, right, -5.0)
    y_positive = geo.directions[..., 1] > 0
    ranges = np.where(y_positive, r_left, r_right)
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0)
    for col, n in ((0, left), (w - 1, right)):
        assert ok[:, col].all()
        assert angle(normals[:, col], n / np.linalg.norm(n)).max() < TOL_RAD


# ------------------------------------------------------------------------------------------- discontinuities
def near_and_far_walls(geo: RangeImageGeometry):
    """A tilted near panel (≈5 m, inside an azimuth/elevation window) in front of a far wall at x = 15."""
    near_n = np.array([-np.cos(np.radians(30)), np.sin(np.radians(30)), 0.0])
    far_n = np.array([-1.0, 0.0, 0.0])
    d = geo.directions
    azimuth = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    elevation = np.degrees(np.arcsin(d[..., 2]))
    window = (np.abs(azimuth) < 10.0) & (np.abs(elevation) < 8.0)
    r_near = plane_ranges(geo, near_n, near_n @ [5.0, 0.0, 0.0])
    r_far = plane_ranges(geo, far_n, -15.0)
    ranges = np.where(window, r_near, r_far)
    expected = np.where(window[..., None], near_n, far_n)  # both already point toward the sensor
    return ranges, expected, window


def test_depth_discontinuity_never_averages():
    geo = RangeImageGeometry.for_fov(64, 1024, 16.6, -16.6)
    ranges, expected, _ = near_and_far_walls(geo)
    vertices = geo.back_project(ranges)
    valid = ranges > 0
    normals, ok = vertex_map_normals(vertices, valid)
    assert_unit_and_facing(normals, ok, vertices)
    # every normal is its own surface's: pixels on the edge use their same-surface neighbour
    assert angle(normals[ok], expected[ok]).max() < TOL_RAD
    assert ok[valid & (ranges < 30.0)].all()  # farther, the wall is seen at grazing angles
    # without the edge test and the crease scoring (plain Eq. 2), the edges average the two walls
    plain, ok_plain = vertex_map_normals(vertices, valid, max_edge_m=None, crease_tol_deg=None)
    assert (angle(plain[ok_plain], expected[ok_plain]) > np.radians(5)).sum() > 20


def test_pixels_without_a_same_surface_neighbour_are_invalid():
    geo = RangeImageGeometry.for_fov(64, 1024, 16.6, -16.6)
    ranges, _, window = near_and_far_walls(geo)
    cols = np.flatnonzero(window.any(axis=0))
    ranges = ranges.copy()
    # a "mixed" column between the two walls just right of the panel (as real edges give) ...
    mixed_col = cols[-1] + 1
    rows = np.flatnonzero(window.any(axis=1))
    ranges[rows, mixed_col] = 10.0
    # ... and a one-column pole at 6 m far left of the panel
    pole_col = cols[0] - 40
    ranges[10:50, pole_col] = 6.0 / np.cos(np.arcsin(geo.directions[10:50, pole_col, 2]))
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0)
    assert not ok[rows, mixed_col].any()
    assert not ok[10:50, pole_col].any()
    # the far wall beside them keeps its normal
    assert ok[rows, mixed_col + 1].all() and ok[10:50, pole_col + 1].all()
    assert angle(normals[rows, mixed_col + 1], [-1, 0, 0]).max() < TOL_RAD


def test_edge_limit_scales_with_range():
    """The same 3 m step between neighbouring columns (0.35° apart) is a depth edge at 10 m (limit
    1 m + 10 m·sin 0.35°/sin 3° = 2.2 m) but one slanted surface at 60 m (limit 8 m)."""
    geo = RangeImageGeometry.for_fov(8, 1024, 2.0, -2.0)
    for r0, is_edge in ((10.0, True), (60.0, False)):
        ranges = np.full(geo.shape, r0)
        ranges[:, 600:] += 3.0
        vertices = geo.back_project(ranges)
        normals, ok = vertex_map_normals(vertices, ranges > 0, crease_tol_deg=None)
        assert ok[:, 599].all()
        # own surface (a sphere around the sensor): the normal points back along the ray
        off = angle(normals[:, 599], -geo.directions[:, 599])
        if is_edge:  # the forward neighbour is across an edge: the backward one is used
            assert off.max() < np.radians(1.0)
        else:  # Eq. 2's forward difference spans the step
            assert off.min() > np.radians(45.0)


# ------------------------------------------------------------------------------------------- properties
def random_rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


quaternions = st.tuples(*[st.floats(-1, 1, allow_nan=False) for _ in range(4)]).filter(
    lambda q: np.linalg.norm(q) > 0.1
)


@settings(max_examples=6, deadline=None)
@given(q=quaternions)
def test_rotating_the_scene_rotates_the_normals(q):
    """Rotate every vertex (same pixel grid): each normal rotates with it. Near-ties in the crease
    choice may flip under float32 rounding, so up to 0.2 % of pixels may differ."""
    R = random_rotation(q)
    geo = RangeImageGeometry.for_fov(32, 512, 16.6, -16.6)
    ranges, _, _ = box_from_inside(geo, (-4.0, -3.0, -1.73), (6.0, 5.0, 2.5))
    ranges = np.where(geo.directions[..., 0] > 0.9, 3.0, ranges)  # a near panel: depth edges too
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0)
    rotated = (vertices.astype(np.float64) @ R.T).astype(np.float32)
    normals_r, ok_r = vertex_map_normals(rotated, ranges > 0)
    same = ok & ok_r
    assert (ok != ok_r).mean() < 0.002
    close = angle(normals_r[same], normals[same] @ R.T) < 1e-3
    assert close.mean() > 0.998


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise=st.sampled_from([0.0, 0.03, 0.3]))
def test_normals_are_unit_and_face_the_sensor(seed, noise):
    rng = np.random.default_rng(seed)
    geo = RangeImageGeometry.for_fov(32, 256, 16.6, -16.6)
    h, w = geo.shape
    smooth = 2.0 + 20.0 * rng.random((4, 8))
    ranges = smooth[np.arange(h) * 4 // h][:, np.arange(w) * 8 // w]  # piecewise-constant depths
    ranges = ranges + rng.normal(0.0, noise, (h, w))
    ranges[rng.random((h, w)) < 0.1] = 0.0
    ranges = np.clip(ranges, 0.0, None)
    vertices = geo.back_project(ranges)
    normals, ok = vertex_map_normals(vertices, ranges > 0, max_edge_m=[None, 0.5, 1.0][seed % 3])
    assert_unit_and_facing(normals, ok, vertices)
    assert not ok[ranges <= 0].any()


# ------------------------------------------------------------------------------------------- scan_normals
def test_scan_normals_give_each_pixel_winner_its_normal():
    geo = RangeImageGeometry.for_fov(32, 512, 16.6, -16.6)
    n = np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0])
    ranges = plane_ranges(geo, n, -1.73, 25.0)
    hit = ranges > 0
    points = geo.back_project(ranges)[hit].astype(np.float64)
    behind = points[::3] * 1.05  # same pixels, farther: they lose their pixel
    junk = np.array(
        [[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 50.0]]
    )  # dropped: NaN, origin, out of FOV
    cloud = np.concatenate([behind, points, junk])
    normals, valid = scan_normals(cloud, geo)
    assert normals.shape == (len(cloud), 3) and normals.dtype == np.float32
    k = len(behind)
    assert not valid[:k].any() and not valid[-3:].any()
    assert np.all(normals[~valid] == 0)
    assert valid[k : k + len(points)].mean() > 0.95
    assert angle(normals[valid], n).max() < TOL_RAD
    # the same as the per-pixel normals of the winners' vertex map (Eq. 1 grid: nothing to destagger)
    pixel_n, pixel_ok = vertex_map_normals(geo.back_project(np.where(hit, ranges, 0.0)), hit)
    np.testing.assert_allclose(normals[k : k + len(points)], pixel_n[hit], atol=1e-5)
    assert np.array_equal(valid[k : k + len(points)], pixel_ok[hit])


def test_scan_normals_with_given_pixels_and_empty_scan():
    geo = os1()
    ranges = plane_ranges(geo, (0.0, 0.0, 1.0), -1.73, 40.0)
    hit = ranges > 0
    rows, cols = np.nonzero(hit)
    normals, valid = scan_normals(geo.back_project(ranges)[hit], geo, rows, cols)
    assert valid.all()
    assert angle(normals, [0, 0, 1]).max() < TOL_RAD
    normals, valid = scan_normals(np.zeros((0, 3)), geo)
    assert normals.shape == (0, 3) and valid.shape == (0,)


def test_bad_inputs_raise():
    with pytest.raises(InputError):
        vertex_map_normals(np.zeros((4, 5)), np.zeros((4, 5), bool))
    with pytest.raises(InputError):
        vertex_map_normals(np.zeros((4, 5, 3)), np.zeros((4, 4), bool))
    with pytest.raises(InputError):
        vertex_map_normals(np.zeros((4, 5, 3)), np.zeros((4, 5), bool), max_edge_m=-1.0)
    with pytest.raises(InputError):
        scan_normals(np.zeros((4, 2)), os1())
    normals, ok = vertex_map_normals(np.zeros((4, 5, 3)), np.ones((4, 5), bool))  # all at the origin
    assert not ok.any() and not normals.any()
