"""LiDAR odometry from kiss-icp for sequences without wheel odometry, and KITTI-style drift metrics that
compare any odometry with the ground truth.

* :class:`KissIcpOdometry` wraps one kiss-icp pipeline (Vizzo et al., RA-L 2023): one
  :meth:`~KissIcpOdometry.register_frame` per scan, no I/O. :func:`kiss_icp_odometry` runs it over the frames
  of a source (a :class:`rangemcl.datasets.kitti.Sequence` or anything with ``__len__``, ``scan``,
  ``point_meta``
  and ``meta``) and returns LiDAR poses like ``Sequence.odometry``.
* :func:`odometry_drift` measures an odometry against the truth: relative translation and rotation errors
  over 20/50/100 m segments (the KITTI odometry benchmark's metric) and the drift at the end of the drive.

Odometry frame: the level vehicle base at the first frame. Frame ``first``'s pose is the mount
``T_base_sensor`` (the identity when the source's meta has none), so ``pose_k = T_base_sensor @ K_k`` with
``K_k`` kiss-icp's pose of the sensor at frame ``k`` in the sensor frame of the first frame. The localizer
uses x, y and yaw increments of these poses only.

Per-point times (``point_meta(i)["time_s"]``, seconds relative to the frame's stamp, ≤ 0, the stamp being
the sweep end) go to kiss-icp's de-skew, which normalises them per scan and moves every point to the
scan's latest time, i.e. to the frame's stamp. Times that are absent, not finite or all equal are not
passed (all-equal times make kiss-icp abort the whole process).

A frame without usable points (empty, or none within the range limits) is not registered: its pose is
predicted at constant velocity from the previous two, and :func:`kiss_icp_odometry` warns once, naming
such frames. kiss-icp itself is an optional extra, imported when a pipeline is built.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from rangemcl.errors import InputError
from rangemcl.se2 import pose2d, pose_matrix, rotation_roll_pitch, wrap_angle, yaw_matrix, yaw_of

__all__ = [
    "DEFAULT_MAX_RANGE_M",
    "DEFAULT_MIN_RANGE_M",
    "KissIcpOdometry",
    "ScanSource",
    "kiss_icp_odometry",
    "mount_of",
    "odometry_drift",
]

DEFAULT_MAX_RANGE_M = 100.0  # kiss-icp's own default, for a source whose meta has no sensor spec
DEFAULT_MIN_RANGE_M = 1.5  # closer returns are mostly the car itself, not the scene
KISS_INSTALL = "--odometry kiss-icp needs kiss-icp: pip install 'simbed-rangemcl[kiss]'"


class ScanSource(Protocol):
    """What :func:`kiss_icp_odometry` reads (:class:`rangemcl.datasets.kitti.Sequence` is one)."""

    meta: dict[str, Any]

    def __len__(self) -> int: ...
    def scan(self, i: int) -> np.ndarray: ...  # (M, 3) float32, sensor frame
    def point_meta(self, i: int) -> dict[str, np.ndarray]: ...


# --- settings from the source's meta ---------------------------------------------------------------------


def _where(source: Any) -> str:
    root = getattr(source, "root", None)
    return f"{root}/meta.yaml" if root is not None else "the source's meta"


def _sensor(meta: Any) -> Mapping[str, Any]:
    sensor = meta.get("sensor") if isinstance(meta, Mapping) else None
    return sensor if isinstance(sensor, Mapping) else {}


def _finite_number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{where}: sensor.{key} must be a finite number, got {value!r}")
    return float(value)


def mount_of(meta: Any, where: str = "meta") -> np.ndarray:
    """``T_base_sensor`` ``(4, 4)`` from ``meta["sensor"]["mount"]`` (``{xyz_m, rpy_deg}``, ``R = Rz Ry Rx``
    as :mod:`rangemcl.sensors` writes it); the identity when the meta has no mount."""
    mount = _sensor(meta).get("mount")
    T = np.eye(4)
    if mount is None:
        return T
    if not isinstance(mount, Mapping):
        raise InputError(f"{where}: sensor.mount must be a mapping with keys xyz_m, rpy_deg, got {mount!r}")
    values = {}
    for key, default in (("xyz_m", [0.0, 0.0, 0.0]), ("rpy_deg", [0.0, 0.0, 0.0])):
        v = mount.get(key, default)
        if not isinstance(v, list | tuple) or len(v) != 3:
            raise InputError(f"{where}: sensor.mount.{key} must be a list of 3 numbers, got {v!r}")
        values[key] = [_finite_number(x, f"mount.{key}", where) for x in v]
    roll, pitch, yaw = np.radians(values["rpy_deg"])
    T[:3, :3] = yaw_matrix(yaw) @ rotation_roll_pitch(roll, pitch)
    T[:3, 3] = values["xyz_m"]
    return T


# --- one kiss-icp pipeline -------------------------------------------------------------------------------


class KissIcpOdometry:
    """One kiss-icp pipeline: feed scans in order with :meth:`register_frame`, get LiDAR poses back.

    Args:
        max_range_m, min_range_m: points outside this range (from the sensor) are dropped.
        voxel_size_m: kiss-icp's map voxel; default ``max_range_m / 100`` (kiss-icp's default).
        T_base_sensor: (4, 4) mount; the first frame's returned pose (see the module docstring).

    Raises :class:`InputError` naming the install when kiss-icp is missing.
    """

    def __init__(
        self,
        *,
        max_range_m: float = DEFAULT_MAX_RANGE_M,
        min_range_m: float = DEFAULT_MIN_RANGE_M,
        voxel_size_m: float | None = None,
        T_base_sensor: np.ndarray | None = None,
    ):
        if not (math.isfinite(max_range_m) and math.isfinite(min_range_m) and 0 <= min_range_m < max_range_m):
            raise InputError(
                f"kiss-icp: need 0 <= min range < max range, got {min_range_m} and {max_range_m}"
            )
        if voxel_size_m is None:
            voxel_size_m = max_range_m / 100.0
        if not (math.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise InputError(f"kiss-icp: voxel size must be > 0 m, got {voxel_size_m}")
        try:
            from kiss_icp.config.parser import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError:
            raise InputError(KISS_INSTALL) from None

        self.max_range_m = float(max_range_m)
        self.min_range_m = float(min_range_m)
        self.voxel_size_m = float(voxel_size_m)
        self.T_base_sensor = np.eye(4) if T_base_sensor is None else np.asarray(T_base_sensor, np.float64)
        # KISSConfig() leaves voxel_size None (KissICP then fails): every field we rely on is set here
        config = KISSConfig()
        config.data.max_range = self.max_range_m
        config.data.min_range = self.min_range_m
        config.data.deskew = True
        config.mapping.voxel_size = self.voxel_size_m
        self._kiss = KissICP(config)
        self.frames = 0  # scans seen
        self.predicted: list[int] = []  # indices (counting scans seen, from 0) of predicted poses

    def register_frame(self, points: np.ndarray, time_s: np.ndarray | None = None) -> np.ndarray:
        """The LiDAR pose ``(4, 4)`` of the next scan in the odometry frame.

        ``points`` ``(M, 3)`` in the sensor frame; ``time_s`` ``(M,)`` per-point times (any offset: kiss-icp
        normalises them per scan) or None. Non-finite points are dropped; a scan with no point left within
        the range limits is not registered, its pose predicted at constant velocity (index in
        :attr:`predicted`).
        """
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] < 3:
            raise InputError(f"kiss-icp: scan {self.frames} has shape {points.shape}, expected (M, 3)")
        xyz = points[:, :3].astype(np.float64)  # (M, 3)
        if time_s is not None:
            time_s = np.asarray(time_s, np.float64).reshape(-1)
            if len(time_s) != len(xyz):
                raise InputError(
                    f"kiss-icp: scan {self.frames} has {len(xyz)} points but {len(time_s)} per-point times"
                )
        r = np.linalg.norm(xyz, axis=1)
        keep = np.isfinite(r) & (r >= self.min_range_m) & (r <= self.max_range_m)
        if not keep.any():
            kiss = self._kiss
            kiss.last_pose = kiss.last_pose @ kiss.last_delta
            self.predicted.append(self.frames)
        else:
            xyz = xyz[keep]
            times = np.array([])
            if time_s is not None:
                t = time_s[keep]
                # all-equal times make kiss-icp's de-skew take exp of NaN and abort the process
                if np.isfinite(t).all() and np.ptp(t) > 0:
                    times = t
            self._kiss.register_frame(xyz, times)
        self.frames += 1
        return self.T_base_sensor @ self._kiss.last_pose

    @classmethod
    def for_source(
        cls,
        source: ScanSource,
        *,
        max_range_m: float | None = None,
        min_range_m: float | None = None,
        voxel_size_m: float | None = None,
    ) -> KissIcpOdometry:
        """A pipeline set up from the source's sensor spec (``meta["sensor"]``: max/min range and mount);
        arguments given here win. Defaults without a spec: 100 m, 1.5 m, identity mount."""
        where = _where(source)
        sensor = _sensor(source.meta)
        if max_range_m is None:
            value = sensor.get("max_range_m")
            max_range_m = (
                DEFAULT_MAX_RANGE_M if value is None else _finite_number(value, "max_range_m", where)
            )
        if min_range_m is None:
            value = sensor.get("min_range_m")
            spec_min = 0.0 if value is None else _finite_number(value, "min_range_m", where)
            min_range_m = min(max(DEFAULT_MIN_RANGE_M, spec_min), 0.5 * max_range_m)
        return cls(
            max_range_m=max_range_m,
            min_range_m=min_range_m,
            voxel_size_m=voxel_size_m,
            T_base_sensor=mount_of(source.meta, where),
        )


@contextlib.contextmanager
def _progress(total: int, enabled: bool) -> Iterator[Any]:
    """A rich progress bar's ``advance()`` (a do-nothing one when disabled)."""
    if not enabled:
        yield lambda: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("kiss-icp"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()) as bar:
        task = bar.add_task("kiss-icp", total=total)
        yield lambda: bar.advance(task)


def _frames_text(frames: Sequence[int]) -> str:
    shown = ", ".join(str(k) for k in frames[:10])
    return shown + (f" … ({len(frames)} in all)" if len(frames) > 10 else "")


def kiss_icp_odometry(
    source: ScanSource,
    *,
    first: int = 0,
    last: int | None = None,
    max_range_m: float | None = None,
    min_range_m: float | None = None,
    voxel_size_m: float | None = None,
    progress: bool = False,
) -> np.ndarray:
    """LiDAR poses ``(N, 4, 4)`` float64 from kiss-icp for frames ``first … last - 1`` of ``source``, in the
    odometry frame of the module docstring (frame ``first``'s pose is the mount ``T_base_sensor``).

    Settings default to the source's sensor spec (:meth:`KissIcpOdometry.for_source`). Frames without
    usable points get a constant-velocity prediction and one warning lists them. Raises
    :class:`InputError` for a bad frame range, a bad sensor spec in the meta or a missing kiss-icp.
    """
    n = len(source)
    stop = n if last is None else last
    if not 0 <= first < stop <= n:
        raise InputError(f"kiss-icp: frames {first} … {stop} out of range (the source has {n} frames)")
    odo = KissIcpOdometry.for_source(
        source, max_range_m=max_range_m, min_range_m=min_range_m, voxel_size_m=voxel_size_m
    )
    poses = np.empty((stop - first, 4, 4))  # (N, 4, 4)
    with _progress(stop - first, progress) as advance:
        for k, i in enumerate(range(first, stop)):
            poses[k] = odo.register_frame(source.scan(i), source.point_meta(i).get("time_s"))
            advance()
    if odo.predicted:
        frames = [first + k for k in odo.predicted]
        warnings.warn(
            f"kiss-icp: frame(s) {_frames_text(frames)} have no points within {odo.min_range_m:g}-"
            f"{odo.max_range_m:g} m: their poses are predicted at constant velocity",
            stacklevel=2,
        )
    return poses


# --- drift metrics ---------------------------------------------------------------------------------------


def _as_poses(a: Any, name: str) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4):
        raise InputError(f"odometry_drift: {name} must be (N, 4, 4) poses, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"odometry_drift: {name} has NaN or inf")
    return a


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angles (rad) of rotations ``(..., 3, 3)``."""
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arccos(np.clip(c, -1.0, 1.0))


def odometry_drift(
    odometry: np.ndarray,
    truth: np.ndarray,
    segment_m: Sequence[float] = (20, 50, 100),
    *,
    planar: bool = False,
    step: int = 1,
) -> dict:
    """KITTI-style drift of an odometry against the truth, both ``(N, 4, 4)`` poses of the same frames.

    For every start frame (every ``step``-th) and segment length ``L`` the segment ends at the first frame
    at least ``L`` metres further along the true path; the error of the odometry's relative pose over the
    segment against the true one gives a translation error (divided by the segment's true length; KITTI
    divides by ``L``, the same to a frame's travel) and a rotation error (its angle, per metre).

    The odometry is aligned to the truth at frame 0 (``truth[0] @ inv(odometry[0]) @ odometry``) for the
    final drift: position error at the last frame as % of the distance driven, and the yaw error there.

    ``planar``: measure the poses' projections onto the ground plane (x, y, yaw), what the localizer uses;
    else in 3D as KITTI does (height and roll/pitch errors count too). ``step``: start every n-th frame.

    Returns a JSON-ready dict (None where no segment fits in the drive): ``frames``, ``planar``,
    ``distance_m``, ``t_err_pct`` and ``r_err_deg_per_100m`` (the mean over all segments of all lengths, as
    KITTI averages), ``segments`` (per length: ``count``, ``t_err_pct``, ``r_err_deg_per_100m``),
    ``final_error_m``, ``final_drift_pct`` and ``final_yaw_err_deg`` (signed, odometry minus truth).
    """
    odo = _as_poses(odometry, "odometry")
    gt = _as_poses(truth, "truth")
    if len(odo) != len(gt) or len(gt) == 0:
        raise InputError(f"odometry_drift: {len(odo)} odometry poses for {len(gt)} true poses")
    if step < 1:
        raise InputError(f"odometry_drift: step must be >= 1, got {step}")
    if not all(math.isfinite(L) and L > 0 for L in segment_m):
        raise InputError(f"odometry_drift: segment lengths must be > 0 m, got {list(segment_m)}")
    if planar:
        odo = pose_matrix(*pose2d(odo).T)
        gt = pose_matrix(*pose2d(gt).T)
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    dist = np.concatenate([[0.0], np.cumsum(steps)])  # (N,) metres along the true path
    gt_inv = np.linalg.inv(gt)
    odo_inv = np.linalg.inv(odo)

    segments: dict[str, dict[str, float | int | None]] = {}
    t_all: list[np.ndarray] = []
    r_all: list[np.ndarray] = []
    starts = np.arange(0, len(gt), step)
    for length in segment_m:
        ends = np.searchsorted(dist, dist[starts] + float(length), side="left")
        ok = ends < len(gt)
        a, b = starts[ok], ends[ok]
        travelled = dist[b] - dist[a]  # (S,) >= length
        d_gt = gt_inv[a] @ gt[b]  # (S, 4, 4)
        d_odo = odo_inv[a] @ odo[b]
        err = np.linalg.inv(d_odo) @ d_gt
        t_err = np.linalg.norm(err[:, :3, 3], axis=1) / travelled  # (S,) fraction
        r_err = _rotation_angle(err[:, :3, :3]) / travelled  # (S,) rad/m
        t_all.append(t_err)
        r_all.append(r_err)
        segments[f"{float(length):g}"] = {
            "count": len(a),
            "t_err_pct": float(100 * t_err.mean()) if len(a) else None,
            "r_err_deg_per_100m": float(100 * np.degrees(r_err.mean())) if len(a) else None,
        }
    t_cat = np.concatenate(t_all) if t_all else np.empty(0)
    r_cat = np.concatenate(r_all) if r_all else np.empty(0)

    aligned_end = gt[0] @ odo_inv[0] @ odo[-1]
    final_error_m = float(np.linalg.norm(aligned_end[:3, 3] - gt[-1, :3, 3]))
    distance_m = float(dist[-1])
    return {
        "frames": len(gt),
        "planar": planar,
        "distance_m": distance_m,
        "t_err_pct": float(100 * t_cat.mean()) if len(t_cat) else None,
        "r_err_deg_per_100m": float(100 * np.degrees(r_cat.mean())) if len(r_cat) else None,
        "segments": segments,
        "final_error_m": final_error_m,
        "final_drift_pct": 100 * final_error_m / distance_m if distance_m > 0 else None,
        "final_yaw_err_deg": math.degrees(float(wrap_angle(yaw_of(aligned_end) - yaw_of(gt[-1])))),
    }
