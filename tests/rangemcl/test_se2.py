"""Planar pose math (rangemcl.se2) by properties on random inputs."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rangemcl import se2
from rangemcl.se2 import (
    circular_mean,
    odometry_increment,
    pose2d,
    pose_matrix,
    rotation_roll_pitch,
    se2_between,
    se2_compose,
    se2_inverse,
    wrap_angle,
    yaw_matrix,
)

angles = st.floats(-1e3, 1e3, allow_nan=False)
coords = st.floats(-1e3, 1e3, allow_nan=False)
poses = st.tuples(coords, coords, st.floats(-10.0, 10.0, allow_nan=False)).map(np.array)


def assert_poses_close(a, b, atol=1e-8):
    """Same ``(..., 3)`` poses: positions close, yaws close on the circle."""
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a[..., :2], b[..., :2], rtol=0, atol=atol)
    assert np.all(np.abs(wrap_angle(a[..., 2] - b[..., 2])) < atol)


# ---------------------------------------------------------------------------------------------- angles


@given(angles)
def test_wrap_angle_range_idempotence_and_equivalence(a):
    w = wrap_angle(a)
    assert -np.pi < w <= np.pi
    assert wrap_angle(w) == w
    assert np.isclose(np.cos(w), np.cos(a), atol=1e-9) and np.isclose(np.sin(w), np.sin(a), atol=1e-9)


@given(st.lists(angles, min_size=0, max_size=50))
def test_wrap_angle_keeps_the_shape(a):
    arr = np.array(a, np.float64).reshape(-1, 1)
    w = wrap_angle(arr)
    assert w.shape == arr.shape and w.dtype == np.float64
    assert np.all((w > -np.pi) & (w <= np.pi))
    np.testing.assert_array_equal(wrap_angle(w), w)


def test_wrap_angle_edges_and_types():
    assert wrap_angle(np.pi) == np.pi and wrap_angle(-np.pi) == np.pi and wrap_angle(3 * np.pi) == np.pi
    assert wrap_angle(0.0) == 0.0 and wrap_angle(-0.0) == 0.0
    w = wrap_angle(1.0)
    assert isinstance(w, np.ndarray) and w.shape == ()  # 0-d: callers wrap it in float() as they need


@given(st.floats(-np.pi, np.pi), st.lists(st.floats(0.0, 1.5), min_size=1, max_size=20), st.integers(-3, 3))
def test_circular_mean_of_a_symmetric_spread_is_its_centre(centre, offsets, turns):
    o = np.array(offsets)
    a = centre + np.concatenate([o, -o]) + 2 * np.pi * turns  # any number of whole turns away
    m = circular_mean(a)
    assert isinstance(m, float) and -np.pi < m <= np.pi
    assert abs(wrap_angle(m - centre)) < 1e-9


def test_circular_mean_across_plus_minus_pi():
    assert abs(wrap_angle(circular_mean(np.array([np.pi - 0.1, -np.pi + 0.1])) - np.pi)) < 1e-12
    assert abs(circular_mean(np.array([np.pi - 0.1, -np.pi + 0.3])) - (-np.pi + 0.1)) < 1e-12
    # weights pull towards the heavier side, still across the seam
    m = circular_mean(np.array([np.pi - 0.2, -np.pi + 0.2]), np.array([3.0, 1.0]))
    assert np.pi - 0.2 < m <= np.pi


# ---------------------------------------------------------------------------------------------- (x, y, yaw)


@given(poses)
def test_compose_with_inverse_is_identity(a):
    assert_poses_close(se2_compose(a, se2_inverse(a)), np.zeros(3))
    assert_poses_close(se2_compose(se2_inverse(a), a), np.zeros(3))
    assert_poses_close(se2_inverse(se2_inverse(a)), a)


@given(poses, poses)
def test_between_undoes_compose(a, b):
    assert_poses_close(se2_between(a, se2_compose(a, b)), b, atol=1e-7)
    assert_poses_close(se2_compose(a, se2_between(a, b)), b, atol=1e-7)
    assert_poses_close(se2_between(a, b), se2_compose(se2_inverse(a), b), atol=1e-7)


@given(poses, poses, poses)
def test_compose_is_associative(a, b, c):
    assert_poses_close(se2_compose(se2_compose(a, b), c), se2_compose(a, se2_compose(b, c)), atol=1e-6)


@given(poses, poses)
def test_compose_and_between_match_the_4x4_matrices(a, b):
    Ta, Tb = pose_matrix(*a), pose_matrix(*b)
    assert_poses_close(se2_compose(a, b), pose2d(Ta @ Tb), atol=1e-7)
    assert_poses_close(se2_between(a, b), pose2d(np.linalg.inv(Ta) @ Tb), atol=1e-7)
    assert_poses_close(se2_inverse(a), pose2d(np.linalg.inv(Ta)), atol=1e-7)


@settings(max_examples=30)
@given(st.integers(0, 2**32 - 1))
def test_stacked_poses_match_one_at_a_time(seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(-50, 50, (7, 3))
    b = rng.uniform(-50, 50, (7, 3))
    comp, betw, inv = se2_compose(a, b), se2_between(a, b), se2_inverse(a)
    assert comp.shape == betw.shape == inv.shape == (7, 3)
    for i in range(7):
        np.testing.assert_array_equal(comp[i], se2_compose(a[i], b[i]))
        np.testing.assert_array_equal(betw[i], se2_between(a[i], b[i]))
        np.testing.assert_array_equal(inv[i], se2_inverse(a[i]))
    assert se2_compose(a[0], b).shape == (7, 3)  # broadcasting


@given(poses, poses)
def test_odometry_increment_replays_the_motion(prev, cur):
    rot1, trans, rot2 = odometry_increment(prev, cur)
    assert trans >= 0 and -np.pi < rot1 <= np.pi and -np.pi < rot2 <= np.pi
    heading = prev[2] + rot1
    replay = np.array([prev[0] + trans * np.cos(heading), prev[1] + trans * np.sin(heading), heading + rot2])
    assert_poses_close(replay, cur, atol=1e-7)


def test_odometry_increment_of_a_turn_on_the_spot():
    assert odometry_increment(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, -3.0])) == (
        0.0,
        0.0,
        float(wrap_angle(-6.0)),
    )


# ---------------------------------------------------------------------------------------------- 4×4 poses


@given(coords, coords, coords, st.floats(-np.pi, np.pi))
def test_pose2d_of_pose_matrix_round_trip(x, y, z, yaw):
    T = pose_matrix(x, y, yaw, z)
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0) and T[2, 3] == z
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    p = pose2d(T)
    assert p.shape == (3,) and p.dtype == np.float64
    assert p[0] == x and p[1] == y
    assert abs(wrap_angle(p[2] - yaw)) < 1e-12
    np.testing.assert_allclose(pose_matrix(*p, z), T, rtol=0, atol=1e-12)


@given(poses, st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))
def test_pose2d_ignores_roll_and_pitch(p, roll, pitch):
    T = pose_matrix(*p)
    T[:3, :3] = T[:3, :3] @ rotation_roll_pitch(roll, pitch)  # R = Rz(yaw) Ry(pitch) Rx(roll)
    assert_poses_close(pose2d(T), p, atol=1e-9)


def test_rotation_roll_pitch_is_ry_times_rx():
    roll, pitch = 0.3, -0.2
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    np.testing.assert_allclose(rotation_roll_pitch(roll, pitch), ry @ rx, atol=1e-15)


def test_stacked_pose_matrices():
    rng = np.random.default_rng(3)
    p = rng.uniform(-5, 5, (4, 2, 3))
    T = pose_matrix(p[..., 0], p[..., 1], p[..., 2])
    assert T.shape == (4, 2, 4, 4)
    assert_poses_close(pose2d(T), p, atol=1e-12)
    np.testing.assert_array_equal(T[1, 1], pose_matrix(*p[1, 1]))
    np.testing.assert_array_equal(T[..., :3, :3], yaw_matrix(p[..., 2]))
    assert pose_matrix(0.0, 0.0, np.zeros(5)).shape == (5, 4, 4)  # scalars broadcast


# ---------------------------------------------------------------------------------------------- the one copy


def test_se2_imports_no_other_rangemcl_module():
    code = "import sys, rangemcl.se2; print(sorted(m for m in sys.modules if m.startswith('rangemcl.')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['rangemcl.se2']"


def test_old_import_paths_are_the_same_functions():
    from rangemcl.localization import particles

    for name in ("wrap_angle", "pose2d", "odometry_increment", "circular_mean"):
        assert getattr(particles, name) is getattr(se2, name), name


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([np.float32, np.float64]), st.floats(-30, 30))
def test_row_norms_equal_numpys_norm_to_the_bit(seed, dtype, log_scale):
    """row_norms is a faster np.linalg.norm(p, axis=1): the same bits on random points of any scale, zero
    rows and infinities included."""
    rng = np.random.default_rng(seed)
    p = (rng.standard_normal((500, 3)) * 10.0**log_scale).astype(dtype)
    p[::50] = 0.0
    p[7, 1] = np.inf
    got, want = se2.row_norms(p), np.linalg.norm(p, axis=1)
    assert got.dtype == want.dtype
    np.testing.assert_array_equal(got, want)
