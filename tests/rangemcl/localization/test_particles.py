"""Particle-filter arithmetic by properties on random inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rangemcl.localization.factory import motion_noise
from rangemcl.localization.particles import (
    MotionNoise,
    circular_mean,
    effective_sample_size,
    low_variance_resample,
    normalize_log_weights,
    odometry_increment,
    pose2d,
    pose_estimate,
    sample_motion,
    wrap_angle,
)
from rangemcl.localization.settings import MotionSettings

angles = st.floats(-1e3, 1e3, allow_nan=False)


@given(angles)
def test_wrap_angle_range_and_equivalence(a):
    w = float(wrap_angle(a))
    assert -np.pi < w <= np.pi
    assert np.isclose(np.cos(w), np.cos(a), atol=1e-9) and np.isclose(np.sin(w), np.sin(a), atol=1e-9)


def test_wrap_angle_edges():
    assert wrap_angle(np.pi) == np.pi and wrap_angle(-np.pi) == np.pi and wrap_angle(3 * np.pi) == np.pi


@settings(max_examples=50)
@given(st.lists(st.floats(-800, 50, allow_nan=False), min_size=1, max_size=200))
def test_log_weights_normalise(log_w):
    w = normalize_log_weights(np.array(log_w))
    assert np.isclose(w.sum(), 1.0) and (w >= 0).all()
    assert w[np.argmax(log_w)] == w.max()
    assert 1.0 <= effective_sample_size(w) <= len(w) + 1e-9


def test_log_weights_all_minus_inf_are_uniform():
    assert np.allclose(normalize_log_weights(np.full(4, -np.inf)), 0.25)


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300))
def test_low_variance_resampling_counts(seed, n):
    rng = np.random.default_rng(seed)
    w = rng.random(n) ** 3
    w /= w.sum()
    idx = low_variance_resample(w, rng)
    counts = np.bincount(idx, minlength=n)
    assert counts.sum() == n
    assert (counts >= np.floor(n * w) - 1e-9).all() and (counts <= np.ceil(n * w) + 1e-9).all()


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1))
def test_circular_mean_across_the_seam(seed):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-np.pi, np.pi)
    a = wrap_angle(centre + rng.normal(0, 0.1, 100))
    assert abs(wrap_angle(circular_mean(a) - centre)) < 0.05
    assert circular_mean([np.pi - 0.01, -np.pi + 0.01]) == pytest.approx(np.pi, abs=1e-9)


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1))
def test_noise_free_motion_reproduces_odometry(seed):
    rng = np.random.default_rng(seed)
    prev = np.array([*rng.uniform(-50, 50, 2), rng.uniform(-np.pi, np.pi)])
    cur = np.array([*(prev[:2] + rng.normal(0, 2, 2)), rng.uniform(-np.pi, np.pi)])
    inc = odometry_increment(prev, cur)
    # the same relative motion applied to a particle at another pose lands where the composition says
    zero = MotionNoise(0.0, 0.0, 0.0, 0.0)
    moved = sample_motion(prev[None], inc, zero, rng)[0]
    np.testing.assert_allclose(moved[:2], cur[:2], atol=1e-9)
    assert abs(wrap_angle(moved[2] - cur[2])) < 1e-9


def test_motion_noise_grows_with_distance():
    rng = np.random.default_rng(0)
    p = np.zeros((5000, 3))
    short = sample_motion(p, (0.0, 1.0, 0.0), motion_noise(MotionSettings()), rng)
    long = sample_motion(p, (0.0, 10.0, 0.0), motion_noise(MotionSettings()), rng)
    assert long[:, 0].std() > 5 * short[:, 0].std()
    assert abs(short[:, 0].mean() - 1.0) < 0.01


def test_pose_estimate_uses_best_particles_and_circular_yaw():
    particles = np.array([[0, 0, np.pi - 0.1], [2, 0, -np.pi + 0.1], [100, 100, 0.0]])
    w = np.array([0.45, 0.45, 0.10])
    est = pose_estimate(particles, w, best_share=0.6)  # ceil(0.6 * 3) = 2: the outlier is left out
    np.testing.assert_allclose(est[:2], [1.0, 0.0], atol=1e-9)
    assert abs(wrap_angle(est[2] - np.pi)) < 1e-9


def test_pose2d():
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.array([[c, -s, 0, 4], [s, c, 0, 5], [0, 0, 1, 1.7], [0, 0, 0, 1]])
    np.testing.assert_allclose(pose2d(T), [4, 5, 0.3])
