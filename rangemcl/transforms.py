"""Rotation and pose helpers on stacked numpy arrays (pure functions, no copies of scipy's objects).

Quaternions are ``(x, y, z, w)`` (scipy's and Warp's order), unit, with ``w >= 0``.
"""

from __future__ import annotations

import numpy as np


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
