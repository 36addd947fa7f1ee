"""Sequences of LiDAR frames in the KITTI odometry layout: simulated drives and real KITTI load alike.

A sequence folder holds::

    velodyne/000000.bin …   float32 (x, y, z, intensity) records, one file per frame
    (``rangemcl.datasets.scanio``)
    poses.txt               one line per frame: 12 numbers, row-major 3×4 pose (ground truth)
    calib.txt               optional; its ``Tr:`` line (12 numbers) maps sensor → pose frame (KITTI:
                            velodyne → left camera); ``P0:`` … ``P3:`` and any other lines are ignored.
                            Missing: identity.
    times.txt               one float per line, seconds, non-decreasing
    odometry.txt            optional: 12 numbers per line, the pose the car's own odometry integrated
    imu.txt                 optional: ``roll pitch`` in radians per line
    meta.yaml               optional: a free mapping (scene, sensor spec, seed, route, ``complete`` …)
    points_meta/000000.npz  optional: per-point arrays of each frame (``ring``, ``column``, ``time_s``…)

Poses returned by :func:`load_sequence` are **LiDAR poses**: ``poses @ Tr`` (and ``odometry @ Tr``). For
our own data ``Tr`` is the identity, so they are the sensor poses in the world. For KITTI, ``poses.txt``
holds left-camera poses in the frame of the camera at frame 0 (x right, y down, z forward), so ``poses @ Tr``
is the velodyne pose in that camera frame; a caller wanting a z-up world left-multiplies by ``inv(Tr)``.

Real KITTI keeps poses apart from the sequence (``dataset/poses/00.txt`` next to
``dataset/sequences/00/``); when a sequence folder has no ``poses.txt`` and sits in a folder named
``sequences``, that file is used.

:class:`SequenceWriter` writes frames one by one so that the folder is readable at every moment: the scan
(and its ``points_meta``) is renamed into place first, then one line is appended (flushed, fsynced) to each
text file. ``meta.yaml`` says ``complete: false`` while recording and ``complete: true`` after ``close``; for
such an incomplete sequence the reader drops a last frame that lacks some of its files or lines (a crash
mid-frame), and a last text line without its newline.
"""

from __future__ import annotations

import math
import os
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rangemcl.common.atomic import atomic_write
from rangemcl.common.yamlio import parse_yaml, read_text
from rangemcl.datasets.recording import Recording
from rangemcl.datasets.scanio import read_scan_bin, write_scan_bin
from rangemcl.errors import InputError

__all__ = [
    "ROTATION_TOL",
    "Sequence",
    "SequenceWriter",
    "load_sequence",
    "poses_to_tum",
    "read_poses_txt",
    "write_poses_txt",
]

ROTATION_TOL = 1e-3  # max |RᵀR − I| entry (and |det R − 1|); KITTI writes poses with ~1e-6 precision

LINE_FILES = ("poses.txt", "times.txt", "odometry.txt", "imu.txt")
_SEQUENCE_FILES = (*LINE_FILES, "calib.txt", "meta.yaml")
_SEQUENCE_DIRS = ("velodyne", "points_meta")


# --- small helpers ---------------------------------------------------------------------------------------


def _oserror(path: Path, what: str, err: OSError) -> InputError:
    reason = err.strerror or str(err)
    return InputError(f"{path}: cannot {what} ({reason})")


def _rotation_problem(R: np.ndarray) -> str | None:
    """Why ``R`` (3×3) is not a rotation within :data:`ROTATION_TOL`, or None."""
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOL:
        return f"rotation is not orthonormal (max |RᵀR − I| = {err:.3g} > {ROTATION_TOL:g})"
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > ROTATION_TOL:
        return f"rotation has determinant {det:.6g}, not +1"
    return None


def _as_pose(value: Any, where: str) -> np.ndarray:
    """A (4, 4) float64 rigid transform from a (4, 4) or (3, 4) array; InputError naming ``where``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: not a numeric (4, 4) or (3, 4) array") from None
    if a.shape not in ((4, 4), (3, 4)):
        raise InputError(f"{where}: must have shape (4, 4) or (3, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{where}: has NaN or inf entries")
    if a.shape == (4, 4) and not np.array_equal(a[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{where}: last row must be 0 0 0 1, got {a[3].tolist()}")
    problem = _rotation_problem(a[:3, :3])
    if problem:
        raise InputError(f"{where}: {problem}")
    T = np.eye(4)
    T[:3] = a[:3]
    return T


def read_lines(path: Path, *, drop_partial: bool) -> list[tuple[int, str]]:
    """Numbered non-empty lines of a text file (1-based numbers).

    Trailing blank lines are ignored; a blank line inside the file is an error. With ``drop_partial`` a
    last line without its newline (an interrupted append) is dropped.
    """
    lines = read_text(path).split("\n")
    if drop_partial and lines and lines[-1] != "":
        lines.pop()  # no newline after it: written half
    while lines and not lines[-1].strip():
        lines.pop()
    out = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            raise InputError(f"{path}: line {n} is empty")
        out.append((n, line))
    return out


def parse_numbers(path: Path, n: int, line: str, count: int) -> list[float]:
    parts = line.split()
    if len(parts) != count:
        raise InputError(f"{path}: line {n} has {len(parts)} numbers, expected {count}")
    try:
        return [float(p) for p in parts]
    except ValueError:
        bad = next(p for p in parts if not _is_float(p))
        raise InputError(f"{path}: line {n}: {bad!r} is not a number") from None


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def poses_from_lines(path: Path, lines: list[tuple[int, str]]) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(lines), 1, 1))
    for k, (n, line) in enumerate(lines):
        values = parse_numbers(path, n, line, 12)
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"{path}: line {n} has NaN or inf")
        poses[k, :3] = np.reshape(values, (3, 4))
        problem = _rotation_problem(poses[k, :3, :3])
        if problem:
            raise InputError(f"{path}: line {n}: {problem}")
    return poses


def _pose_line(T: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in T[:3].reshape(-1)) + "\n"


# --- poses.txt and TUM -----------------------------------------------------------------------------------


def read_poses_txt(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a KITTI pose file: ``(N, 4, 4)`` float64, validated (12 finite numbers a line, rotations)."""
    path = Path(path)
    return poses_from_lines(path, read_lines(path, drop_partial=False))


def write_poses_txt(path: str | os.PathLike[str], poses: Any) -> Path:
    """Write ``(N, 4, 4)`` or ``(N, 3, 4)`` poses as KITTI text (``%.9e``), atomically. Returns the path."""
    path = Path(path)
    a = np.asarray(poses, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(f"{path}: poses must have shape (N, 4, 4) or (N, 3, 4), got {a.shape}")
    lines = [_pose_line(_as_pose(T, f"{path}: pose {k}")) for k, T in enumerate(a)]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, "".join(lines))
    except OSError as err:
        raise _oserror(path, "write poses", err) from None
    return path


def poses_to_tum(poses: Any, times: Any) -> list[str]:
    """TUM trajectory lines ``t x y z qx qy qz qw`` (no newlines) for ``(N, 4, 4)`` poses and ``N`` times.

    The quaternion comes from ``scipy.spatial.transform.Rotation`` (scalar last), with ``qw >= 0``.
    """
    from scipy.spatial.transform import Rotation

    P = np.asarray(poses, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if P.ndim != 3 or P.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(f"poses must have shape (N, 4, 4) or (N, 3, 4), got {P.shape}")
    if len(t) != len(P):
        raise InputError(f"{len(t)} times for {len(P)} poses")
    if len(P) == 0:
        return []
    q = Rotation.from_matrix(P[:, :3, :3]).as_quat()
    q[q[:, 3] < 0] *= -1.0
    xyz = P[:, :3, 3]
    return [
        f"{ti:.9f} " + " ".join(f"{v:.9e}" for v in (*p, *qi)) for ti, p, qi in zip(t, xyz, q, strict=True)
    ]


# --- meta.yaml -------------------------------------------------------------------------------------------


def read_meta(path: Path) -> dict[str, Any]:
    if not path.exists():
        return {}
    data = parse_yaml(read_text(path), str(path))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping, got a {type(data).__name__}")
    return data


def _plain(value: Any, key: str) -> Any:
    """``value`` as plain YAML-safe Python (numpy scalars and arrays, tuples, paths converted)."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, dict):
        return {_plain(k, key): _plain(v, f"{key}.{k}") for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v, f"{key}[{i}]") for i, v in enumerate(value)]
    raise InputError(f"meta key {key!r}: cannot write a {type(value).__name__} to meta.yaml")


def _meta_text(meta: dict[str, Any]) -> str:
    """YAML of ``meta``: a block mapping at the top (so more keys can be appended), short lists inline."""
    out = []
    for key, value in meta.items():
        v = _plain(value, str(key))
        flow = False if not isinstance(v, dict | list) else None
        out.append(
            yaml.safe_dump(
                {str(key): v}, sort_keys=False, default_flow_style=flow, width=110, allow_unicode=True
            )
        )
    return "".join(out)


# --- reading ---------------------------------------------------------------------------------------------


@dataclass
class Sequence(Recording):
    """A sequence folder: scans are read lazily, everything else is loaded and validated.

    ``poses`` and ``odometry`` are LiDAR poses (``file @ Tr``), ``(N, 4, 4)`` float64; ``None`` where the
    file is absent (likewise ``times`` ``(N,)`` and ``imu_roll_pitch`` ``(N, 2)``).
    """

    root: Path
    scan_paths: list[Path]
    # calib_source: "calib.txt", or "identity (no calib.txt)": said, never silently assumed

    def __len__(self) -> int:
        return len(self.scan_paths)

    def _index(self, i: int) -> int:
        n = len(self.scan_paths)
        k = int(i)
        if k < 0:
            k += n
        if not 0 <= k < n:
            raise InputError(f"{self.root}: frame {i} out of range (the sequence has {n})")
        return k

    def scan(self, i: int) -> np.ndarray:
        """Points ``(M, 3)`` float32 of frame ``i`` in the sensor frame."""
        return read_scan_bin(self.scan_paths[self._index(i)])[0]

    def scan_with_intensity(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(M, 3)`` float32 and intensity ``(M,)`` float32 of frame ``i``."""
        return read_scan_bin(self.scan_paths[self._index(i)])

    def point_meta(self, i: int) -> dict[str, np.ndarray]:
        """Per-point arrays of frame ``i`` from ``points_meta/NNNNNN.npz``; ``{}`` when there is none.

        Every array's first dimension is checked against the scan's point count.
        """
        scan_path = self.scan_paths[self._index(i)]
        path = self.root / "points_meta" / f"{scan_path.stem}.npz"
        if not path.is_file():
            return {}
        try:
            with open(path, "rb") as fh:
                is_zip = fh.read(2) == b"PK"
        except OSError as err:
            raise _oserror(path, "read per-point arrays", err) from None
        if not is_zip:  # else numpy would try it as a pickle, and say so
            raise InputError(f"{path}: cannot read per-point arrays (not an .npz file)")
        try:
            with np.load(path, allow_pickle=False) as npz:
                arrays = {key: npz[key] for key in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise InputError(f"{path}: cannot read per-point arrays ({err})") from None
        try:
            n_points = scan_path.stat().st_size // 16
        except OSError as err:
            raise _oserror(scan_path, "read scan", err) from None
        for key, a in arrays.items():
            if a.ndim == 0 or len(a) != n_points:
                got = "a scalar" if a.ndim == 0 else f"{len(a)} values"
                raise InputError(f"{path}: array {key!r} has {got} for a scan of {n_points} points")
        return arrays


def _scan_files(root: Path) -> list[Path]:
    velo = root / "velodyne"
    if not velo.is_dir():
        raise InputError(f"{root}: no velodyne/ folder (not a KITTI-layout sequence)")
    paths = [p for p in velo.iterdir() if p.suffix == ".bin" and not p.name.startswith(".")]
    if not paths:
        raise InputError(f"{velo}: no .bin scans")
    if all(p.stem.isdigit() for p in paths):
        paths.sort(key=lambda p: int(p.stem))
        for k, p in enumerate(paths):
            if int(p.stem) != k:
                raise InputError(f"{velo / f'{k:06d}.bin'}: missing (scans must be numbered 0 … N-1)")
    else:
        paths.sort()
    return paths


def read_calib(path: Path) -> np.ndarray:
    if not path.exists():
        return np.eye(4)
    found: list[tuple[int, str]] = []
    for n, line in read_lines(path, drop_partial=False):
        key, sep, rest = line.partition(":")
        if sep and key.strip() in ("Tr", "Tr_velo_to_cam"):
            found.append((n, rest))
    if not found:
        raise InputError(f"{path}: no 'Tr:' line (velodyne → pose-frame transform)")
    if len(found) > 1:
        raise InputError(f"{path}: {len(found)} 'Tr:' lines (lines {', '.join(str(n) for n, _ in found)})")
    n, rest = found[0]
    parts = rest.split()
    if len(parts) != 12:
        raise InputError(f"{path}: 'Tr:' on line {n} has {len(parts)} numbers, expected 12")
    values = parse_numbers(path, n, rest, 12)
    return _as_pose(np.reshape(values, (3, 4)), f"{path}: 'Tr:' on line {n}")


def kitti_poses_file(root: Path) -> Path | None:
    """``root/poses.txt``, else KITTI's ``…/poses/NN.txt`` for ``…/sequences/NN``, else None."""
    own = root / "poses.txt"
    if own.exists():
        return own
    if root.parent.name == "sequences":
        kitti = root.parent.parent / "poses" / f"{root.name}.txt"
        if kitti.is_file():
            return kitti
    return None


def load_sequence(path: str | os.PathLike[str], *, require_poses: bool = False) -> Sequence:
    """Load and validate a sequence folder (scans are only listed; each is read when asked for).

    Every problem is an :class:`InputError` naming the file. The counts of scans and of lines in
    ``poses.txt``, ``times.txt``, ``odometry.txt`` and ``imu.txt`` must agree, except in a folder whose
    ``meta.yaml`` says ``complete: false`` (a recording in progress or interrupted): there, with ``n`` the
    smallest count, counts of ``n + 1`` are cut to ``n`` (a frame written half), and a last line without its
    newline is not counted.
    """
    root = Path(path)
    if not root.exists():
        raise InputError(f"{root}: no such sequence folder")
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    meta = read_meta(root / "meta.yaml")
    incomplete = meta.get("complete") is False
    scan_paths = _scan_files(root)
    calib_Tr = read_calib(root / "calib.txt")

    sources: dict[str, Path] = {}
    poses_file = kitti_poses_file(root)
    if poses_file is not None:
        sources["poses"] = poses_file
    elif require_poses:
        raise InputError(f"{root / 'poses.txt'}: no such file (ground-truth poses are required)")
    for key in ("times", "odometry", "imu"):
        p = root / f"{key}.txt"
        if p.exists():
            sources[key] = p
    lines = {key: read_lines(p, drop_partial=incomplete) for key, p in sources.items()}

    counts = {key: len(v) for key, v in lines.items()}
    n = min([len(scan_paths), *counts.values()])
    all_counts = [len(scan_paths), *counts.values()]
    if incomplete and all(c - n in (0, 1) for c in all_counts):
        if n == 0:
            raise InputError(f"{root}: the recording has no complete frame yet (meta.yaml: complete: false)")
        scan_paths = scan_paths[:n]
        lines = {key: v[:n] for key, v in lines.items()}
    else:
        for key, c in counts.items():
            if c != len(scan_paths):
                raise InputError(
                    f"{sources[key]}: {c} lines for {len(scan_paths)} scans in {root / 'velodyne'}"
                )

    seq = Sequence(root=root, scan_paths=scan_paths, calib_Tr=calib_Tr, meta=meta)
    if not (root / "calib.txt").exists():
        seq.calib_source = "identity (no calib.txt)"
    identity = np.array_equal(calib_Tr, np.eye(4))
    if "poses" in lines:
        P = poses_from_lines(sources["poses"], lines["poses"])
        seq.poses = P if identity else P @ calib_Tr
    if "odometry" in lines:
        O = poses_from_lines(sources["odometry"], lines["odometry"])
        seq.odometry = O if identity else O @ calib_Tr
    if "times" in lines:
        p = sources["times"]
        t = np.array([parse_numbers(p, n, line, 1)[0] for n, line in lines["times"]], dtype=np.float64)
        for k, (n, _) in enumerate(lines["times"]):
            if not math.isfinite(t[k]):
                raise InputError(f"{p}: line {n} is not finite")
            if k and t[k] < t[k - 1]:
                raise InputError(f"{p}: line {n}: time {t[k]:.9g} is before the previous {t[k - 1]:.9g}")
        seq.times = t
    if "imu" in lines:
        p = sources["imu"]
        rp = np.array([parse_numbers(p, n, line, 2) for n, line in lines["imu"]], dtype=np.float64)
        rp = rp.reshape(-1, 2)
        bad = np.flatnonzero(~np.all(np.isfinite(rp), axis=1))
        if len(bad):
            raise InputError(f"{p}: line {lines['imu'][bad[0]][0]} has NaN or inf")
        seq.imu_roll_pitch = rp
    return seq


# --- writing ---------------------------------------------------------------------------------------------


class SequenceWriter:
    """Record a sequence frame by frame; the folder is a readable sequence at every moment.

    ``pose`` and ``odometry`` given to :meth:`add_frame` are LiDAR poses, as :func:`load_sequence` returns
    them: with a non-identity ``calib_Tr`` the files hold ``pose @ inv(Tr)``. ``meta.yaml`` gets the given
    ``meta`` plus ``complete`` (managed by the writer: false until :meth:`close`). Leaving the ``with`` block
    by an exception closes the files but leaves ``complete: false``.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        *,
        meta: dict[str, Any] | None = None,
        calib_Tr: Any = None,
        overwrite: bool = False,
        resume_at: int | None = None,
    ) -> None:
        """``resume_at`` n: continue the sequence in ``root`` after its first n frames (an interrupted
        recording, continued from a checkpoint taken at its n-th frame): frames written after them are
        removed, and the next :meth:`add_frame` writes frame n."""
        self.root = Path(root)
        self.meta: dict[str, Any] = dict(meta or {})
        self.meta.pop("complete", None)
        self.calib_Tr = np.eye(4) if calib_Tr is None else _as_pose(calib_Tr, "calib_Tr")
        self._identity = bool(np.array_equal(self.calib_Tr, np.eye(4)))
        self._inv_Tr = np.linalg.inv(self.calib_Tr)
        self._frames = 0
        self._last_time: float | None = None
        self._has: dict[str, bool] = {}  # "odometry"/"imu" -> given with frame 0
        self._files: dict[str, Any] = {}
        self._closed = False
        self._broken = False
        self._complete = False
        self._meta_text = _meta_text(self.meta)  # fail on unwritable meta before touching the disk
        if resume_at is not None:
            self._cut_back(int(resume_at))
            self._write_meta(complete=False)
            return
        self._prepare(overwrite)
        self._write_meta(complete=False)
        self._write_text("calib.txt", "Tr: " + _pose_line(self.calib_Tr))
        for name in ("poses.txt", "times.txt"):
            self._write_text(name, "")

    # -- setup

    def _prepare(self, overwrite: bool) -> None:
        root = self.root
        if root.exists() and not root.is_dir():
            raise InputError(f"{root}: exists and is not a folder")
        try:
            entries = list(root.iterdir()) if root.is_dir() else []
        except OSError as err:
            raise _oserror(root, "list output folder", err) from None
        if entries:
            names = {p.name for p in entries}
            if not overwrite:
                raise InputError(
                    f"{root}: folder is not empty (give --overwrite to replace the sequence in it)"
                )
            if not names & {*_SEQUENCE_FILES, *_SEQUENCE_DIRS}:
                raise InputError(f"{root}: folder is not empty and holds no sequence; refusing to overwrite")
            try:
                for name in _SEQUENCE_DIRS:
                    if (root / name).is_dir() and not (root / name).is_symlink():
                        shutil.rmtree(root / name)
                    else:
                        (root / name).unlink(missing_ok=True)
                for name in _SEQUENCE_FILES:
                    (root / name).unlink(missing_ok=True)
            except OSError as err:
                raise _oserror(root, "clear the old sequence", err) from None
        try:
            (root / "velodyne").mkdir(parents=True, exist_ok=True)
        except OSError as err:
            probe = root
            while not probe.exists() and probe != probe.parent:
                probe = probe.parent
            if probe.exists() and not probe.is_dir():
                raise InputError(
                    f"{root}: cannot create the output folder ({probe} is not a folder)"
                ) from None
            raise _oserror(root, "create the output folder", err) from None

    def _cut_back(self, n: int) -> None:
        """Keep the first ``n`` frames of the sequence in ``root`` (the line files cut to ``n`` lines, later
        scans and per-point arrays removed) and continue after them."""
        root = self.root
        lines: dict[str, list[str]] = {}
        for name in LINE_FILES:
            path = root / name
            if path.is_file():
                try:
                    lines[name] = path.read_text(encoding="utf-8").splitlines(keepends=True)
                except (OSError, UnicodeDecodeError) as err:
                    raise InputError(f"{path}: cannot read it to continue the sequence ({err})") from None
        for name in ("poses.txt", "times.txt"):
            if len(lines.get(name, ())) < n:
                raise InputError(
                    f"{root / name}: {len(lines.get(name, ()))} lines, but the recording to continue had "
                    f"written {n} frames"
                )
        for name, got in lines.items():
            if len(got) != n:
                self._write_text(name, "".join(got[:n]))
        for folder in _SEQUENCE_DIRS:
            if (root / folder).is_dir():
                for f in (root / folder).iterdir():
                    stem = f.name.split(".")[0]
                    if not stem.isdigit() or int(stem) >= n:
                        f.unlink()
        (root / "velodyne").mkdir(parents=True, exist_ok=True)
        self._frames = n
        if n:
            self._last_time = float(lines["times.txt"][n - 1])
            self._has = {key: len(lines.get(f"{key}.txt", ())) >= n for key in ("odometry", "imu")}

    def _write_text(self, name: str, text: str) -> None:
        path = self.root / name
        try:
            atomic_write(path, text)
        except OSError as err:
            raise _oserror(path, "write", err) from None

    def _write_meta(self, *, complete: bool) -> None:
        self._write_text("meta.yaml", self._meta_text + f"complete: {'true' if complete else 'false'}\n")

    # -- frames

    def __len__(self) -> int:
        return self._frames

    def add_frame(
        self,
        points: Any,
        *,
        pose: Any,
        time_s: float,
        intensity: Any = None,
        odometry: Any = None,
        imu_roll_pitch: Any = None,
        point_meta: dict[str, Any] | None = None,
    ) -> int:
        """Write one frame (scan, per-point arrays, then one line per text file); return its index.

        Everything is validated before anything is written. ``odometry`` and ``imu_roll_pitch`` must be
        given with every frame or with none.
        """
        if self._closed:
            raise RuntimeError(f"{self.root}: SequenceWriter is closed")
        if self._broken:
            raise RuntimeError(f"{self.root}: SequenceWriter failed earlier; the sequence ends before it")
        k = self._frames
        where = f"{self.root}: frame {k}"
        T = _as_pose(pose, f"{where}: pose")
        try:
            t = float(time_s)
        except (TypeError, ValueError):
            raise InputError(f"{where}: time_s {time_s!r} is not a number") from None
        if not math.isfinite(t):
            raise InputError(f"{where}: time_s {t} is not finite")
        if self._last_time is not None and t < self._last_time:
            raise InputError(f"{where}: time_s {t:.9g} is before the previous frame's {self._last_time:.9g}")
        extra: dict[str, Any] = {"odometry": odometry, "imu": imu_roll_pitch}
        for key, value in extra.items():
            given = value is not None
            if k == 0:
                self._has[key] = given
            elif given != self._has[key]:
                was = "given" if self._has[key] else "not given"
                raise InputError(f"{where}: {key} was {was} with earlier frames; give it always or never")
        O = _as_pose(odometry, f"{where}: odometry") if odometry is not None else None
        rp = None
        if imu_roll_pitch is not None:
            rp = np.asarray(imu_roll_pitch, dtype=np.float64).reshape(-1)
            if rp.shape != (2,) or not np.all(np.isfinite(rp)):
                raise InputError(f"{where}: imu_roll_pitch must be 2 finite numbers, got {rp.tolist()}")
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"{where}: points must have shape (N, 3), got {pts.shape}")
        n_points = len(pts)
        arrays: dict[str, np.ndarray] = {}
        for key, value in (point_meta or {}).items():
            a = np.asarray(value)
            if a.dtype == object or a.ndim == 0 or len(a) != n_points:
                got = "a scalar" if a.ndim == 0 else f"{len(a)} values"
                raise InputError(f"{where}: point_meta {key!r} has {got} for {n_points} points")
            arrays[str(key)] = a

        stem = f"{k:06d}"
        bin_path = self.root / "velodyne" / f"{stem}.bin"
        try:
            write_scan_bin(bin_path, points, intensity)
        except OSError as err:
            raise _oserror(bin_path, "write scan", err) from None
        if arrays:
            npz_path = self.root / "points_meta" / f"{stem}.npz"
            tmp = npz_path.with_name(f".{npz_path.name}.tmp.npz")
            try:
                npz_path.parent.mkdir(exist_ok=True)
                np.savez(tmp, **arrays)
                os.replace(tmp, npz_path)
            except OSError as err:
                tmp.unlink(missing_ok=True)
                raise _oserror(npz_path, "write per-point arrays", err) from None

        P = T if self._identity else T @ self._inv_Tr
        lines = {"poses.txt": _pose_line(P), "times.txt": f"{t:.9f}\n"}
        if O is not None:
            lines["odometry.txt"] = _pose_line(O if self._identity else O @ self._inv_Tr)
        if rp is not None:
            lines["imu.txt"] = f"{rp[0]:.9e} {rp[1]:.9e}\n"
        for name, line in lines.items():
            self._append(name, line)
        self._frames += 1
        self._last_time = t
        return k

    def _append(self, name: str, line: str) -> None:
        path = self.root / name
        try:
            f = self._files.get(name)
            if f is None:
                f = self._files[name] = open(path, "a", encoding="utf-8")  # noqa: SIM115 - kept open
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        except OSError as err:
            self._broken = True
            raise _oserror(path, "append", err) from None

    # -- meta and closing

    def update_meta(self, **items: Any) -> None:
        """Merge ``items`` into ``meta.yaml`` and rewrite it atomically (``complete`` stays the writer's)."""
        items.pop("complete", None)
        merged = {**self.meta, **items}
        text = _meta_text(merged)
        self.meta = merged
        self._meta_text = text
        self._write_meta(complete=self._complete)

    def _close_files(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()

    def close(self, *, complete: bool = True) -> None:
        """Close the files and mark ``meta.yaml`` ``complete: true`` (unless ``complete=False`` or a
        write failed). Calling it again does nothing."""
        if self._closed:
            return
        self._close_files()
        self._closed = True
        if complete and not self._broken:
            self._complete = True
            self._write_meta(complete=True)

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close(complete=exc_type is None)
        return False


def perturb_odometry(
    odometry: np.ndarray, times: np.ndarray, *, scale: float = 1.0, yaw_bias_rad_s: float = 0.0
) -> np.ndarray:
    """Odometry poses ``(N, 4, 4)`` as a miscalibrated car would report them: each frame's planar step
    (in the previous frame's pose) with its translation times ``scale`` (a wheel-radius error) and its
    yaw change plus ``yaw_bias_rad_s`` x the frame's duration (a gyro bias), chained again from the
    first pose; height, roll and pitch of each pose are kept."""
    from rangemcl.se2 import pose_matrix, se2_between, se2_compose, yaw_matrix

    T = np.asarray(odometry, np.float64)
    t = np.asarray(times, np.float64).reshape(-1)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(t) != len(T):
        raise InputError(f"odometry: expected (N, 4, 4) poses and N times, got {T.shape} and {t.shape}")
    if not (np.isfinite(scale) and scale > 0 and np.isfinite(yaw_bias_rad_s)):
        raise InputError(
            f"odometry perturbation: scale must be > 0 and the bias finite, got {scale}, {yaw_bias_rad_s}"
        )
    xyyaw = np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])])
    out = T.copy()
    pose = xyyaw[0].copy()
    for k in range(1, len(T)):
        step = se2_between(xyyaw[k - 1], xyyaw[k])
        step[:2] *= scale
        step[2] += yaw_bias_rad_s * (t[k] - t[k - 1])
        pose = se2_compose(pose, step)
        planar = pose_matrix(pose[0], pose[1], pose[2], T[k, 2, 3])
        # keep the frame's own tilt: its rotation relative to its own heading
        planar[:3, :3] = planar[:3, :3] @ (yaw_matrix(xyyaw[k, 2]).T @ T[k, :3, :3])
        out[k] = planar
    return out


def splice_kidnapped(seq_dir, out, a: int, b: int, half: int) -> Path:
    """A kidnapped-car sequence: frames ``a .. a+half-1`` of ``seq_dir``, then frames ``b .. b+half-1``,
    whose odometry carries on smoothly across the jump (the car is teleported; its odometry does not see
    it). Times are re-stamped at the sequence's median frame period. ``meta.yaml`` records the splice."""
    seq = load_sequence(seq_dir, require_poses=True)
    n = len(seq)
    if half < 1 or min(a, b) < 0 or max(a, b) + half > n:
        raise InputError(f"{seq.root}: cannot splice frames {a}+{half} and {b}+{half} from {n} frames")
    if seq.odometry is None:
        raise InputError(f"{seq.root}: a kidnapped-car sequence needs odometry.txt")
    frames = list(range(a, a + half)) + list(range(b, b + half))
    period = float(np.median(np.diff(seq.times))) if seq.times is not None and n > 1 else 0.1
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    meta = dict(seq.meta)
    meta.pop("complete", None)
    meta["spliced_from"] = {"sequence": str(seq.root), "frames": [a, a + half, b, b + half], "jump_at": half}
    odo = seq.odometry[a].copy()
    with SequenceWriter(out, meta=meta, calib_Tr=seq.calib_Tr) as w:
        for k, i in enumerate(frames):
            if k:
                # the odometry's own step into frame i (at the jump: frame b's ordinary step)
                odo = odo @ (np.linalg.inv(seq.odometry[i - 1]) @ seq.odometry[i] if i > 0 else np.eye(4))
            pts, intensity = seq.scan_with_intensity(i)
            w.add_frame(
                pts,
                intensity=intensity,
                pose=seq.poses[i],
                time_s=k * period,
                odometry=odo,
                imu_roll_pitch=seq.imu_roll_pitch[i] if seq.imu_roll_pitch is not None else None,
                point_meta=seq.point_meta(i) or None,
            )
    return out
