"""One way in for every kind of recording: :func:`open_source` gives a sequence object with the same
attributes and methods whatever it was read from (a KITTI-layout folder, a ROS 1 or ROS 2 bag, an MCAP
file), so the localizer and the map builder do not know where their frames came from.

What every source has is :class:`FrameSource` (the KITTI folder's :class:`rangemcl.datasets.kitti.Sequence`,
the bags' :class:`rangemcl.datasets.rosbag.BagSequence`, the scan folders'
:class:`rangemcl.datasets.scanfolder.ScanFolderSequence`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from rangemcl.datasets.kitti import Sequence, load_sequence
from rangemcl.errors import InputError


@runtime_checkable
class FrameSource(Protocol):
    """A recording as the localizer and the map builder read it, whatever it was read from.

    Poses are LiDAR poses in the world, ``(N, 4, 4)`` float64, or None where the recording has none;
    ``calib_Tr`` maps the sensor frame into the frame of the recording's poses files (identity for bags and
    our own drives); ``calib_source`` says where it came from. Scans are read when asked for."""

    root: Path  # where it was read from
    meta: dict[str, Any]  # the recording's metadata (sensor spec, scene, seed, ...; may be empty)
    calib_Tr: np.ndarray  # (4, 4)
    calib_source: str
    poses: np.ndarray | None  # (N, 4, 4) ground truth, if known
    odometry: np.ndarray | None  # (N, 4, 4) the odometry the car measured, if any
    times: np.ndarray | None  # (N,) seconds: each scan's end of sweep
    imu_roll_pitch: np.ndarray | None  # (N, 2) radians, from an IMU, if any

    def __len__(self) -> int: ...

    @property
    def scan_paths(self) -> list:
        """One name per scan (files, or a bag's message indices): resume fingerprints compare them."""
        ...

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i``: ``(M, 3)`` float32 points in the sensor frame."""
        ...

    def scan_with_intensity(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``i`` and its ``(M,)`` float32 intensities (zeros where the recording has none)."""
        ...

    def point_meta(self, i: int) -> dict[str, np.ndarray]:
        """Per-point fields of scan ``i`` the recording has (``ring``, ``column``, ``time_s``, ``label``)."""
        ...


def open_source(path: str | os.PathLike, *, require_poses: bool = False, bag_options=None) -> FrameSource:
    """The recording at ``path`` as a sequence: a folder with ``velodyne/`` (KITTI layout), a bag
    (``.bag``, ``.mcap``, ``.db3`` or a ROS 2 bag folder, read with ``bag_options``, a
    :class:`rangemcl.datasets.rosbag.BagOptions`), or a folder of ``.pcd``/``.ply`` scans
    (:mod:`rangemcl.datasets.scanfolder`; ``bag_options.poses_file`` is its poses file)."""
    from rangemcl.datasets.rosbag import BagOptions, is_bag, open_bag
    from rangemcl.datasets.scanfolder import is_scan_folder, load_scan_folder

    p = Path(path)
    if is_bag(p):
        return open_bag(p, bag_options or BagOptions(), require_poses=require_poses)
    if p.is_dir() and not (p / "velodyne").is_dir():
        storage = [f for f in p.iterdir() if f.suffix in (".mcap", ".db3")]
        if len(storage) == 1:  # a ROS 2 bag folder without metadata.yaml (written at the end)
            return open_bag(storage[0], bag_options or BagOptions(), require_poses=require_poses)
    if is_scan_folder(p):
        poses = bag_options.poses_file if bag_options is not None else None
        return load_scan_folder(p, poses_file=poses, require_poses=require_poses)
    if bag_options is not None and _bag_only(bag_options):
        raise InputError(f"{p}: topic options are for bags; this is a {'folder' if p.is_dir() else 'file'}")
    return load_sequence(p, require_poses=require_poses)


def _bag_only(options) -> bool:
    return any(
        getattr(options, k) is not None
        for k in ("lidar_topic", "imu_topic", "odom_topic", "truth_topic", "point_time_field", "scan_stamp")
    )


__all__ = ["FrameSource", "Sequence", "open_source"]
