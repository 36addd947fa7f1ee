"""Particle-filter arithmetic over ``(x, y, yaw)`` particles: the odometry motion model, log-weights,
low-variance resampling (and the roughening after it) and circular pose estimates. Pure numpy functions;
all randomness comes from the generator passed in. The pose math they build on (angle wrapping, circular
means, odometry increments) lives in :mod:`rangemcl.se2` and is re-exported here.

Particles are ``(N, 3)`` float64 arrays ``(x, y, yaw)`` with yaw wrapped to (−π, π].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# the pose math lives in rangemcl.se2; these names stay importable from here too
from rangemcl.se2 import circular_mean as circular_mean
from rangemcl.se2 import odometry_increment as odometry_increment
from rangemcl.se2 import pose2d as pose2d
from rangemcl.se2 import wrap_angle as wrap_angle


@dataclass
class MotionNoise:
    """Noise of the odometry motion model (Thrun et al.): standard deviations grow with the motion."""

    rot_per_rot: float  # alpha1: rotation noise per radian turned
    rot_per_trans: float  # alpha2: rotation noise (rad) per metre driven
    trans_per_trans: float  # alpha3: translation noise per metre driven
    trans_per_rot: float  # alpha4: translation noise (m) per radian turned


def sample_motion(
    particles: np.ndarray, increment: tuple[float, float, float], noise: MotionNoise, rng: np.random.Generator
) -> np.ndarray:
    """Move every particle by a noisy copy of the odometry increment ``(rot1, trans, rot2)``."""
    rot1, trans, rot2 = increment
    n = len(particles)
    a = noise
    s_rot1 = a.rot_per_rot * abs(rot1) + a.rot_per_trans * trans
    s_trans = a.trans_per_trans * trans + a.trans_per_rot * (abs(rot1) + abs(rot2))
    s_rot2 = a.rot_per_rot * abs(rot2) + a.rot_per_trans * trans
    r1 = rot1 + rng.normal(0.0, 1.0, n) * s_rot1
    t = trans + rng.normal(0.0, 1.0, n) * s_trans
    r2 = rot2 + rng.normal(0.0, 1.0, n) * s_rot2
    out = np.empty_like(particles, dtype=np.float64)
    heading = particles[:, 2] + r1
    out[:, 0] = particles[:, 0] + t * np.cos(heading)
    out[:, 1] = particles[:, 1] + t * np.sin(heading)
    out[:, 2] = wrap_angle(heading + r2)
    return out


def normalize_log_weights(log_w: np.ndarray) -> np.ndarray:
    """Weights that sum to 1 from log-weights (log-sum-exp; ``-inf`` entries get weight 0)."""
    log_w = np.asarray(log_w, dtype=np.float64)
    top = np.max(log_w)
    if not np.isfinite(top):
        return np.full(len(log_w), 1.0 / len(log_w))
    w = np.exp(log_w - top)
    return w / w.sum()


def effective_sample_size(weights: np.ndarray) -> float:
    """``N_eff = 1 / Σ w²`` of normalised weights."""
    w = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(w * w))


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices of ``n`` (default: as many) particles drawn by low-variance (systematic) resampling.

    Particle ``i`` is drawn ``floor(n·w_i)`` or ``ceil(n·w_i)`` times.
    """
    w = np.asarray(weights, dtype=np.float64)
    n = len(w) if n is None else int(n)
    positions = (rng.uniform(0.0, 1.0) + np.arange(n)) / n
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0  # guard against rounding
    return np.searchsorted(cumulative, positions, side="right").clip(0, len(w) - 1)


def resample_roughened(
    particles: np.ndarray,
    weights: np.ndarray,
    rng: np.random.Generator,
    n: int,
    jitter_xy_m: float,
    jitter_yaw_deg: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` particles drawn by :func:`low_variance_resample`, then roughened: Gaussian noise of
    ``jitter_xy_m`` on x and y and of ``jitter_yaw_deg`` on yaw (nothing drawn when both are 0), so that
    the copies of one particle spread again. Returns the new particles and the index of each one's
    parent."""
    idx = low_variance_resample(weights, rng, n)
    parts = particles[idx].copy()
    if jitter_xy_m > 0 or jitter_yaw_deg > 0:
        parts[:, :2] += rng.normal(0.0, jitter_xy_m, (n, 2))
        parts[:, 2] = wrap_angle(parts[:, 2] + rng.normal(0.0, math.radians(jitter_yaw_deg), n))
    return parts, idx


def pose_estimate(particles: np.ndarray, weights: np.ndarray, best_share: float = 0.8) -> np.ndarray:
    """``(x, y, yaw)``: the weighted mean of the best ``best_share`` of the particles (by weight), with a
    circular mean for yaw (the paper's estimate, without the reference code's linear yaw average)."""
    w = np.asarray(weights, dtype=np.float64)
    k = max(1, int(np.ceil(best_share * len(w))))
    best = np.argsort(-w, kind="stable")[:k]
    wb = w[best] / w[best].sum() if w[best].sum() > 0 else np.full(k, 1.0 / k)
    p = particles[best]
    return np.array([wb @ p[:, 0], wb @ p[:, 1], circular_mean(p[:, 2], wb)])
