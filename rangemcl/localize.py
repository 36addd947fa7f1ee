"""``rangemcl localize``: run the Monte Carlo localizer over a recorded sequence and write the results.

A results folder holds::

    config.yaml          the effective localizer settings (give it back with --config)
    frames.csv           one line per frame, appended as the run goes (frame, time, estimate, particle
                         count, convergence, update/resampling/recovery flags, residual, seconds)
    estimate_kitti.txt   the estimated poses, 12 numbers per line, in the convention of the sequence's
                         poses.txt (so ``evo_ape kitti poses.txt estimate_kitti.txt`` compares them)
    estimate_tum.txt     the estimated LiDAR poses as TUM lines (time x y z qx qy qz qw)
    summary.json         convergence frame, counts, timings, odometry source, device, seed
    metrics.json         the paper's metrics (:mod:`rangemcl.evaluate`) when the sequence has poses
    particles.npz        particle clouds at a few frames
    trajectory.png, error.png, particles.png

The estimate is written for every frame; before convergence it is the (meaningless) mean of a spread
cloud, and the metrics count from the convergence frame on. An interrupted run (Ctrl-C) writes everything
computed up to the interruption, marked ``"interrupted": true``.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.atomic import atomic_write
from rangemcl.config import write_config
from rangemcl.dataset import Sequence, load_sequence, poses_to_tum, write_poses_txt
from rangemcl.errors import InputError
from rangemcl.evaluate import localization_metrics, shift_event_frames, xyyaw_of
from rangemcl.mapping.meshmap import MeshMap
from rangemcl.mcl import LocalizerSettings, MonteCarloLocalizer, rotation_roll_pitch, se2_between

FRAME_COLUMNS = (
    "frame,time_s,x,y,yaw,particles,converged,updated,resampled,skipped_scan,recovered,"
    "best_residual_m,seconds,hypotheses,evidence_nats,inliers,vetoed"
)


@dataclass
class RunOptions:
    mode: str = "global"  # global | tracking
    particles: int | None = None  # global: the spread count; tracking: the tracking count
    device: str = "cpu"
    seed: int = 0
    threads: int | None = None
    first_frame: int = 0
    frames: int | None = None  # at most this many frames
    init_pose: tuple[float, float, float] | None = None  # tracking start (default: the first true pose)
    odometry_from_poses: bool = False  # without odometry.txt: derive it from poses.txt (and say so)
    plots: bool = True
    progress: bool = False


def odometry_xyyaw(seq: Sequence, from_poses: bool) -> tuple[np.ndarray, str]:
    """The odometry as ``(N, 3)`` x, y, yaw and where it came from."""
    if seq.odometry is not None:
        return xyyaw_of(seq.odometry), "odometry.txt"
    if from_poses and seq.poses is not None:
        return xyyaw_of(seq.poses), "poses.txt (derived because the sequence has no odometry.txt)"
    hint = " (or pass --odometry-from-poses to derive it from poses.txt)" if seq.poses is not None else ""
    raise InputError(f"{seq.root}: the sequence has no odometry.txt{hint}")


def check_map_frame(seq: Sequence, mesh_map: MeshMap, margin_m: float = 50.0) -> None:
    """A clear error when the sequence's true poses mostly lie outside the map (another frame, another
    place)."""
    if seq.poses is None:
        return
    x0, y0, _, x1, y1, _ = mesh_map.extent
    xy = seq.poses[:, :2, 3]
    inside = (
        (xy[:, 0] > x0 - margin_m)
        & (xy[:, 0] < x1 + margin_m)
        & (xy[:, 1] > y0 - margin_m)
        & (xy[:, 1] < y1 + margin_m)
    )
    if inside.mean() < 0.5:
        raise InputError(
            f"{seq.root}: {100 * (1 - inside.mean()):.0f} % of the poses lie more than {margin_m:.0f} m "
            f"outside the map (map x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}; poses start at "
            f"({xy[0, 0]:.0f}, {xy[0, 1]:.0f})): is the map in the sequence's frame?"
        )


def _frame_period(seq: Sequence) -> float | None:
    if seq.times is not None and len(seq.times) > 1:
        d = np.diff(seq.times)
        d = d[d > 0]
        if len(d):
            return float(np.median(d))
    return None


def _sensor_height(seq: Sequence, mesh_map: MeshMap, settings: LocalizerSettings) -> tuple[float, str]:
    if settings.sensor_height_m is not None:
        return float(settings.sensor_height_m), "settings"
    sensor = seq.meta.get("sensor") if isinstance(seq.meta, dict) else None
    if isinstance(sensor, dict):
        mount = sensor.get("mount")
        if isinstance(mount, dict) and isinstance(mount.get("xyz_m"), list) and len(mount["xyz_m"]) == 3:
            return float(mount["xyz_m"][2]), "the sequence's sensor mount"
    if "sensor_height_m" in mesh_map.meta:
        return float(mesh_map.meta["sensor_height_m"]), "the map's metadata"
    return 1.73, "default (KITTI)"


def localize_sequence(
    seq_dir, map_dir, out_dir, settings: LocalizerSettings | None = None, options: RunOptions | None = None
) -> dict:
    """Localize every frame of a sequence in a map; write the results folder; return the summary."""
    settings = settings or LocalizerSettings()
    opt = options or RunOptions()
    settings.check()
    if opt.mode not in ("global", "tracking"):
        raise InputError(f"mode {opt.mode!r}: expected 'global' or 'tracking'")
    if opt.particles is not None and opt.particles <= 0:
        raise InputError(f"particles must be > 0, got {opt.particles}")
    seq = load_sequence(seq_dir)
    if len(seq) == 0:
        raise InputError(f"{seq.root}: the sequence has no scans")
    mesh_map = MeshMap.load(map_dir)
    check_map_frame(seq, mesh_map)
    odo, odo_source = odometry_xyyaw(seq, opt.odometry_from_poses)
    first = int(opt.first_frame)
    if not 0 <= first < len(seq):
        raise InputError(f"first frame {first} out of range (the sequence has {len(seq)} frames)")
    last = len(seq) if opt.frames is None else min(len(seq), first + int(opt.frames))
    height, height_source = _sensor_height(seq, mesh_map, settings)

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(opt.seed)
    loc = MonteCarloLocalizer(
        mesh_map, settings, rng=rng, device=opt.device, threads=opt.threads, sensor_height_m=height
    )
    truth = xyyaw_of(seq.poses) if seq.poses is not None else None
    if opt.mode == "global":
        loc.spread(opt.particles)
    else:
        if opt.init_pose is not None:
            start = np.asarray(opt.init_pose, np.float64)
        elif truth is not None:
            start = truth[first]
        else:
            raise InputError(f"{seq.root}: tracking mode needs --init-pose (the sequence has no poses.txt)")
        loc.start_at(start, opt.particles)

    write_config(settings, out_dir / "config.yaml")  # feeds back in with --config

    period = _frame_period(seq)
    n = last - first
    est = np.zeros((n, 3))
    counts = np.zeros(n, np.int64)
    seconds = np.zeros(n)
    converged_flags = np.zeros(n, bool)
    snapshots: dict[str, np.ndarray] = {}
    snap_at = set(np.linspace(first, last - 1, 4).astype(int).tolist())
    state = dict(
        converged_frame=None if opt.mode == "global" else first,
        updates=0,
        resamples=0,
        recoveries=0,
        skipped_scans=0,
        unreadable_scans=0,
        recovery_frames=[],
        convergence_frames=[],
        vetoed_frames=[],
    )
    done = 0
    interrupted = False
    csv = (out_dir / "frames.csv").open("w")
    csv.write(FRAME_COLUMNS + "\n")
    bar = _Progress(n, opt.progress)
    clock = time.perf_counter()
    try:
        for k, i in enumerate(range(first, last)):
            delta = se2_between(odo[i - 1], odo[i]) if i > first else np.zeros(3)
            points = fire = None
            try:
                points = seq.scan(i)
                fire = seq.point_meta(i).get("time_s")
            except InputError:
                state["unreadable_scans"] += 1
            rp = tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None
            was_converged = loc.converged
            if (
                k == 0
                or i in snap_at
                or (not was_converged and opt.mode == "global" and k % 10 == 0 and len(snapshots) < 8)
            ):
                snapshots[f"frame_{i:06d}"] = loc.particles.copy()
            info = loc.step(delta, points, fire_time_s=fire, frame_period_s=period, roll_pitch=rp)
            est[k] = info.estimate
            counts[k] = info.particles
            seconds[k] = info.seconds
            converged_flags[k] = info.converged
            state["updates"] += info.updated
            state["resamples"] += info.resampled
            state["skipped_scans"] += info.skipped_scan
            if info.recovered:
                state["recoveries"] += 1
                state["recovery_frames"].append(i)
                state["converged_frame"] = None
            if info.converged_now:
                state["convergence_frames"].append(i)
            if info.vetoed:
                state["vetoed_frames"].append(i)
            if info.converged and state["converged_frame"] is None:
                state["converged_frame"] = i
                snapshots[f"frame_{i:06d}_converged"] = loc.particles.copy()
            csv.write(
                f"{i},{seq.times[i] if seq.times is not None else i * (period or 0.1):.6f},"
                f"{est[k, 0]:.4f},{est[k, 1]:.4f},{est[k, 2]:.6f},{info.particles},{int(info.converged)},"
                f"{int(info.updated)},{int(info.resampled)},{int(info.skipped_scan)},{int(info.recovered)},"
                f"{info.best_residual_m:.4f},{info.seconds:.4f},{info.hypotheses},{info.evidence_nats:.3f},"
                f"{info.inliers:.3f},{int(info.vetoed)}\n"
            )
            csv.flush()
            done = k + 1
            bar.update(info)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        csv.close()
        bar.close()
    wall = time.perf_counter() - clock
    est, counts, seconds, converged_flags = est[:done], counts[:done], seconds[:done], converged_flags[:done]
    poses = _poses_4x4(est, loc, seq, first)
    Tr_inv = np.linalg.inv(seq.calib_Tr)
    if done:
        write_poses_txt(out_dir / "estimate_kitti.txt", poses @ Tr_inv)
        times = (
            seq.times[first : first + done] if seq.times is not None else np.arange(done) * (period or 0.1)
        )
        atomic_write(out_dir / "estimate_tum.txt", "\n".join(poses_to_tum(poses, times)) + "\n")
    if snapshots:
        atomic_write(out_dir / "particles.npz", lambda fh: np.savez(fh, **snapshots))
    after = converged_flags & (counts <= settings.particles.converged_count)
    before = ~converged_flags
    summary = {
        "sequence": str(seq.root),
        "map": str(map_dir),
        "mode": opt.mode,
        "device": loc.caster.device,
        "seed": opt.seed,
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in opt.__dict__.items()},
        "first_frame": first,
        "frames": done,
        "frames_requested": n,
        "interrupted": interrupted,
        "converged_frame": state["converged_frame"],
        "updates": state["updates"],
        "resamples": state["resamples"],
        "recoveries": state["recoveries"],
        "recovery_frames": state["recovery_frames"],
        "convergence_frames": state["convergence_frames"],
        "vetoed_alarms": loc.vetoed_alarms,
        "vetoed_frames": state["vetoed_frames"],
        "skipped_scans": state["skipped_scans"],
        "unreadable_scans": state["unreadable_scans"],
        "odometry_source": odo_source,
        "sensor_height_m": height,
        "sensor_height_source": height_source,
        "particles_initial": int(counts[0]) if done else None,
        "seconds_total": wall,
        "seconds_per_frame_before_convergence_median": _median(seconds[before]),
        "seconds_per_frame_before_convergence_max": float(seconds[before].max()) if before.any() else None,
        "seconds_per_frame_after_convergence_median": _median(seconds[after]),
        "hz_after_convergence": (1.0 / _median(seconds[after]))
        if after.any() and _median(seconds[after])
        else None,
        "calib_Tr": seq.calib_Tr.tolist(),
    }
    if loc.prior is not None:
        summary["place_prior"] = {
            "source": loc.prior_source,
            "cells": len(loc.prior.xy),
            "megabytes": loc.prior.nbytes / 1e6,
            "build_seconds": loc.prior.build_s,
        }
    if truth is not None and done:
        conv = state["converged_frame"]
        metrics = localization_metrics(
            est,
            truth[first : first + done],
            None if conv is None else conv - first,
            convergence_frames=[f - first for f in state["convergence_frames"]],
            recovery_frames=[f - first for f in state["recovery_frames"]],
        )
        shift_event_frames(metrics, first)
        metrics["first_frame"] = first
        atomic_write(out_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        summary["metrics"] = {
            k: metrics.get(k)
            for k in (
                "success",
                "location_rmse_m",
                "yaw_rmse_deg",
                "converged_frame",
                "wrong_convergences_count",
                "wrong_convergences_uncaught",
                "false_alarms_count",
            )
        }
    atomic_write(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    if opt.plots and done:
        from rangemcl.plots import plot_localization

        plot_localization(
            out_dir,
            mesh_map,
            est,
            truth[first : first + done] if truth is not None else None,
            first,
            state["converged_frame"],
            snapshots,
        )
    if interrupted:
        raise KeyboardInterrupt
    return summary


def _median(x: np.ndarray) -> float | None:
    return float(np.median(x)) if len(x) else None


def _poses_4x4(est: np.ndarray, loc: MonteCarloLocalizer, seq: Sequence, first: int) -> np.ndarray:
    """Estimated LiDAR poses: x, y, yaw from the filter, z from the map's ground plus the mounting
    height, roll and pitch from the IMU (level without one)."""
    out = np.tile(np.eye(4), (len(est), 1, 1))
    if len(est) == 0:
        return out
    out[:, :2, 3] = est[:, :2]
    out[:, 2, 3] = loc.sensor_z(est[:, :2])
    for k, yaw in enumerate(est[:, 2]):
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        if seq.imu_roll_pitch is not None:
            R = R @ rotation_roll_pitch(*seq.imu_roll_pitch[first + k])
        out[k, :3, :3] = R
    return out


class _Progress:
    """A rich progress bar with frame rate, particle count and convergence (nothing when disabled)."""

    def __init__(self, total: int, enabled: bool):
        self.p = None
        if not enabled:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.p = Progress(
            TextColumn("localize"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[rate]:>6.1f} Hz"),
            TextColumn("{task.fields[n]:>6d} particles"),
            TextColumn("{task.fields[state]}"),
            TimeRemainingColumn(),
        )
        self.p.start()
        self.task = self.p.add_task("localize", total=total, rate=0.0, n=0, state="")
        self.recent: list[float] = []

    def update(self, info) -> None:
        if self.p is None:
            return
        self.recent = [*self.recent, info.seconds][-20:]
        rate = 1.0 / max(np.mean(self.recent), 1e-6)
        state = "converged" if info.converged else "global search"
        self.p.update(self.task, advance=1, rate=rate, n=info.particles, state=state)

    def close(self) -> None:
        if self.p is not None:
            self.p.stop()
