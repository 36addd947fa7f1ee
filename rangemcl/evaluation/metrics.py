"""The paper's localization metrics for an estimated trajectory against ground truth.

* **Success**: the location error is below 5 m at every 100th frame after convergence (the convergence
  frame itself, then every 100th frame after it), and the filter converged at all. Where it is known at
  which frames the filter weighed a scan (its updates: ``rangemcl localize`` and ``evaluate`` of its
  results), success also needs at least one of them from the convergence frame on
  (``success_requires_a_scan_update``: true): a run whose scans had no valid point (all NaN, empty,
  unreadable), or that never moved far enough for an update, tracked with odometry alone and is not a
  success, whatever its error. Runs that weighed scans keep the paper's definition unchanged.
  ``failure_reason`` says why a run failed (None for a success).
* **Frames localized from scans** (given): frames whose scan had valid points for the filter to weigh
  against (``frames_localized_from_scans``, ``frames_without_scan``), and the updates that weighed one
  (``scan_updates``).
* **Location RMSE** over (x, y) and **yaw RMSE** in degrees, over the frames from convergence on.
* **Frames to converge**: from the first frame of the run.
* **First correct fix**: the first convergence declared within ``success_m`` of the truth
  (``first_fix_frame``) and the distance the car drove meanwhile (``first_fix_driven_m``, along the true
  path); given the seconds each frame took (``rangemcl evaluate`` reads them from ``frames.csv``; a run
  writes them in ``summary.json``, not in its ``metrics.json``, whose bytes repeat), the compute from the
  first frame through that frame's own (``first_fix_seconds``). None when no convergence was correct. A
  wrong convergence before it costs its time.
* **Wrong convergences** (given the frames where the filter declared convergence): declared while more
  than ``success_m`` off, each with its frame, its error and the frame of the re-spread that undid it
  (``caught_frame``, None if none did); a run with one is reported as such even if it recovers.
* **False alarms** (given the frames where the filter declared itself lost): declared while the estimate
  it gave up was within ``false_alarm_m`` (2 m) of the truth.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from rangemcl.datasets.kitti import read_poses_txt
from rangemcl.errors import InputError
from rangemcl.se2 import wrap_angle, xyyaw_of


def pose_errors(estimate_xyyaw: np.ndarray, truth_xyyaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Location errors (m) and absolute yaw errors (deg) of ``(N, 3)`` estimates against ``(N, 3)`` truth."""
    e = np.asarray(estimate_xyyaw, np.float64)
    t = np.asarray(truth_xyyaw, np.float64)
    if e.shape != t.shape or e.ndim != 2 or e.shape[1] != 3:
        raise InputError(f"estimate {e.shape} and truth {t.shape} must both be (N, 3) x, y, yaw")
    loc = np.hypot(e[:, 0] - t[:, 0], e[:, 1] - t[:, 1])
    yaw = np.degrees(np.abs(wrap_angle(e[:, 2] - t[:, 2])))
    return loc, yaw


def track_errors(estimate_xyyaw: np.ndarray, truth_xyyaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed along-track and cross-track errors (m): the estimate's offset from the truth in the true
    pose's own frame (along: x forward, positive ahead of the car; cross: y, positive to its left)."""
    e = np.asarray(estimate_xyyaw, np.float64)
    t = np.asarray(truth_xyyaw, np.float64)
    if e.shape != t.shape or e.ndim != 2 or e.shape[1] != 3:
        raise InputError(f"estimate {e.shape} and truth {t.shape} must both be (N, 3) x, y, yaw")
    dx, dy = e[:, 0] - t[:, 0], e[:, 1] - t[:, 1]
    c, s = np.cos(t[:, 2]), np.sin(t[:, 2])
    return c * dx + s * dy, -s * dx + c * dy


def localization_metrics(
    estimate_xyyaw: np.ndarray,
    truth_xyyaw: np.ndarray,
    converged_frame: int | None,
    *,
    check_every: int = 100,
    success_m: float = 5.0,
    convergence_frames: list[int] | None = None,
    recovery_frames: list[int] | None = None,
    false_alarm_m: float = 2.0,
    caught_within: int = 10,
    frames_with_scan: int | None = None,
    updates: np.ndarray | None = None,
    seconds: np.ndarray | None = None,
) -> dict:
    """The metrics of the module docstring as a JSON-ready dict (NaN-free: missing values are None).
    Frame numbers (``converged_frame`` and the event lists) count from the first row of the arrays.
    ``frames_with_scan``: how many frames had a scan with valid points for the filter; ``updates``
    ``(N,)`` bool: the frames at which the filter weighed a scan (then success needs one from the
    convergence frame on); ``seconds`` ``(N,)``: each frame's compute (then the first correct fix's
    figures). None: not known (the fields are left out, success as the paper's)."""
    loc, yaw = pose_errors(estimate_xyyaw, truth_xyyaw)
    n = len(loc)
    scans: dict = {}
    if frames_with_scan is not None:
        scans.update(
            frames_localized_from_scans=int(frames_with_scan), frames_without_scan=n - int(frames_with_scan)
        )
    weighed = None  # a scan weighed from the convergence frame on (from the first frame while not converged)
    if updates is not None:
        updates = np.asarray(updates, bool).reshape(-1)
        if len(updates) != n:
            raise InputError(f"updates: {len(updates)} flags for {n} frames")
        weighed = bool(updates[converged_frame if converged_frame is not None else 0 :].any())
        scans.update(scan_updates=int(updates.sum()), success_requires_a_scan_update=True)
    no_scan = None
    if frames_with_scan == 0:
        no_scan = "no frame had a scan with a valid point: the estimate is odometry alone"
    elif weighed is False:
        no_scan = "the filter weighed no scan from the convergence frame on: the estimate is odometry alone"
    events = convergence_events(
        loc, convergence_frames, recovery_frames, success_m=success_m, false_alarm_m=false_alarm_m
    )
    events["wrong_convergences_uncaught"] = sum(
        1
        for w in events["wrong_convergences"]
        if w["caught_frame"] is None or w["caught_frame"] - w["frame"] > caught_within
    )
    events["caught_within_frames"] = caught_within
    onsets = convergence_frames if convergence_frames is not None else [converged_frame]
    fix = first_correct_fix(loc, truth_xyyaw, onsets, seconds, success_m=success_m)
    if seconds is None:  # a timing: not part of a run's metrics.json, whose bytes repeat with its input
        del fix["first_fix_seconds"]
    events.update(fix)
    out: dict = {
        "frames": n,
        "converged": converged_frame is not None,
        "converged_frame": converged_frame,
        "frames_to_converge": converged_frame,
        "success_threshold_m": success_m,
        "check_every": check_every,
        **events,
        **scans,
    }
    if converged_frame is None or not 0 <= converged_frame < n:
        out.update(success=False, failure_reason=no_scan or "never converged", checked_frames=[])
        out.update(location_rmse_m=None, yaw_rmse_deg=None)
        return out
    checks = list(range(converged_frame, n, check_every))
    after = slice(converged_frame, n)
    close = bool(np.all(loc[checks] < success_m))
    far = f"location error {loc[checks].max():.2f} m at a checked frame (success: under {success_m:g} m)"
    out.update(
        success=close and no_scan is None,
        failure_reason=no_scan or (None if close else far),
        checked_frames=checks,
        max_error_at_checks_m=float(loc[checks].max()),
        location_rmse_m=float(np.sqrt(np.mean(loc[after] ** 2))),
        yaw_rmse_deg=float(np.sqrt(np.mean(yaw[after] ** 2))),
        location_median_m=float(np.median(loc[after])),
        location_max_m=float(loc[after].max()),
        yaw_max_deg=float(yaw[after].max()),
        final_location_error_m=float(loc[-1]),
    )
    return out


def convergence_events(
    location_error_m: np.ndarray,
    convergence_frames: list[int] | None,
    recovery_frames: list[int] | None,
    *,
    success_m: float = 5.0,
    false_alarm_m: float = 2.0,
) -> dict:
    """Wrong convergences and false alarms (module docstring) from the per-frame location errors and the
    frames (indices into them) where convergence and "lost" were declared. A lost declaration judges the
    estimate it gave up: the error at the frame before it."""
    err = np.asarray(location_error_m, np.float64)
    conv = sorted(int(f) for f in (convergence_frames or []) if 0 <= int(f) < len(err))
    lost = sorted(int(f) for f in (recovery_frames or []) if 0 <= int(f) < len(err))
    wrong = []
    for f in conv:
        if err[f] > success_m:
            after = [r for r in lost if r > f]
            caught = after[0] if after else None
            wrong.append(
                {
                    "frame": f,
                    "error_m": float(err[f]),
                    "caught_frame": caught,
                    "frames_to_catch": None if caught is None else caught - f,
                }
            )
    alarms = [
        {"frame": r, "error_m": float(err[max(r - 1, 0)])} for r in lost if err[max(r - 1, 0)] < false_alarm_m
    ]
    return {
        "convergences": len(conv),
        "wrong_convergences": wrong,
        "wrong_convergences_count": len(wrong),
        "recoveries": len(lost),
        "false_alarms": alarms,
        "false_alarms_count": len(alarms),
    }


def first_correct_fix(
    location_error_m: np.ndarray,
    truth_xyyaw: np.ndarray,
    convergence_frames: list[int | None],
    seconds: np.ndarray | None = None,
    *,
    success_m: float = 5.0,
) -> dict:
    """The first convergence declared within ``success_m`` of the truth (an index into the arrays), the
    seconds of compute from the first frame through it (``seconds`` ``(N,)``, each frame's; None: not
    known) and the distance driven meanwhile along the true path ``(N, 3)``; all None when no convergence
    was correct."""
    err = np.asarray(location_error_m, np.float64)
    secs = None if seconds is None else np.asarray(seconds, np.float64).reshape(-1)
    if secs is not None and len(secs) != len(err):
        raise InputError(f"seconds: {len(secs)} values for {len(err)} frames")
    right = sorted(int(f) for f in convergence_frames if f is not None and 0 <= int(f) < len(err))
    right = [f for f in right if err[f] <= success_m]
    if not right:
        return {"first_fix_frame": None, "first_fix_seconds": None, "first_fix_driven_m": None}
    f = right[0]
    xy = np.asarray(truth_xyyaw, np.float64)[: f + 1, :2]
    return {
        "first_fix_frame": f,
        "first_fix_seconds": None if secs is None else float(secs[: f + 1].sum()),
        "first_fix_driven_m": float(np.hypot(*np.diff(xy, axis=0).T).sum()),
    }


def evaluate_results(results_dir, gt_path, *, check_every: int = 100, success_m: float = 5.0) -> dict:
    """Metrics of a ``rangemcl localize`` results folder against a ground-truth ``poses.txt`` (the same
    convention as the sequence's, so the folder's ``estimate_kitti.txt`` compares line by line)."""
    results_dir = Path(results_dir)
    spath = results_dir / "summary.json"
    epath = results_dir / "estimate_kitti.txt"
    if not (spath.is_file() and epath.is_file()) and (results_dir / "frames.csv").is_file():
        return _evaluate_partial(results_dir, gt_path, check_every=check_every, success_m=success_m)
    for p in (spath, epath):
        if not p.is_file():
            raise InputError(f"{p}: missing (is {results_dir} a `rangemcl localize` results folder?)")
    try:
        summary = json.loads(spath.read_text())
    except (OSError, ValueError) as err:
        raise InputError(f"{spath}: cannot read ({err})") from None
    try:  # a summary edited or damaged by hand: one line naming it
        if not isinstance(summary, dict):
            raise ValueError(f"expected a JSON object, got {type(summary).__name__}")
        first = int(summary.get("first_frame", 0))
        conv = summary.get("converged_frame")
        conv = None if conv is None else int(conv) - first
        conv_frames = [int(f) - first for f in summary.get("convergence_frames", [])]
        rec_frames = [int(f) - first for f in summary.get("recovery_frames", [])]
        Tr = np.asarray(summary.get("calib_Tr", np.eye(4).tolist()), np.float64)
        if Tr.shape != (4, 4) or not np.isfinite(Tr).all():
            raise ValueError(f"calib_Tr: expected a finite 4 x 4 matrix, got shape {Tr.shape}")
    except (TypeError, ValueError) as err:
        raise InputError(f"{spath}: malformed ({err})") from None
    est = read_poses_txt(epath)
    gt = read_poses_txt(gt_path)
    if len(gt) < first + len(est):
        raise InputError(
            f"{gt_path}: has {len(gt)} poses but the run estimated frames {first}..{first + len(est) - 1}"
        )
    est_l = est @ Tr
    gt_l = gt[first : first + len(est)] @ Tr
    updated = _frames_column(results_dir / "frames.csv", "updated", len(est))
    with_scan = summary.get("frames_localized_from_scans")  # (results of an earlier version: not known)
    metrics = localization_metrics(
        xyyaw_of(est_l),
        xyyaw_of(gt_l),
        conv,
        check_every=check_every,
        success_m=success_m,
        convergence_frames=conv_frames,
        recovery_frames=rec_frames,
        frames_with_scan=with_scan if isinstance(with_scan, int) and 0 <= with_scan <= len(est) else None,
        updates=None if updated is None else updated == 1.0,
        seconds=_frames_column(results_dir / "frames.csv", "seconds", len(est)),
    )
    shift_event_frames(metrics, first)
    metrics["first_frame"] = first
    metrics["ground_truth"] = str(gt_path)
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in metrics.items()}


def _frames_column(path: Path, name: str, n: int) -> np.ndarray | None:
    """Column ``name`` of a results folder's ``frames.csv`` as floats (``updated``: the frames at which the
    filter weighed a scan, 1/0; ``seconds``: each frame's compute), when it has one for each of the ``n``
    frames; else None."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return None
    cols = lines[0].split(",") if lines else []
    if name not in cols or len(lines) != n + 1:
        return None
    at = cols.index(name)
    try:
        return np.array([float(line.split(",")[at]) for line in lines[1:]])
    except (IndexError, ValueError):
        return None


def _evaluate_partial(results_dir: Path, gt_path, *, check_every: int, success_m: float) -> dict:
    """A run that was killed outright (no summary.json, no estimate files): its ``frames.csv``, written
    and flushed frame by frame, has every finished frame's planar estimate and events. The sensor-to-pose
    calibration is read from the ``calib.txt`` beside ``gt_path`` (identity without one). The metrics
    say ``"partial": true``."""
    from rangemcl.datasets.kitti import read_calib

    path = results_dir / "frames.csv"
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror or err})") from None
    if len(lines) < 2:
        raise InputError(f"{path}: no frame was finished: nothing to evaluate")
    cols = lines[0].split(",")
    need = ("frame", "x", "y", "yaw", "converged", "recovered")
    if any(c not in cols for c in need):
        raise InputError(f"{path}: not a `rangemcl localize` frames.csv (columns {', '.join(need)} expected)")
    rows, updated, secs = [], [], []
    for n, line in enumerate(lines[1:], start=2):
        parts = line.split(",")
        if len(parts) != len(cols):
            break  # a last line cut by the kill
        try:
            rows.append([float(parts[cols.index(c)]) for c in need])
            updated.append(parts[cols.index("updated")] == "1" if "updated" in cols else False)
            secs.append(float(parts[cols.index("seconds")]) if "seconds" in cols else 0.0)
        except ValueError:
            raise InputError(f"{path}: line {n} is not numbers") from None
    if not rows:
        raise InputError(f"{path}: no complete frame line: nothing to evaluate")
    data = np.asarray(rows)
    frames = data[:, 0].astype(int)
    first = int(frames[0])
    gt = read_poses_txt(gt_path)
    if len(gt) <= frames[-1]:
        raise InputError(f"{gt_path}: has {len(gt)} poses but the run reached frame {frames[-1]}")
    Tr = read_calib(Path(gt_path).parent / "calib.txt")
    truth = xyyaw_of(gt[frames] @ Tr)
    converged = data[:, 4] > 0.5
    onsets = [k for k in range(len(frames)) if converged[k] and (k == 0 or not converged[k - 1])]
    recoveries = [k for k in range(len(frames)) if data[k, 5] > 0.5]
    conv = onsets[-1] if onsets and converged[-1] else None
    metrics = localization_metrics(
        data[:, 1:4],
        truth,
        conv,
        check_every=check_every,
        success_m=success_m,
        convergence_frames=onsets,
        recovery_frames=recoveries,
        updates=np.asarray(updated, bool) if "updated" in cols else None,
        seconds=np.asarray(secs) if "seconds" in cols else None,
    )
    shift_event_frames(metrics, first)
    metrics["first_frame"] = first
    metrics["ground_truth"] = str(gt_path)
    metrics["partial"] = True
    metrics["partial_reason"] = "summary.json or estimate_kitti.txt missing: evaluated frames.csv"
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in metrics.items()}


def shift_event_frames(metrics: dict, first: int) -> None:
    """Frame numbers of a metrics dict from run-relative to the sequence's own."""
    if metrics["converged_frame"] is not None:
        metrics["converged_frame"] += first
    if metrics.get("first_fix_frame") is not None:
        metrics["first_fix_frame"] += first
    for w in metrics["wrong_convergences"]:
        w["frame"] += first
        if w["caught_frame"] is not None:
            w["caught_frame"] += first
    for a in metrics["false_alarms"]:
        a["frame"] += first
