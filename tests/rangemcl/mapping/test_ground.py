"""Ground labels on a synthetic street cast here analytically: a ground plane 1.73 m below the sensor,
walls, two car-like boxes on the ground, and a carport roof above the sensor on a post."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.mapping.ground import ground_normal, label_ground
from rangemcl.mapping.normals import scan_normals
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.sensors import load_spec

HEIGHT = 1.73

# axis-aligned boxes in the world frame (ground at z = 0, sensor at (0, 0, HEIGHT))
BOXES = [
    ((24.0, -30.0, 0.0), (25.0, 30.0, 8.0)),  # wall ahead
    ((-23.0, -30.0, 0.0), (-22.0, 30.0, 8.0)),  # wall behind
    ((-23.0, 15.0, 0.0), (25.0, 16.0, 6.0)),  # wall left
    ((-23.0, -17.0, 0.0), (25.0, -16.0, 10.0)),  # wall right
    ((6.0, -3.5, 0.0), (10.5, -1.7, 1.5)),  # car
    ((-9.0, 2.0, 0.0), (-4.5, 3.8, 1.5)),  # car
    ((-3.0, -6.0, 3.0), (4.0, -1.0, 3.3)),  # carport roof, above the sensor
    ((-3.0, -6.5, 0.0), (-2.7, -6.0, 3.0)),  # its post
]


def roll(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def slab_entry(o: np.ndarray, d: np.ndarray, lo, hi) -> np.ndarray:
    """Distance along each ray to where it enters the box (inf on a miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
    inside = (o >= lo) & (o <= hi)
    t_min = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=-1)
    t_max = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=-1)
    return np.where((t_min <= t_max) & (t_min > 0), t_min, np.inf)


def cast(geo: RangeImageGeometry, R: np.ndarray = np.eye(3), max_range: float = 80.0):
    """Points (sensor frame) of one sweep, their pixels, and what each hit (0 ground, k box k)."""
    o = geo.origins @ R.T + [0.0, 0.0, HEIGHT]
    d = geo.directions @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[..., 2] < 0, -o[..., 2] / d[..., 2], np.inf)
    t = np.stack([t_ground] + [slab_entry(o, d, lo, hi) for lo, hi in BOXES])
    what, t = np.argmin(t, axis=0), np.min(t, axis=0)
    hit = t < max_range
    rows, cols = np.nonzero(hit)
    points = geo.origins[hit] + t[hit, None] * geo.directions[hit]
    return points, rows, cols, what[hit]


@pytest.fixture(scope="module")
def geo() -> RangeImageGeometry:
    return RangeImageGeometry.for_spec(load_spec("os1-64"))


@pytest.mark.parametrize("roll_deg", [0.0, 5.0])
def test_ground_of_a_street_scene(geo, roll_deg):
    R = roll(roll_deg)
    points, rows, cols, what = cast(geo, R)
    normals, valid = scan_normals(points, geo, rows, cols)
    up = R.T @ [0.0, 0.0, 1.0]  # the world's up in the sensor frame
    e3 = ground_normal(points, normals, valid)
    assert np.degrees(np.arccos(min(1.0, e3 @ up))) < 0.1
    ground = label_ground(points, normals, valid, sensor_height_m=HEIGHT)
    is_ground = what == 0
    assert is_ground.sum() > 15_000 and (~is_ground).sum() > 30_000
    assert ground[is_ground].mean() > 0.98
    assert ground[~is_ground].mean() < 0.01
    for k in (5, 6, 7):  # car tops and sides, the carport roof and its underside: not ground
        assert ground[what == k].mean() < 0.01


def test_tilted_sensor_needs_e3(geo):
    """With a 5° roll the far ground on one side is more than 1 m "higher" in sensor z: thresholding the
    raw z instead of the height along e3 loses it."""
    points, rows, cols, what = cast(geo, roll(5.0))
    normals, valid = scan_normals(points, geo, rows, cols)
    level = label_ground(points, normals, valid, sensor_height_m=HEIGHT, e3=[0.0, 0.0, 1.0])
    assert level[what == 0].mean() < 0.95
    assert label_ground(points, normals, valid, sensor_height_m=HEIGHT)[what == 0].mean() > 0.98


def test_e3_from_points_alone(geo):
    """Without normals, e3 comes from all points (the paper): in this scene still close to up."""
    points, *_ = cast(geo)
    e3 = ground_normal(points)
    assert e3[2] > np.cos(np.radians(2.0))


def test_thresholds():
    points = np.array([[5.0, 0.0, -1.73], [5.0, 0.0, -0.80], [5.0, 0.0, -0.70], [5.0, 0.0, -1.73]])
    tilt = np.radians(25.0)
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [np.sin(tilt), 0.0, np.cos(tilt)]])
    valid = np.ones(4, bool)
    kw = dict(sensor_height_m=1.73, e3=[0.0, 0.0, 1.0])
    assert label_ground(points, normals, valid, **kw).tolist() == [True, True, False, True]
    assert label_ground(points, normals, valid, max_angle_deg=20.0, **kw).tolist() == [
        True,
        True,
        False,
        False,
    ]
    assert label_ground(points, -normals, valid, **kw).tolist() == [True, True, False, True]  # |n · e3|
    assert label_ground(points, normals, valid, z_margin_m=0.5, **kw).tolist() == [True, False, False, True]
    valid[0] = False
    assert not label_ground(points, normals, valid, **kw)[0]


def test_ground_normal_points_up_and_falls_back():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-20, 20, (500, 2))
    tilted = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    z = -(tilted[0] * xy[:, 0] + tilted[1] * xy[:, 1] + 1.73) / tilted[2]
    plane = np.column_stack([xy, z])
    np.testing.assert_allclose(ground_normal(plane), tilted, atol=1e-9)
    assert ground_normal(np.zeros((0, 3))).tolist() == [0.0, 0.0, 1.0]
    assert ground_normal(plane[:5]).tolist() == [0.0, 0.0, 1.0]  # too few points
    line = np.outer(np.linspace(-5, 5, 50), [1.0, 2.0, 0.0])
    assert ground_normal(line).tolist() == [0.0, 0.0, 1.0]  # collinear
    wall = np.column_stack([np.full(200, 5.0), rng.uniform(-20, 20, 200), rng.uniform(-1.7, 20.0, 200)])
    assert ground_normal(wall).tolist() == [0.0, 0.0, 1.0]  # best plane is vertical: not the ground
    # with normals: only up-facing points count, so a big wall does not tilt e3
    up = np.tile([0.0, 0.0, 1.0], (len(plane), 1))
    side = np.tile([-1.0, 0.0, 0.0], (len(wall), 1))
    both, both_n = np.concatenate([plane, wall]), np.concatenate([up, side])
    np.testing.assert_allclose(ground_normal(both, both_n, np.ones(len(both), bool)), tilted, atol=1e-9)
    assert ground_normal(both, both_n, np.zeros(len(both), bool)).tolist() == [0.0, 0.0, 1.0]


def test_empty_and_invalid_scans(geo):
    empty = np.zeros((0, 3))
    labels = label_ground(empty, empty, np.zeros(0, bool), sensor_height_m=HEIGHT)
    assert labels.shape == (0,) and labels.dtype == bool
    points, rows, cols, _ = cast(geo)
    normals, _ = scan_normals(points, geo, rows, cols)
    labels = label_ground(points, normals, np.zeros(len(points), bool), sensor_height_m=HEIGHT)
    assert labels.shape == (len(points),) and not labels.any()
    nan = np.full((3, 3), np.nan)
    assert not label_ground(nan, nan, np.ones(3, bool), sensor_height_m=HEIGHT).any()


def test_bad_inputs_raise():
    p = np.zeros((3, 3))
    with pytest.raises(InputError):
        label_ground(p, np.zeros((2, 3)), np.ones(3, bool), sensor_height_m=HEIGHT)
    with pytest.raises(InputError):
        label_ground(p, p, np.ones(2, bool), sensor_height_m=HEIGHT)
    with pytest.raises(InputError):
        label_ground(p, p, np.ones(3, bool), sensor_height_m=HEIGHT, e3=[0.0, 0.0, 0.0])
    with pytest.raises(InputError):
        ground_normal(np.zeros((3, 2)))
