"""Scan files in the KITTI layout: ``velodyne/NNNNNN.bin`` holds float32 (x, y, z, intensity) records."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write
from rangemcl.errors import InputError


def write_scan_bin(path, points: np.ndarray, intensity: np.ndarray | None = None) -> Path:
    """Write an ``(N, 3)`` scan as a KITTI ``.bin`` atomically (a temporary file renamed into place)."""
    p = np.asarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{path}: points must have shape (N, 3), got {p.shape}")
    i = np.zeros(len(p), np.float32) if intensity is None else np.asarray(intensity, np.float32).reshape(-1)
    if len(i) != len(p):
        raise InputError(f"{path}: {len(i)} intensities for {len(p)} points")
    records = np.column_stack([p, i]).astype(np.float32)  # (N, 4)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, records.tobytes())  # on disk before any index line that refers to it
    return path


def read_scan_bin(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI ``.bin``: points ``(N, 3)`` float32 and intensity ``(N,)`` float32.

    A missing file or one whose size is not a whole number of 16-byte records is an ``InputError``.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such scan file") from None
    except OSError as err:
        raise InputError(f"{path}: cannot read scan ({err.strerror})") from None
    if len(raw) % 16:
        raise InputError(
            f"{path}: truncated scan ({len(raw)} bytes is not a multiple of 16-byte x,y,z,i records)"
        )
    records = np.frombuffer(raw, dtype=np.float32).reshape(-1, 4)
    return records[:, :3].copy(), records[:, 3].copy()
