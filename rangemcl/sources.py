"""One way in for every kind of recording: :func:`open_source` gives a sequence object with the same
attributes and methods whatever it was read from (a KITTI-layout folder, a ROS 1 or ROS 2 bag, an MCAP
file), so the localizer and the map builder do not know where their frames came from.

What every source has (see :class:`rangemcl.dataset.Sequence`): ``root``, ``meta``, ``calib_Tr``,
``calib_source``, ``poses``, ``odometry`` (``(N, 4, 4)`` LiDAR poses or None), ``times`` (``(N,)``),
``imu_roll_pitch`` (``(N, 2)``), ``len()``, ``scan(i)``, ``scan_with_intensity(i)``, ``point_meta(i)`` and
``scan_paths`` (one name per scan, for resume fingerprints).
"""

from __future__ import annotations

import os
from pathlib import Path

from rangemcl.dataset import Sequence, load_sequence
from rangemcl.errors import InputError


def open_source(path: str | os.PathLike, *, require_poses: bool = False, bag_options=None):
    """The recording at ``path`` as a sequence: a folder with ``velodyne/`` (KITTI layout), a bag
    (``.bag``, ``.mcap``, ``.db3`` or a ROS 2 bag folder, read with ``bag_options``, a
    :class:`rangemcl.ros.bag.BagOptions`), or a folder of ``.pcd``/``.ply`` scans
    (:mod:`rangemcl.scanfolder`; ``bag_options.poses_file`` is its poses file)."""
    from rangemcl.ros.bag import BagOptions, is_bag, open_bag
    from rangemcl.scanfolder import is_scan_folder, load_scan_folder

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


__all__ = ["Sequence", "open_source"]
