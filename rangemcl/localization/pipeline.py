"""``rangemcl localize``: run the Monte Carlo localizer over a recorded sequence and write the results.

A results folder holds::

    config.yaml          the effective localizer settings (give it back with --config)
    frames.csv           one line per frame, appended as the run goes (frame, time, estimate, particle
                         count, convergence, update/resampling/recovery flags, residual, seconds, search
                         and lost-detection signals, refinement, odometry calibration)
    estimate_kitti.txt   the estimated poses, 12 numbers per line, in the convention of the sequence's
                         poses.txt (so ``evo_ape kitti poses.txt estimate_kitti.txt`` compares them)
    estimate_tum.txt     the estimated LiDAR poses as TUM lines (time x y z qx qy qz qw)
    summary.json         convergence frame, counts, timings, odometry source and calibration, device, seed
    odometry_kiss_icp.txt  with ``--odometry kiss-icp``: the LiDAR poses kiss-icp gave (reused by --resume)
    metrics.json         the paper's metrics (:mod:`rangemcl.evaluation.metrics`) when the sequence has poses
    particles.npz        particle clouds at a few frames
    trajectory.png, error.png, particles.png
    .resume/state.npz    while running and after an interruption: the filter's whole state every 10
                         frames (:mod:`rangemcl.common.checkpoint`); removed when the run finishes

The estimate is written for every frame; before convergence it is the (meaningless) mean of a spread
cloud, and the metrics count from the convergence frame on. An interrupted run (Ctrl-C, SIGTERM) writes
everything computed up to the interruption, marked ``"interrupted": true``; one killed outright (SIGKILL,
a power cut) leaves ``frames.csv`` up to its last frame. Either is continued with ``resume``: the state of
the last checkpoint is restored and the frames after it are localized again, so the results are those
of an uninterrupted run with the same seed, byte for byte.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from rangemcl import __version__
from rangemcl.common.atomic import atomic_write, savez_stable
from rangemcl.common.checkpoint import restore_state, save_state
from rangemcl.config import write_config
from rangemcl.datasets.kitti import Sequence, poses_to_tum, write_poses_txt
from rangemcl.datasets.sources import open_source
from rangemcl.errors import InputError
from rangemcl.evaluation.metrics import localization_metrics, shift_event_frames
from rangemcl.localization import LocalizerSettings, MonteCarloLocalizer, build_localizer, prepare_rays
from rangemcl.maps.meshmap import MeshMap
from rangemcl.se2 import rotation_roll_pitch, se2_between, xyyaw_of
from rangemcl.viz.rerun import RunViewer, check_rrd_path, rerun_module

FRAME_COLUMNS = (
    "frame,time_s,x,y,yaw,particles,converged,updated,resampled,skipped_scan,recovered,"
    "best_residual_m,seconds,hypotheses,evidence_nats,inliers,vetoed,refined,refine_shift_m,"
    "odometry_scale,gyro_bias_deg_s,map_tiles,map_left_out,map_coarse,map_mb,map_load_ms,late"
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
    odometry: str | None = None  # None: the sequence's own; "kiss-icp"; "poses:FILE" (KITTI or TUM)
    bag: Any = None  # rangemcl.datasets.rosbag.BagOptions for a bag (topics, mounting, point times)
    viz: bool = False  # --viz: stream the run to the rerun viewer
    viz_out: str | None = None  # --viz-out FILE: save the run as a rerun .rrd
    plots: bool = True
    progress: bool = False
    resume: bool = False  # continue the interrupted run in the results folder (its checkpoint)
    checkpoint_every: int = 10  # frames between two checkpoints of the filter's state
    map_memory_mb: float | None = None  # --map-memory: hold only the tiles near the particles, within this
    # --realtime: replay at the sensor's pace; a scan that arrives (by its stamp) while the localizer is still
    # busy with an earlier one is dropped (prediction only, its odometry carried to the next), as on a car
    realtime: bool = False


KISS_ODOMETRY = "odometry_kiss_icp.txt"  # --odometry kiss-icp: the LiDAR poses it gave, in the results
CHECKPOINT = Path(".resume") / "state.npz"  # the filter's state at the last checkpoint, in the results folder


def odometry_xyyaw(seq: Sequence, from_poses: bool, source: str | None = None) -> tuple[np.ndarray, str]:
    """The odometry as ``(N, 3)`` x, y, yaw and where it came from: the sequence's own (``odometry.txt``,
    a bag's odometry topic), or ``source``: ``kiss-icp`` (LiDAR odometry computed from the scans) or
    ``poses:FILE`` (LiDAR poses, KITTI one line per scan or TUM by time)."""
    if source is not None:
        if source == "kiss-icp":
            from rangemcl.datasets.lidar_odometry import kiss_icp_odometry

            return xyyaw_of(kiss_icp_odometry(seq)), "kiss-icp (LiDAR odometry from the scans)"
        if source.startswith("poses:") and len(source) > len("poses:"):
            from rangemcl.datasets.rosbag import poses_at_scans

            path = Path(source[len("poses:") :])
            if seq.times is None:
                raise InputError(f"{seq.root}: --odometry {source}: the sequence has no times to match")
            return xyyaw_of(poses_at_scans(path, seq.times)), f"{path} (--odometry poses:FILE)"
        raise InputError(f"--odometry {source!r}: expected kiss-icp or poses:FILE")
    if seq.odometry is not None:
        return xyyaw_of(seq.odometry), getattr(seq, "odometry_source", "odometry.txt")
    if from_poses and seq.poses is not None:
        return xyyaw_of(seq.poses), "poses.txt (derived because the sequence has no odometry.txt)"
    hint = " (or pass --odometry-from-poses to derive it from poses.txt)" if seq.poses is not None else ""
    if getattr(seq, "topic", None) is not None:  # a bag
        raise InputError(
            f"{seq.root}: no odometry topic (give --odom-topic, --odometry kiss-icp or --odometry poses:FILE)"
        )
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


def frame_period(seq: Sequence) -> float | None:
    if seq.times is not None and len(seq.times) > 1:
        d = np.diff(seq.times)
        d = d[d > 0]
        if len(d):
            return float(np.median(d))
    return None


def frame_rays(seq: Sequence, i: int, observation, rng: np.random.Generator, odometry: np.ndarray):
    """Frame ``i``'s rays as the localizer draws them for an update (:func:`prepare_rays` with the
    observation settings): de-skewed with the frame's motion in ``odometry`` (``(N, 3)`` x, y, yaw, as
    :func:`odometry_xyyaw` gives it), levelled by the IMU's roll and pitch where the sequence has them.
    For tools that score a recorded frame outside a run."""
    return prepare_rays(
        seq.scan(i),
        observation,
        rng,
        fire_time_s=seq.point_meta(i).get("time_s"),
        frame_period_s=frame_period(seq),
        frame_motion=se2_between(odometry[i - 1], odometry[i]) if i else np.zeros(3),
        roll_pitch=tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None,
    )


def resolve_sensor_height(seq: Sequence, mesh_map: MeshMap, settings: LocalizerSettings) -> tuple[float, str]:
    if settings.sensor_height_m is not None:
        return float(settings.sensor_height_m), "settings"
    sensor = seq.meta.get("sensor") if isinstance(seq.meta, dict) else None
    if isinstance(sensor, dict):
        mount = sensor.get("mount")
        if isinstance(mount, dict) and isinstance(mount.get("xyz_m"), list) and len(mount["xyz_m"]) == 3:
            z = mount["xyz_m"][2]
            if isinstance(z, bool) or not isinstance(z, int | float) or not math.isfinite(z):
                raise InputError(f"{seq.root}/meta.yaml: sensor.mount.xyz_m[2] must be a number, got {z!r}")
            return float(z), "the sequence's sensor mount"
    if "sensor_height_m" in mesh_map.meta:
        return float(mesh_map.meta["sensor_height_m"]), "the map's metadata"
    return 1.73, "default (KITTI)"


def localize_sequence(
    seq_dir, map_dir, out_dir, settings: LocalizerSettings | None = None, options: RunOptions | None = None
) -> dict:
    """Localize every frame of a sequence in a map; write the results folder; return the summary."""
    return LocalizationPipeline(seq_dir, map_dir, out_dir, settings, options).run()


@dataclass
class FrameLog:
    """What the filter did, frame by frame (the first ``done`` rows are filled)."""

    estimate: np.ndarray  # (n, 3)
    particles: np.ndarray  # (n,)
    seconds: np.ndarray  # (n,)
    converged: np.ndarray  # (n,) bool
    scanned: np.ndarray  # (n,) bool: the frame's scan had valid points for the filter to weigh against
    updated: np.ndarray  # (n,) bool: the filter weighed the frame's scan (an update)
    late: np.ndarray  # (n,) bool: --realtime dropped the frame's scan (the localizer was busy)
    done: int = 0
    interrupted: bool = False
    wall_s: float = 0.0

    @classmethod
    def empty(cls, n: int) -> FrameLog:
        flags = [np.zeros(n, bool) for _ in range(4)]  # converged, scanned, updated, late
        return cls(np.zeros((n, 3)), np.zeros(n, np.int64), np.zeros(n), *flags)

    def trim(self) -> None:
        k = self.done
        self.estimate, self.particles = self.estimate[:k], self.particles[:k]
        self.seconds, self.converged = self.seconds[:k], self.converged[:k]
        self.scanned, self.updated, self.late = self.scanned[:k], self.updated[:k], self.late[:k]


class LocalizationPipeline:
    """``rangemcl localize`` as steps: :meth:`run` reads as the table of contents."""

    def __init__(self, seq_dir, map_dir, out_dir, settings=None, options=None):
        self.seq_dir, self.map_dir, self.out_dir = seq_dir, map_dir, Path(out_dir)
        self.settings = settings or LocalizerSettings()
        self.opt = options or RunOptions()
        self.snapshots: dict[str, np.ndarray] = {}
        self.events = dict(
            converged_frame=None,  # tracking: the first frame (set by load)
            updates=0,
            resamples=0,
            recoveries=0,
            skipped_scans=0,
            late_scans=0,  # --realtime: scans dropped because the localizer was busy
            unreadable_scans=0,
            nan_points_dropped=0,  # points of a scan that are not finite (NaN, inf): the filter drops them
            scans_with_nan_points=0,
            recovery_frames=[],
            convergence_frames=[],
            vetoed_frames=[],
        )
        self.metrics: dict | None = None
        self.viz = RunViewer.disabled()

    def run(self) -> dict:
        t0 = time.perf_counter()
        self.load()  # sequence, map, odometry, frame range, sensor height: every check before any output
        if self.opt.resume:
            self.check_resume()  # the checkpoint fits this run: before anything is built or written
        t1 = time.perf_counter()
        self.start_filter()  # the localizer, spread (global) or started at the initial pose (tracking)
        self.resume_from = self.restore() if self.opt.resume else 0  # the checkpoint's state
        t2 = time.perf_counter()
        self.warm_up()  # the place priors loaded before the first frame, not during it
        t3 = time.perf_counter()
        self.startup = {"seconds": t3 - t0, "load_s": t1 - t0, "filter_s": t2 - t1, "prior_s": t3 - t2}
        self.filter_frames()  # one step per frame, frames.csv appended as it goes
        self.write_estimates()  # estimate_kitti.txt, estimate_tum.txt, particles.npz
        self.evaluate()  # metrics.json against the sequence's poses
        summary = self.write_summary()  # summary.json
        self.plot()  # the PNGs
        if self.log.interrupted:
            raise KeyboardInterrupt
        shutil.rmtree(self.out_dir / CHECKPOINT.parent, ignore_errors=True)
        return summary

    # --- steps -------------------------------------------------------------------------------------------

    def load(self) -> None:
        opt, settings = self.opt, self.settings
        settings.check()
        if opt.mode not in ("global", "tracking"):
            raise InputError(f"mode {opt.mode!r}: expected 'global' or 'tracking'")
        if opt.particles is not None and opt.particles <= 0:
            raise InputError(f"particles must be > 0, got {opt.particles}")
        if opt.frames is not None and opt.frames <= 0:
            raise InputError(f"frames must be > 0, got {opt.frames}")
        if opt.first_frame < 0:
            raise InputError(f"first frame must be >= 0, got {opt.first_frame}")
        if opt.threads is not None and opt.threads <= 0:
            raise InputError(f"threads must be > 0, got {opt.threads}")
        if opt.init_pose is not None and opt.mode != "tracking":
            raise InputError(
                "an initial pose is for tracking mode (--mode tracking); global mode searches the map"
            )
        self.seq = seq = open_source(self.seq_dir, bag_options=opt.bag)
        if len(seq) == 0:
            raise InputError(f"{seq.root}: the sequence has no scans")
        from rangemcl.maps.view import open_map  # whole, or the tiles near the particles within a budget

        memory = opt.map_memory_mb if opt.map_memory_mb is not None else settings.map_memory_mb
        self.map, self.caster = open_map(self.map_dir, memory, device=opt.device, threads=opt.threads)
        check_map_frame(seq, self.map)
        self.kiss_poses = None
        if opt.odometry == "kiss-icp":  # computed once: a resumed run reads what the run wrote
            cached = self.out_dir / KISS_ODOMETRY
            if opt.resume and cached.is_file():
                from rangemcl.datasets.kitti import read_poses_txt

                self.kiss_poses = read_poses_txt(cached)
                if len(self.kiss_poses) != len(seq):
                    raise InputError(f"{cached}: {len(self.kiss_poses)} poses for {len(seq)} scans")
            else:
                from rangemcl.datasets.lidar_odometry import kiss_icp_odometry

                self.kiss_poses = kiss_icp_odometry(seq, progress=opt.progress)
            self.odo, self.odo_source = (
                xyyaw_of(self.kiss_poses),
                f"kiss-icp (LiDAR odometry, {KISS_ODOMETRY})",
            )
        else:
            self.odo, self.odo_source = odometry_xyyaw(seq, opt.odometry_from_poses, opt.odometry)
        self.first = int(opt.first_frame)
        if not 0 <= self.first < len(seq):
            raise InputError(f"first frame {self.first} out of range (the sequence has {len(seq)} frames)")
        self.last = len(seq) if opt.frames is None else min(len(seq), self.first + int(opt.frames))
        self.height, self.height_source = resolve_sensor_height(seq, self.map, settings)
        self.truth = xyyaw_of(seq.poses) if seq.poses is not None else None
        if self.opt.mode == "tracking":
            self.events["converged_frame"] = self.first
        if opt.viz or opt.viz_out:  # the extra and the file's folder, before any work
            rerun_module()
        if opt.viz_out:
            check_rrd_path(opt.viz_out)

    def start_filter(self) -> None:
        opt, seq = self.opt, self.seq
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.loc = loc = build_localizer(
            self.map,
            self.settings,
            rng=np.random.default_rng(opt.seed),
            device=opt.device,
            threads=opt.threads,
            sensor_height_m=self.height,
            caster=self.caster,
        )
        loc.prior_notify = lambda message: print(f"rangemcl: {message}", file=sys.stderr)
        loc.prior_fallback_dir = self.out_dir  # a map folder that is not writable: beside the results
        if opt.mode == "global":
            loc.spread(opt.particles)
        else:
            if opt.init_pose is not None:
                start = np.asarray(opt.init_pose, np.float64)
            elif self.truth is not None:
                start = self.truth[self.first]
            else:
                raise InputError(
                    f"{seq.root}: tracking mode needs --init-pose (the sequence has no poses.txt)"
                )
            loc.start_at(start, opt.particles)
        if not opt.resume:
            write_config(self.settings, self.out_dir / "config.yaml")  # feeds back in with --config
            if self.kiss_poses is not None:
                write_poses_txt(self.out_dir / KISS_ODOMETRY, self.kiss_poses)
        self.log = FrameLog.empty(self.last - self.first)
        if opt.viz or opt.viz_out:
            self.viz = RunViewer.open(f"localize {Path(seq.root).name}", out_rrd=opt.viz_out, spawn=opt.viz)
            if isinstance(self.map, MeshMap):  # a map within a budget is not sent whole
                self.viz.log_mesh_map(self.map)

    def _first_fix_seconds(self) -> float | None:
        m = self.metrics
        if not m or m.get("first_fix_frame") is None:
            return None
        return float(self.log.seconds[: m["first_fix_frame"] - self.first + 1].sum())

    def warm_up(self) -> None:
        """The filter's start-up work done before the first frame (:meth:`MonteCarloLocalizer.warm_up`),
        with the first frame's scan (an unreadable one: the beam prior is decided at the first update)."""
        if self.resume_from >= self.last - self.first:
            return
        i = self.first + self.resume_from
        try:
            points, intensity = self.seq.scan_with_intensity(i)
        except InputError:
            points = intensity = None
        rp = tuple(self.seq.imu_roll_pitch[i]) if self.seq.imu_roll_pitch is not None else None
        self.loc.warm_up(points, rp, intensity)

    def fingerprint(self) -> dict:
        """What decides a run's results: a resumed run must have the same."""
        opt = self.opt
        fp = {
            "rangemcl_version": __version__,  # the checkpoint's layout is the filter's of this version
            "sequence": str(Path(self.seq_dir).resolve()),
            "map": str(Path(self.map_dir).resolve()),
            "settings": asdict(self.settings),
            "options": {
                k: getattr(opt, k)
                for k in ("mode", "particles", "device", "seed", "first_frame", "frames", "init_pose")
            }
            | {"odometry_from_poses": opt.odometry_from_poses, "odometry": opt.odometry}
            | ({"bag": asdict(opt.bag)} if opt.bag is not None else {})
            | ({"map_memory_mb": opt.map_memory_mb} if opt.map_memory_mb is not None else {})
            | ({"realtime": True} if opt.realtime else {}),
        }
        return json.loads(json.dumps(fp))

    def checkpoint_parts(self) -> dict:
        return {"loc": self.loc, "log": self.log, "events": self.events, "snapshots": self.snapshots}

    def save_checkpoint(self, elapsed_s: float) -> None:
        (self.out_dir / CHECKPOINT.parent).mkdir(exist_ok=True)
        extra = {"fingerprint": self.fingerprint(), "done": self.log.done, "elapsed_s": elapsed_s}
        save_state(self.out_dir / CHECKPOINT, self.checkpoint_parts(), extra)

    def check_resume(self) -> None:
        """Refuse, in one line and before any work, a folder without a checkpoint that fits this run."""
        path = self.out_dir / CHECKPOINT
        summary = self.out_dir / "summary.json"
        if not path.is_file():
            try:
                finished = not json.loads(summary.read_text()).get("interrupted", True)
            except (OSError, ValueError, AttributeError):
                finished = False
            if finished:
                raise InputError(
                    f"{self.out_dir}: holds a finished run, nothing to resume (--overwrite runs again)"
                )
            raise InputError(
                f"{self.out_dir}: no checkpoint to resume from ({CHECKPOINT} missing: the run was stopped "
                "before its first checkpoint, or by an earlier version); run it again with --overwrite"
            )
        from rangemcl.common.checkpoint import read_state

        _tree, extra, _arrays = read_state(path)
        saved = extra.get("fingerprint", {}) if isinstance(extra, dict) else {}
        if saved.get("rangemcl_version") != __version__:
            raise InputError(
                f"{self.out_dir}: its checkpoint was written by rangemcl "
                f"{saved.get('rangemcl_version') or 'before 0.17.1'}, this is {__version__}: resume it with "
                "that version, or --overwrite"
            )
        diff = _differences(saved, self.fingerprint())
        if diff:
            raise InputError(
                f"{self.out_dir}: was started with other inputs or settings ({', '.join(diff[:4])}); "
                "resume with the same command, or --overwrite"
            )

    def restore(self) -> int:
        """Put the filter, the frame log and the counts back to the folder's last checkpoint (checked by
        :meth:`check_resume`); return the number of frames it holds (the frames after it are localized
        again)."""
        path = self.out_dir / CHECKPOINT
        from rangemcl.common.checkpoint import read_state

        _tree, extra, _arrays = read_state(path)
        restore_state(path, self.checkpoint_parts())
        self.resumed_elapsed_s = float(extra.get("elapsed_s", 0.0))
        self.events.setdefault("resumed_at_frames", []).append(self.first + self.log.done)
        return self.log.done

    def filter_frames(self) -> None:
        seq, loc, first, last, ev, log = self.seq, self.loc, self.first, self.last, self.events, self.log
        period = self.period = frame_period(seq)
        snap_at = set(np.linspace(first, last - 1, 4).astype(int).tolist())
        k0 = self.resume_from
        csv = self._open_frames_csv(k0)
        bar = _Progress(last - first, self.opt.progress)
        every = max(1, int(self.opt.checkpoint_every))
        clock = time.perf_counter() - getattr(self, "resumed_elapsed_s", 0.0)
        if not k0:
            self.save_checkpoint(0.0)  # from the first frame on, a run can be resumed
        busy_until = self._busy_until(k0)  # --realtime: the sensor time until which the localizer works
        try:
            for k, i in enumerate(range(first + k0, last), start=k0):
                delta = se2_between(self.odo[i - 1], self.odo[i]) if i > first else np.zeros(3)
                points = fire = intensity = None
                try:
                    points, intensity = seq.scan_with_intensity(i)
                    fire = seq.point_meta(i).get("time_s")
                except InputError as err:
                    ev["unreadable_scans"] += 1
                    ev.setdefault("unreadable_files", []).append(str(err))
                    print(f"rangemcl: warning: {err} (frame {i}: prediction only)", file=sys.stderr)
                rp = tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None
                searching = not loc.converged and self.opt.mode == "global"
                if k == 0 or i in snap_at or (searching and k % 10 == 0 and len(self.snapshots) < 8):
                    self.snapshots[f"frame_{i:06d}"] = loc.particles.copy()
                dt = None
                if i > first:
                    dt = float(seq.times[i] - seq.times[i - 1]) if seq.times is not None else period
                late = self.opt.realtime and self._stamp(i) < busy_until
                info = loc.step(
                    delta,
                    None if late else points,
                    fire_time_s=fire,
                    frame_period_s=period,
                    roll_pitch=rp,
                    dt_s=dt,
                    intensity=None if late else intensity,
                )
                if late:  # not a scan without points: one the localizer had no time for
                    info = replace(info, skipped_scan=False)
                    ev["late_scans"] += 1
                else:
                    busy_until = self._stamp(i) + info.seconds
                log.late[k] = late
                self._record(k, i, info)
                log.scanned[k] = not late and self._count_points(points) and not info.skipped_scan
                if self.viz.enabled:
                    self.viz.frame(
                        i,
                        float(seq.times[i]) if seq.times is not None else i * (period or 0.1),
                        scan_sensor=points,
                        estimate=_poses_4x4(info.estimate[None], loc, seq, i)[0],
                        truth=None if seq.poses is None else seq.poses[i],
                        particles=loc.particles,
                        weights=loc.weights,
                        particle_z=loc.sensor_z(loc.particles[:, :2]),
                        converged=info.converged,
                    )
                csv.write(self._csv_line(i, info, late))
                csv.flush()
                log.done = k + 1
                if log.done % every == 0 and log.done < last - first:
                    self.save_checkpoint(time.perf_counter() - clock)
                bar.update(info)
        except KeyboardInterrupt:
            log.interrupted = True
        finally:
            csv.close()
            bar.close()
            self.viz.close()
            if not isinstance(self.map, MeshMap):  # a map within a budget: stop its tile loader
                self.map.close()
        log.wall_s = time.perf_counter() - clock
        log.trim()

    def _open_frames_csv(self, k0: int):
        """frames.csv for appending: new, or (resuming) cut back to the header and the first ``k0`` frames."""
        path = self.out_dir / "frames.csv"
        if not k0:
            csv = path.open("w")
            csv.write(FRAME_COLUMNS + "\n")
            return csv
        try:
            lines = path.read_text().splitlines(keepends=True)
        except OSError as err:
            raise InputError(f"{path}: cannot resume without it ({err.strerror or err})") from None
        if not lines or lines[0].strip() != FRAME_COLUMNS or len(lines) < 1 + k0:
            raise InputError(
                f"{path}: does not hold the {k0} frames of the checkpoint; run again with --overwrite"
            )
        atomic_write(path, "".join(lines[: 1 + k0]))
        return path.open("a")

    def write_estimates(self) -> None:
        log, seq, first = self.log, self.seq, self.first
        if log.done:
            poses = _poses_4x4(log.estimate, self.loc, seq, first)
            write_poses_txt(self.out_dir / "estimate_kitti.txt", poses @ np.linalg.inv(seq.calib_Tr))
            times = (
                seq.times[first : first + log.done]
                if seq.times is not None
                else np.arange(log.done) * (self.period or 0.1)
            )
            atomic_write(self.out_dir / "estimate_tum.txt", "\n".join(poses_to_tum(poses, times)) + "\n")
        if self.snapshots:
            atomic_write(self.out_dir / "particles.npz", lambda fh: savez_stable(fh, **self.snapshots))

    def evaluate(self) -> None:
        if self.truth is None or not self.log.done:
            return
        first, ev = self.first, self.events
        conv = ev["converged_frame"]
        metrics = localization_metrics(
            self.log.estimate,
            self.truth[first : first + self.log.done],
            None if conv is None else conv - first,
            convergence_frames=[f - first for f in ev["convergence_frames"]],
            recovery_frames=[f - first for f in ev["recovery_frames"]],
            frames_with_scan=int(self.log.scanned.sum()),
            updates=self.log.updated,
        )
        shift_event_frames(metrics, first)
        metrics["first_frame"] = first
        atomic_write(self.out_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        self.metrics = metrics

    def write_summary(self) -> dict:
        log, ev, seq, loc, opt = self.log, self.events, self.seq, self.loc, self.opt
        after = log.converged & (log.particles <= self.settings.particles.converged_count)
        before = ~log.converged
        summary = {
            "rangemcl_version": __version__,
            "sequence": str(seq.root),
            "map": str(self.map_dir),
            "mode": opt.mode,
            "device": loc.caster.device,
            "seed": opt.seed,
            "options": asdict(opt),  # nested dataclasses (a bag's BagOptions) too; tuples become lists
            "first_frame": self.first,
            "frames": log.done,
            "frames_requested": self.last - self.first,
            "interrupted": log.interrupted,
            "resumed_at_frames": ev.get("resumed_at_frames", []),
            "converged_frame": ev["converged_frame"],
            "updates": ev["updates"],
            "resamples": ev["resamples"],
            "recoveries": ev["recoveries"],
            "recovery_frames": ev["recovery_frames"],
            "convergence_frames": ev["convergence_frames"],
            "vetoed_alarms": loc.vetoed_alarms,
            "vetoed_frames": ev["vetoed_frames"],
            "refinements": loc.refinements,
            "refused_refinements": loc.refused_refinements,
            "odometry_calibration": None
            if loc.calibrator is None
            else {
                "scale": loc.calibrator.scale,
                "gyro_bias_deg_s": math.degrees(loc.calibrator.gyro_bias),
                "observed_distance_m": loc.calibrator.distance_m,
                "intervals": loc.calibrator.observed,
                "intervals_left_out": loc.calibrator.rejected,
            },
            "skipped_scans": ev["skipped_scans"],
            "late_scans": ev.get("late_scans", 0),
            "unreadable_scans": ev["unreadable_scans"],
            "unreadable_scan_errors": ev.get("unreadable_files", [])[:100],
            "nan_points_dropped": ev.get("nan_points_dropped", 0),
            "scans_with_nan_points": ev.get("scans_with_nan_points", 0),
            "frames_localized_from_scans": int(log.scanned.sum()),  # its scan had valid points to weigh
            "odometry_source": self.odo_source,
            "sensor_height_m": self.height,
            "sensor_height_source": self.height_source,
            "particles_initial": int(log.particles[0]) if log.done else None,
            "seconds_total": log.wall_s,
            # the first correct fix's compute, from the first frame through its frame (metrics.json has
            # the frame and the metres driven: its bytes do not depend on the machine's speed)
            "first_fix_seconds": self._first_fix_seconds(),
            # before the first frame: the sequence and map opened, the filter built, its priors loaded
            "startup_seconds": self.startup["seconds"],
            "startup": self.startup,
            "seconds_per_frame_before_convergence_median": _median(log.seconds[before]),
            "seconds_per_frame_before_convergence_max": float(log.seconds[before].max())
            if before.any()
            else None,
            "seconds_per_frame_after_convergence_median": _median(log.seconds[after]),
            "hz_after_convergence": (1.0 / _median(log.seconds[after]))
            if after.any() and _median(log.seconds[after])
            else None,
            "calib_Tr": seq.calib_Tr.tolist(),
            "calib_source": seq.calib_source,
        }
        if self.map.budgeted:
            summary["map_memory"] = self.map.summary()
        if loc.prior is not None:
            summary["place_prior"] = {
                "source": loc.prior_source,
                "cells": len(loc.prior.xy),
                "megabytes": loc.prior.nbytes / 1e6,
                "build_seconds": loc.prior.build_s,
            }
        if loc.beam_prior is not None:  # a sensor that sees nothing above the parked cars (the MQ-8)
            summary["beam_prior"] = {
                "source": loc.beam_prior_source,
                "beam_deg": loc.beam_prior.params.beam_deg,
                "megabytes": loc.beam_prior.nbytes / 1e6,
                "build_seconds": loc.beam_prior.build_s,
            }
        if self.metrics is not None:
            summary["metrics"] = {
                k: self.metrics.get(k)
                for k in (
                    "success",
                    "location_rmse_m",
                    "yaw_rmse_deg",
                    "converged_frame",
                    "wrong_convergences_count",
                    "wrong_convergences_uncaught",
                    "false_alarms_count",
                    "frames_localized_from_scans",
                    "frames_without_scan",
                    "failure_reason",
                )
            }
        atomic_write(self.out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
        return summary

    def plot(self) -> None:
        if not (self.opt.plots and self.log.done):
            return
        from rangemcl.viz.plots import plot_localization

        first = self.first
        plot_localization(
            self.out_dir,
            self.map,
            self.log.estimate,
            self.truth[first : first + self.log.done] if self.truth is not None else None,
            first,
            self.events["converged_frame"],
            self.snapshots,
        )

    # --- per frame ---------------------------------------------------------------------------------------

    def _record(self, k: int, i: int, info) -> None:
        log, ev = self.log, self.events
        log.estimate[k] = info.estimate
        log.particles[k] = info.particles
        log.seconds[k] = info.seconds
        log.converged[k] = info.converged
        log.updated[k] = info.updated
        ev["updates"] += info.updated
        ev["resamples"] += info.resampled
        ev["skipped_scans"] += info.skipped_scan
        if info.recovered:
            ev["recoveries"] += 1
            ev["recovery_frames"].append(i)
            ev["converged_frame"] = None
        if info.converged_now:
            ev["convergence_frames"].append(i)
        if info.vetoed:
            ev["vetoed_frames"].append(i)
        if info.converged and ev["converged_frame"] is None:
            ev["converged_frame"] = i
            self.snapshots[f"frame_{i:06d}_converged"] = self.loc.particles.copy()

    def _count_points(self, points) -> bool:
        """Count the points of a frame's scan that are not finite (NaN, inf: the filter drops them) in the
        summary; whether any finite point is left (None, an unreadable scan: none)."""
        if points is None or not len(points):
            return False
        finite = np.isfinite(np.asarray(points).reshape(len(points), -1)).all(axis=1)
        dropped = len(finite) - int(np.count_nonzero(finite))
        if dropped:
            ev = self.events
            ev["nan_points_dropped"] = ev.get("nan_points_dropped", 0) + dropped
            ev["scans_with_nan_points"] = ev.get("scans_with_nan_points", 0) + 1
        return dropped < len(finite)

    def _stamp(self, i: int) -> float:
        """Frame ``i``'s time stamp in s (its index times the frame period where the sequence has none)."""
        seq = self.seq
        return float(seq.times[i]) if seq.times is not None else i * (self.period or 0.1)

    def _busy_until(self, k0: int) -> float:
        """``--realtime``: the sensor time until which the localizer works on the last scan it took before
        frame ``k0`` (its stamp plus its compute; a resumed run reads it from the frame log)."""
        taken = np.flatnonzero(~self.log.late[:k0])
        if not self.opt.realtime or len(taken) == 0:
            return -math.inf
        k = int(taken[-1])
        return self._stamp(self.first + k) + float(self.log.seconds[k])

    def _csv_line(self, i: int, info, late: bool = False) -> str:
        e = info.estimate
        t = self._stamp(i)
        return (
            f"{i},{t:.6f},{e[0]:.4f},{e[1]:.4f},{e[2]:.6f},{info.particles},{int(info.converged)},"
            f"{int(info.updated)},{int(info.resampled)},{int(info.skipped_scan)},{int(info.recovered)},"
            f"{info.best_residual_m:.4f},{info.seconds:.4f},{info.hypotheses},{info.evidence_nats:.3f},"
            f"{info.inliers:.3f},{int(info.vetoed)},{info.refined},{info.refine_shift_m:.4f},"
            f"{info.odometry_scale:.5f},{info.gyro_bias_deg_s:.4f},{info.map_tiles},{info.map_left_out},{info.map_coarse},"
            f"{info.map_mb:.2f},{info.map_load_ms:.1f},{int(late)}\n"
        )


def _differences(a, b, path: str = "") -> list[str]:
    """The keys (dotted) in which two JSON trees differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _differences(a.get(k), b.get(k), f"{path}.{k}" if path else k)
        return out
    return [] if a == b else [path or "(all)"]


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
