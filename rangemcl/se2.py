"""Planar (SE(2)) pose math, the one copy the code base uses: angle wrapping and circular means, ground-plane
projection of 4×4 poses and back, composing, inverting and relating ``(x, y, yaw)`` poses, the odometry
motion model's increment, and the sensor's roll/pitch attitude.

Pure numpy functions, no other rangemcl import (so that everything, simbed included, can use them).
Conventions:

* a planar pose is ``(x, y, yaw)``, float64, stacked as ``(..., 3)``; yaw in radians, wrapped to (−π, π];
* a 3D pose is a 4×4 rigid transform ``T`` with ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``;
* ``a ⊕ b`` composes pose ``b``, given in the frame of ``a``, onto ``a``; ``a⁻¹ ⊕ b`` is ``b`` seen from
  ``a``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "circular_mean",
    "odometry_increment",
    "pose2d",
    "pose_matrix",
    "rotation_roll_pitch",
    "se2_between",
    "se2_compose",
    "se2_inverse",
    "wrap_angle",
    "yaw_matrix",
]

# ---------------------------------------------------------------------------------------------- angles


def wrap_angle(a):
    """Angles wrapped to (−π, π]: any shape in, a float64 array of that shape out (0-d for a scalar;
    callers that need a Python float wrap it in ``float()``)."""
    a = np.asarray(a, dtype=np.float64)
    w = np.mod(a + np.pi, 2 * np.pi) - np.pi  # [−π, π)
    return np.where(w == -np.pi, np.pi, w)


def circular_mean(angles: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted mean direction of angles ``(N,)`` with optional weights ``(N,)``, through the unit vectors
    (so it is right across ±π); a float in (−π, π]."""
    a = np.asarray(angles, dtype=np.float64)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64)
    return float(wrap_angle(np.arctan2(np.sum(w * np.sin(a)), np.sum(w * np.cos(a)))))


# ---------------------------------------------------------------------------------------------- 4×4 poses


def pose2d(T: np.ndarray) -> np.ndarray:
    """``(x, y, yaw)`` of 4×4 poses (their projection onto the ground plane): ``(..., 4, 4)`` in,
    ``(..., 3)`` float64 out (``(3,)`` for one pose). Yaw is the heading of the pose's x axis,
    ``atan2(R10, R00)``, in [−π, π] (−π only for an ``R10`` of ``-0.0``)."""
    T = np.asarray(T, dtype=np.float64)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])], axis=-1)


def yaw_matrix(yaw) -> np.ndarray:
    """``Rz(yaw)``: rotations ``(..., 3, 3)`` about z by angles of shape ``(...)``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((*yaw.shape, 3, 3))
    R[..., 0, 0], R[..., 0, 1] = c, -s
    R[..., 1, 0], R[..., 1, 1] = s, c
    R[..., 2, 2] = 1.0
    return R


def pose_matrix(x, y, yaw, z=0.0) -> np.ndarray:
    """4×4 poses ``(..., 4, 4)`` at ``(x, y, z)`` heading ``yaw`` (no roll or pitch); the arguments broadcast
    to a common shape ``(...)``. The inverse of :func:`pose2d` for such poses: ``pose_matrix(*p)`` for a
    planar pose ``p``."""
    x, y, yaw, z = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, y, yaw, z)))
    T = np.zeros((*x.shape, 4, 4))
    T[..., :3, :3] = yaw_matrix(yaw)
    T[..., 0, 3], T[..., 1, 3], T[..., 2, 3] = x, y, z
    T[..., 3, 3] = 1.0
    return T


def rotation_roll_pitch(roll: float, pitch: float) -> np.ndarray:
    """``Ry(pitch) · Rx(roll)`` ``(3, 3)``: the sensor's attitude without its yaw (``R = Rz Ry Rx``)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return ry @ rx


# ---------------------------------------------------------------------------------------------- (x, y, yaw)


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ⊕ b``: pose ``b`` (given in the frame of ``a``) in the frame ``a`` is given in; ``(..., 3)``
    poses in (broadcasting), ``(..., 3)`` out."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """``a⁻¹``: the pose, ``(..., 3)`` in and out, that composes with ``a`` (either side) to the identity."""
    a = np.asarray(a, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])], axis=-1
    )


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ⊕ b``: pose ``b`` expressed in the frame of pose ``a``; ``(..., 3)`` poses in (broadcasting),
    ``(..., 3)`` out."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def odometry_increment(prev: np.ndarray, cur: np.ndarray) -> tuple[float, float, float]:
    """``(rot1, trans, rot2)`` of the standard odometry motion model (Thrun et al.) between two ``(3,)``
    ``(x, y, yaw)`` poses: turn by ``rot1`` towards ``cur``, drive ``trans``, turn by ``rot2``."""
    dx, dy = cur[0] - prev[0], cur[1] - prev[1]
    trans = float(np.hypot(dx, dy))
    rot1 = float(wrap_angle(np.arctan2(dy, dx) - prev[2])) if trans > 1e-9 else 0.0
    rot2 = float(wrap_angle(cur[2] - prev[2] - rot1))
    return rot1, trans, rot2
