"""``rangemcl convert``: a recording from any source (KITTI folder, bag, MCAP, folder of .pcd/.ply scans)
written as a KITTI folder or as a bag, frame by frame (scans, per-point fields, times, poses, odometry,
IMU roll and pitch, and the recording's meta)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rangemcl.datasets.rosbag import FORMATS as BAG_FORMATS
from rangemcl.datasets.sources import open_source
from rangemcl.errors import InputError

FORMATS = ("kitti", *BAG_FORMATS)
_RUNTIME_KEYS = ("complete", "frames", "scan_stamp", "scan_times", "sensor_to_base", "point_times")


def sensor_mount(meta: dict) -> np.ndarray:
    """``T_base_sensor`` from a recording's meta: its sensor's mount, or a bag's TF, else identity."""
    from rangemcl.datasets.lidar_odometry import mount_of

    sensor = meta.get("sensor") if isinstance(meta, dict) else None
    mount = sensor.get("mount") if isinstance(sensor, dict) else None
    if mount is None and isinstance(meta, dict):
        mount = meta.get("sensor_to_base")
    if isinstance(mount, dict):  # a bag's TF mount carries its source beside xyz_m and rpy_deg
        mount = {k: mount[k] for k in ("xyz_m", "rpy_deg") if k in mount}
    return mount_of({"sensor": {"mount": mount}}, "the recording's meta")


def convert(
    src: str | os.PathLike,
    out: str | os.PathLike,
    fmt: str,
    *,
    bag_options=None,
    overwrite: bool = False,
    progress: bool = False,
) -> int:
    """Write ``src`` to ``out`` in ``fmt`` (``kitti``, ``mcap``, ``rosbag2``, ``rosbag1``); the frames
    written. Everything is checked before the first file is written."""
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    seq = open_source(src, bag_options=bag_options)
    n = len(seq)
    if n == 0:
        raise InputError(f"{src}: no scans")
    if fmt == "kitti" and seq.poses is None:
        raise InputError(f"{src}: a KITTI folder needs poses (give --poses FILE)")
    times = seq.times if seq.times is not None else 0.1 * (np.arange(n) + 1)
    meta = {k: v for k, v in (seq.meta or {}).items() if k not in _RUNTIME_KEYS}
    meta["converted_from"] = str(Path(src).resolve())
    if fmt == "kitti":
        from rangemcl.datasets.kitti import SequenceWriter

        writer = SequenceWriter(out, meta=meta, overwrite=overwrite)
    else:
        from rangemcl.datasets.rosbag import BagWriter

        if times[0] <= 0:  # ROS stamps start after 0
            times = times - times[0] + 0.1
        writer = BagWriter(out, fmt, meta=meta, T_base_sensor=sensor_mount(seq.meta), overwrite=overwrite)
    frames = range(n)
    if progress:
        from rich.progress import track

        frames = track(frames, description="converting", transient=True)
    with writer:
        for i in frames:
            points, intensity = seq.scan_with_intensity(i)
            writer.add_frame(
                points,
                pose=None if seq.poses is None else seq.poses[i],
                time_s=float(times[i]),
                intensity=intensity,
                odometry=None if seq.odometry is None else seq.odometry[i],
                imu_roll_pitch=None if seq.imu_roll_pitch is None else seq.imu_roll_pitch[i],
                point_meta=seq.point_meta(i),
            )
    return n
