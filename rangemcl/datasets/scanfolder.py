"""A folder of ``.pcd`` or ``.ply`` scans as a sequence (Open3D reads them, extra fields included).

Scans are taken in natural order of their names (``2.pcd`` before ``10.pcd``). Times come from ``times.txt``
in the folder (one a scan), else from the names when they are numbers (seconds, or nanoseconds when they
are that large: ``1634567890123456789.pcd``), else 10 Hz is assumed and said in ``meta``. Ground truth
from ``poses.txt`` in the folder (KITTI, one line a scan) or a poses file (KITTI or TUM); odometry from
``odometry.txt`` (KITTI) when present, else ``--odometry kiss-icp`` or ``--odometry poses:FILE``.
Per-point fields other than the position are kept (``intensity`` as the intensity; a time field, as in
bags, becomes ``time_s``). Points with a non-finite or all-zero position are dropped.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangemcl.datasets import pointcloud2 as pc2
from rangemcl.datasets.recording import Recording
from rangemcl.errors import InputError

SUFFIXES = (".pcd", ".ply")


def scan_files(root: Path) -> list[Path]:
    """The folder's ``.pcd``/``.ply`` files in natural order (one kind only)."""
    files = [p for p in root.iterdir() if p.suffix.lower() in SUFFIXES and not p.name.startswith(".")]
    kinds = {p.suffix.lower() for p in files}
    if len(kinds) > 1:
        raise InputError(f"{root}: holds both .pcd and .ply scans; keep one kind in a sequence folder")

    def natural(p: Path):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.stem)]

    return sorted(files, key=natural)


def is_scan_folder(path: Path) -> bool:
    return path.is_dir() and not (path / "velodyne").is_dir() and any(scan_files(path))


@dataclass
class ScanFolderSequence(Recording):
    """The same attributes and methods as :class:`rangemcl.datasets.kitti.Sequence`."""

    root: Path
    scan_paths: list[Path]
    calib_source: str = field(default="identity (scans are in the sensor frame)", kw_only=True)
    _cache: tuple[int, pc2.Cloud] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.scan_paths)

    def _read(self, i: int) -> pc2.Cloud:
        n = len(self)
        k = int(i) + (n if int(i) < 0 else 0)
        if not 0 <= k < n:
            raise InputError(f"{self.root}: frame {i} out of range (the folder has {n} scans)")
        if self._cache is not None and self._cache[0] == k:
            return self._cache[1]
        cloud = read_scan_file(self.scan_paths[k])
        self._cache = (k, cloud)
        return cloud

    def scan(self, i: int) -> np.ndarray:
        return self._read(i).points

    def scan_with_intensity(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        c = self._read(i)
        return c.points, c.intensity

    def point_meta(self, i: int) -> dict[str, np.ndarray]:
        c = self._read(i)
        out = {k: v for k, v in c.fields.items() if v.ndim == 1}
        name = pc2.find_time_field(out)
        if name is not None:
            t = out.pop(name)
            stamp = float(self.times[int(i)]) if self.times is not None else 0.0
            rel = pc2.point_times(t, stamp, where=str(self.scan_paths[int(i)]))
            if len(rel) and np.ptp(rel) > 0:
                end = float(rel.max()) if rel.max() > 0 else 0.0  # times after the stamp: it was the start
                out["time_s"] = (rel - end).astype(np.float32)
        return out

    def close(self) -> None:
        pass

    def __enter__(self) -> ScanFolderSequence:
        return self

    def __exit__(self, *exc) -> bool:
        return False


def read_scan_file(path: Path) -> pc2.Cloud:
    """One ``.pcd``/``.ply`` scan: points, intensity and its other per-point fields."""
    import open3d as o3d

    if not path.is_file():
        raise InputError(f"{path}: no such scan file")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        try:
            pcd = o3d.t.io.read_point_cloud(str(path))
        except RuntimeError as err:
            raise InputError(f"{path}: cannot read the scan ({str(err).strip().splitlines()[-1]})") from None
    if "positions" not in pcd.point:
        raise InputError(f"{path}: cannot read the scan (not a point cloud, or empty)")
    xyz = pcd.point["positions"].numpy().astype(np.float32).reshape(-1, 3)
    keep = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0, axis=1)
    fields = {}
    for key in pcd.point:
        if key == "positions":
            continue
        a = pcd.point[key].numpy()
        a = a.reshape(len(a)) if a.ndim == 2 and a.shape[1] == 1 else a
        fields[key] = a[keep]
    intensity = np.zeros(int(keep.sum()), np.float32)
    for name in pc2.INTENSITY_FIELDS:
        if name in fields and fields[name].ndim == 1:
            intensity = fields.pop(name).astype(np.float32)
            break
    return pc2.Cloud(np.ascontiguousarray(xyz[keep]), intensity, fields, dropped=int((~keep).sum()))


def _times(root: Path, files: list[Path], meta: dict) -> np.ndarray:
    from rangemcl.datasets.kitti import parse_numbers, read_lines

    p = root / "times.txt"
    if p.is_file():
        lines = read_lines(p, drop_partial=False)
        if len(lines) != len(files):
            raise InputError(f"{p}: {len(lines)} lines for {len(files)} scans")
        t = np.array([parse_numbers(p, n, line, 1)[0] for n, line in lines])
        source = "times.txt"
    else:
        try:
            t = np.array([float(f.stem) for f in files])
        except ValueError:
            t = None
        if t is not None and len(t) and np.all(np.isfinite(t)):
            if np.max(np.abs(t)) > 1e15:
                t = t / 1e9
            source = "the file names"
        else:
            t = np.arange(len(files)) * 0.1
            source = "none: 10 Hz assumed"
    bad = np.flatnonzero(~np.isfinite(t) | np.r_[False, np.diff(t) <= 0])
    if len(bad):
        raise InputError(f"{root}: scan {files[bad[0]].name}'s time is not after the previous one ({source})")
    meta.setdefault("scan_times", source)
    return t


def load_scan_folder(
    path: str | os.PathLike, *, poses_file: str | None = None, require_poses: bool = False
) -> ScanFolderSequence:
    """Open a folder of ``.pcd``/``.ply`` scans (see the module's docstring)."""
    from rangemcl.datasets.kitti import kitti_poses_file, poses_from_lines, read_lines, read_meta

    root = Path(path)
    files = scan_files(root)
    if not files:
        raise InputError(f"{root}: no .pcd or .ply scans")
    meta = read_meta(root / "meta.yaml") if (root / "meta.yaml").is_file() else {}
    seq = ScanFolderSequence(root=root, scan_paths=files, meta=meta)
    seq.times = _times(root, files, seq.meta)
    if poses_file is not None:
        from rangemcl.datasets.rosbag import poses_at_scans

        seq.poses = poses_at_scans(poses_file, seq.times)
    elif (kitti := kitti_poses_file(root)) is not None:
        lines = read_lines(kitti, drop_partial=False)
        if len(lines) != len(files):
            raise InputError(f"{kitti}: {len(lines)} lines for {len(files)} scans")
        seq.poses = poses_from_lines(kitti, lines)
    if require_poses and seq.poses is None:
        raise InputError(f"{root}: no poses (put poses.txt in the folder or give --poses FILE)")
    odo = root / "odometry.txt"
    if odo.is_file():
        lines = read_lines(odo, drop_partial=False)
        if len(lines) != len(files):
            raise InputError(f"{odo}: {len(lines)} lines for {len(files)} scans")
        seq.odometry = poses_from_lines(odo, lines)
    return seq
