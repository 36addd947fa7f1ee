"""Pose math, the one copy the code base uses. Planar (SE(2)): angle wrapping and circular means,
ground-plane projection of 4×4 poses and back, composing, inverting and relating ``(x, y, yaw)`` poses, the
odometry motion model's increment, the sensor's roll/pitch attitude. Rigid 3D (SE(3)): quaternions,
roll/pitch/yaw mountings, inverting and interpolating 4×4 poses. And the lengths of a point array's rows.

Pure numpy functions, no other rangemcl import (so that everything, simbed included, can use them).
Conventions:

* a planar pose is ``(x, y, yaw)``, float64, stacked as ``(..., 3)``; yaw in radians, wrapped to (−π, π];
* a 3D pose is a 4×4 rigid transform ``T`` with ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``;
* quaternions are ``(x, y, z, w)`` (scipy's and Warp's order), unit, with ``w >= 0``, except
  :func:`quat_wxyz_from_ypr`'s ``(w, x, y, z)`` (MuJoCo's order);
* ``a ⊕ b`` composes pose ``b``, given in the frame of ``a``, onto ``a``; ``a⁻¹ ⊕ b`` is ``b`` seen from
  ``a``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "circular_mean",
    "interpolate_poses",
    "invert_rigid",
    "matrix_from_quat",
    "odometry_increment",
    "pose2d",
    "pose_matrix",
    "quat_from_matrix",
    "quat_wxyz_from_ypr",
    "rotation_roll_pitch",
    "se2_between",
    "se2_compose",
    "se2_inverse",
    "transform_from_xyz_rpy",
    "wrap_angle",
    "xyyaw_of",
    "xyz_rpy_from_transform",
    "yaw_matrix",
    "yaw_of",
]

# ---------------------------------------------------------------------------------------------- points


def row_norms(p: np.ndarray) -> np.ndarray:
    """The length of each row of ``p`` ``(N, 3)``: ``np.linalg.norm(p, axis=1)`` to the bit (the squares
    are summed in the same order, x then y then z), in a quarter of its time (numpy reduces a length-3
    axis row by row; this is three whole-column passes). The per-frame scan preparation calls it on
    every point of the scan."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.sqrt(x * x + y * y + z * z)


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


# ------------------------------------------------------------------------------------------- 3D poses


def yaw_of(T: np.ndarray) -> float:
    """The yaw (rad) of a 4×4 pose: the heading of its x axis in the ground plane."""
    return math.atan2(T[1, 0], T[0, 0])


def xyyaw_of(poses: np.ndarray) -> np.ndarray:
    """``(N, 3)`` x, y, yaw of ``(N, 4, 4)`` poses (:func:`pose2d` of each)."""
    return np.array([pose2d(T) for T in np.asarray(poses, np.float64)]).reshape(-1, 3)


def transform_from_xyz_rpy(xyz_m: Any, rpy_deg: Any) -> np.ndarray:
    """4x4 transform with translation ``xyz_m`` and rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, cp, cy = np.cos(np.radians(rpy_deg))
    sr, sp, sy = np.sin(np.radians(rpy_deg))
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = xyz_m
    return T


def xyz_rpy_from_transform(T: np.ndarray) -> tuple[list[float], list[float]]:
    """Inverse of :func:`transform_from_xyz_rpy`: (xyz_m, rpy_deg) as lists of floats."""
    R = T[:3, :3]
    cos_pitch = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cos_pitch)
    if cos_pitch > 1e-9:
        roll, yaw = math.atan2(R[2, 1], R[2, 2]), math.atan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: only roll - yaw (or roll + yaw) is defined; put it all in roll
        roll, yaw = math.atan2(-R[1, 2], R[1, 1]), 0.0
    return [float(v) for v in T[:3, 3]], [math.degrees(a) for a in (roll, pitch, yaw)]


def quat_wxyz_from_ypr(
    yaw: float, pitch: float = 0.0, roll: float = 0.0
) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    )


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (x, y, z, w) of rotation matrices ``(..., 3, 3)`` (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], axis=1)  # pick the largest for stability
    k = np.argmax(diag, axis=1)
    q = np.empty((len(m), 4))
    for case in range(4):
        s = k == case
        if not s.any():
            continue
        a = m[s]
        if case == 3:
            r = np.sqrt(1.0 + tr[s]) * 2.0
            q[s] = np.stack(
                [
                    (a[:, 2, 1] - a[:, 1, 2]) / r,
                    (a[:, 0, 2] - a[:, 2, 0]) / r,
                    (a[:, 1, 0] - a[:, 0, 1]) / r,
                    r / 4,
                ],
                axis=1,
            )
        else:
            i, j, l = case, (case + 1) % 3, (case + 2) % 3
            r = np.sqrt(1.0 + a[:, i, i] - a[:, j, j] - a[:, l, l]) * 2.0
            v = np.empty((len(a), 4))
            v[:, i] = r / 4
            v[:, j] = (a[:, j, i] + a[:, i, j]) / r
            v[:, l] = (a[:, l, i] + a[:, i, l]) / r
            v[:, 3] = (a[:, l, j] - a[:, j, l]) / r
            q[s] = v
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q.reshape((*R.shape[:-2], 4))


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` (x, y, z, w), normalised first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)`` without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses ``(Q, 4, 4)`` at ``query`` times between samples ``(times (S,) increasing, poses (S, 4, 4))``:
    translation linear, rotation by normalised quaternion interpolation (exact to first order in the
    angle between neighbouring samples, which is what a physics step apart gives). Queries outside the
    samples are clamped to the ends."""
    times = np.asarray(times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    q = np.clip(np.asarray(query, dtype=np.float64), times[0], times[-1])
    out = np.zeros((len(q), 4, 4))
    out[:, 3, 3] = 1.0
    if len(times) == 1:
        out[:] = poses[0]
        return out
    k = np.clip(np.searchsorted(times, q, side="right") - 1, 0, len(times) - 2)
    span = np.maximum(times[k + 1] - times[k], 1e-12)
    a = ((q - times[k]) / span)[:, None]
    out[:, :3, 3] = (1 - a) * poses[k, :3, 3] + a * poses[k + 1, :3, 3]
    quats = quat_from_matrix(poses[:, :3, :3])  # (S, 4)
    q0, q1 = quats[k], quats[k + 1]
    q1 = np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0, -q1, q1)  # shortest way round
    out[:, :3, :3] = matrix_from_quat((1 - a) * q0 + a * q1)
    return out
