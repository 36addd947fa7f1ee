"""Recording drives to disk in the KITTI layout (``rangemcl.datasets.kitti``), with ground truth and
odometry."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.datasets.kitti import SequenceWriter, read_meta
from rangemcl.errors import InputError
from rangemcl.sensors import load_spec
from simbed import __version__
from simbed.scenes.lanes import MAX_SPEED_MPS, check_lane, lane_from_waypoints, read_waypoints
from simbed.scenes.routes import Route, is_waypoint_file, load_waypoints, make_route
from simbed.sim import DEFAULT_SENSOR_MODEL
from simbed.sim.actors import ACTOR_KINDS, actors_along_route, check_actor_paths, read_actor_paths
from simbed.sim.drive import Drive
from simbed.sim.lidar import sensor_setup
from simbed.sim.world import World, resolve_scene

CHECKPOINT_EVERY = 200  # frames between a recording's checkpoints (20 s of a 10 Hz sensor)
CHECKPOINT_NAME = ".record_checkpoint.npz"
CHECKPOINT_VERSION = 1


@dataclass
class RecordSummary:
    out: Path
    frames: int
    seconds_simulated: float
    route_length_m: float
    distance_driven_m: float
    route_done: bool
    stuck_at: tuple[float, float] | None = None  # where the car got stuck, if it did


def check_writable(out: Path) -> None:
    """Fail before any simulation if ``out`` cannot become a sequence folder."""
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{out}: cannot create the output folder ({probe} is not a folder)")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write the output folder ({probe} is not writable)")


def record(
    scene: str,
    route: str,
    sensor: str,
    out: str | os.PathLike,
    *,
    frames: int,
    actors: int = 0,
    variant: int = 0,
    seed: int = 0,
    skew: bool = True,
    device: str = "cpu",
    overwrite: bool = False,
    progress: bool = True,
    loop: bool = False,
    actor_paths: str | os.PathLike | None = None,
    fmt: str = "kitti",
    viz: bool = False,
    viz_out: str | os.PathLike | None = None,
    sensor_model: str = DEFAULT_SENSOR_MODEL,
    weather: str = "clear",
    return_mode: str = "strongest",
    dropout: float = 0.0,
    resume: bool = False,
    checkpoint_every: int = CHECKPOINT_EVERY,
) -> RecordSummary:
    """Drive ``route`` in ``scene`` and write ``frames`` LiDAR frames to ``out``.

    ``scene`` is a generated town or any MJCF scene (a car is added if it has none; the ground comes from
    its own geometry without a sidecar); ``route`` a named route of a town's road network or a waypoint
    file (:mod:`simbed.scenes.lanes`; ``loop`` closes it and the car drives it lap after lap until
    ``frames``).
    ``actors`` move on a town's roads, or beside a waypoint route in a scene without roads; with
    ``actor_paths`` (a YAML file, :func:`simbed.sim.actors.read_actor_paths`) they follow their own paths.
    Everything that can be checked (scene, sensor, route against the scene, output folder) is checked
    before the first file is written; frames are written one by one, so an interrupted recording leaves
    a readable prefix. The drive stops early when the route ends.

    ``fmt`` ``kitti`` writes a KITTI-layout folder; ``mcap``, ``rosbag2`` and ``rosbag1`` a bag
    (:class:`rangemcl.datasets.rosbag.BagWriter`: PointCloud2 with per-point time and ring, IMU, odometry, TF,
    the true pose and the actors' boxes), which is complete only once closed. ``viz`` streams the scene,
    the car, its sweeps and the actors to the rerun viewer, ``viz_out`` saves them as an ``.rrd``.
    ``sensor_model`` is ``ideal`` or ``realistic`` (:mod:`simbed.sim.lidar`); the realistic one writes
    each point's intensity, meets ``weather`` (``clear``, ``fog:V``, ``rain:R``) and reports its
    ``return_mode``'s echoes (``strongest``, ``last``, ``dual``: each point's ``echo`` in its metadata).
    ``dropout`` drops that share of the returns at random on top (a stress test; the spec's
    ``dropout_prob`` when larger).

    A KITTI recording keeps a checkpoint in ``out`` every ``checkpoint_every`` frames (the simulation's
    whole state; removed when the recording ends); ``resume`` continues an interrupted recording from its
    last checkpoint, with the same arguments (``frames`` may differ), and gives the same bytes as an
    uninterrupted one.
    """
    out = Path(out)
    if frames < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    if actors < 0:
        raise InputError(f"actors must be >= 0, got {actors}")
    if variant < 0:
        raise InputError(f"variant must be >= 0, got {variant}")
    if seed < 0:
        raise InputError(f"seed must be >= 0, got {seed}")
    spec = load_spec(sensor)
    if not 0.0 <= dropout < 1.0:
        raise InputError(f"dropout must be in [0, 1), got {dropout}")
    if dropout > spec.dropout_prob:
        spec = dataclasses.replace(spec, dropout_prob=float(dropout))
    _, sky = sensor_setup(spec, sensor_model, weather, return_mode)  # before anything is written
    if fmt not in ("kitti", *BAG_FORMATS):
        raise InputError(f"format {fmt!r}: expected kitti, {', '.join(BAG_FORMATS)}")
    if resume and fmt != "kitti":
        raise InputError(f"{out}: --resume continues KITTI recordings only (a bag is whole only once closed)")
    if fmt != "kitti":
        from rangemcl.datasets.rosbag import require_rosbags

        require_rosbags(f"--format {fmt}")
        if (fmt == "rosbag1") != (out.suffix == ".bag"):
            raise InputError(
                f"{out}: a ROS 1 bag is a file ending in .bag"
                if fmt == "rosbag1"
                else f"{out}: a {fmt} bag is a folder; give a name without .bag"
            )
    check_writable(out)
    from rangemcl.viz.rerun import DriveViewer, check_rrd_path, rerun_module

    if viz or viz_out is not None:  # the extra and the file's folder, before anything is written
        rerun_module()
    if viz_out is not None:
        check_rrd_path(viz_out)
    if checkpoint_every < 1:
        raise InputError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    args = {  # what a resumed recording must share with the one it continues
        "scene": str(resolve_scene(scene)),
        "route": route,
        "sensor": sensor,
        "actors": actors,
        "variant": variant,
        "seed": seed,
        "skew": skew,
        "device": device,
        "loop": loop,
        "actor_paths": None if actor_paths is None else str(actor_paths),
        "sensor_model": sensor_model,
        "weather": weather,
        "return_mode": return_mode,
        "dropout": dropout,
    }
    ckpt = _read_checkpoint(out, args, frames) if resume else None
    rng = np.random.default_rng(seed)
    if loop and not is_waypoint_file(route):
        raise InputError(f"--loop is for waypoint files; route {route!r} is not one")
    plan, dropped = None, []
    if actor_paths is not None:
        if actors:
            raise InputError("--actors and --actor-paths exclude each other (the file gives the actors)")
        plan = read_actor_paths(actor_paths)
    elif actors and is_waypoint_file(route) and not (resolve_scene(scene).with_suffix(".yaml")).is_file():
        lane = lane_from_waypoints(read_waypoints(Path(route)), loop=loop)
        plan = actors_along_route(actors, lane.points, loop, rng, keep_clear_xy=tuple(lane.points[0]))
    world = World(
        scene,
        variant=variant,
        n_actors=0 if plan is not None else actors,
        rng=rng,
        device=device,
        add_car=True,
        actors=plan,
    )
    path = scene_route(world, route, loop=loop, min_length_m=frames / spec.rotation_hz * MAX_SPEED_MPS)
    if plan is not None:
        ground = world.scene_ground.height if world.scene_ground is not None else world.ground_height
        source = str(actor_paths) if actor_paths is not None else f"actors beside {route}"
        dropped = check_actor_paths(world.actors, ground, world.caster, world.static_handle, source)
        for line in dropped:
            print(f"simbed: warning: {line}", file=sys.stderr)
    drive = Drive(
        world,
        path,
        spec,
        rng,
        skew=skew,
        sensor_model=sensor_model,
        weather=str(sky),
        return_mode=return_mode,
    )
    viewer = DriveViewer.open(f"simbed record {Path(scene).stem} {route}", out_rrd=viz_out, spawn=viz)
    if viewer.enabled:
        viewer.log_map(*world.static_triangles)
    meta = {
        "generator": f"simbed {__version__}",
        "scene": world.path.stem,
        "scene_file": str(world.path),
        "route": route,
        "route_loop": loop,
        "route_length_m": round(path.length_m, 3),
        "parked_variant": variant,
        "actors": len(world.actors),
        "actors_requested": actors if actor_paths is None else len(plan),
        "actor_paths": None if actor_paths is None else str(actor_paths),
        "actors_left_out": dropped,
        "seed": seed,
        "skew": skew,
        "physics_timestep_s": float(world.model.opt.timestep),
        "sensor": spec.to_dict(),
        "sensor_model": sensor_model,
        **({"weather": str(sky), "return_mode": return_mode} if sensor_model == "realistic" else {}),
        "frames_requested": frames,
        "point_labels": {"0": "static world", "1": "moving actor"},
        "odometry": drive.odometry_errors(),
    }
    summary = RecordSummary(out, 0, 0.0, path.length_m, 0.0, False)
    last, resume_at = None, None
    if ckpt is not None:
        doc, arrays = ckpt
        try:
            drive.restore(doc["drive"], arrays)
        except (KeyError, ValueError, TypeError) as err:
            raise InputError(f"{checkpoint_path(out)}: unreadable checkpoint ({err}); record again") from None
        summary.frames, summary.seconds_simulated = doc["frames"], doc["seconds_simulated"]
        summary.distance_driven_m, last = doc["distance_driven_m"], arrays.get("last_pose")
        resume_at = summary.frames
    if fmt == "kitti":
        if resume_at is None and overwrite:
            checkpoint_path(out).unlink(missing_ok=True)  # an earlier recording's
        writer = SequenceWriter(out, meta=meta, overwrite=overwrite, resume_at=resume_at)
    else:
        from rangemcl.datasets.rosbag import BagWriter

        writer = BagWriter(out, fmt, meta=meta, T_base_sensor=spec.T_base_sensor, overwrite=overwrite)
    with writer, _progress(progress, frames, summary.frames) as bar, viewer:
        for _ in range(summary.frames, frames):
            frame = drive.next_frame()
            s = frame.sweep
            extra = {} if fmt == "kitti" else {"actors": _actor_boxes(world)}
            writer.add_frame(
                s.points,
                pose=frame.T_world_sensor,
                time_s=frame.time_s,
                intensity=s.intensity,
                odometry=frame.T_odom_sensor,
                imu_roll_pitch=frame.imu_roll_pitch,
                point_meta={
                    "ring": s.ring,
                    "column": s.column,
                    "time_s": s.time_s,
                    "label": s.label,
                    **({"echo": s.echo, "snr": s.snr} if sensor_model == "realistic" else {}),
                },
                **extra,
            )
            if last is not None:
                summary.distance_driven_m += float(np.linalg.norm(frame.T_world_sensor[:2, 3] - last[:2, 3]))
            last = frame.T_world_sensor
            summary.frames += 1
            summary.seconds_simulated = frame.time_s
            bar(frame)
            if viewer.enabled:
                viewer.record_frame(frame, actors=_actor_boxes(world))
            if frame.route_done:
                summary.route_done = True
                break
            if frame.stuck:
                summary.stuck_at = tuple(float(c) for c in frame.T_world_sensor[:2, 3])
                break
            if fmt == "kitti" and summary.frames % checkpoint_every == 0 and summary.frames < frames:
                _write_checkpoint(out, args, drive, summary, last)
        writer.update_meta(frames=summary.frames, route_done=summary.route_done, stuck_at=summary.stuck_at)
    if fmt == "kitti":
        checkpoint_path(out).unlink(missing_ok=True)
    return summary


def checkpoint_path(out: Path) -> Path:
    """Where a KITTI recording in ``out`` keeps its checkpoint."""
    return Path(out) / CHECKPOINT_NAME


def _complete(out: Path) -> bool:
    """Whether the KITTI recording in ``out`` is marked complete (its writer's flag in meta.yaml)."""
    return bool(read_meta(Path(out) / "meta.yaml").get("complete"))


def resumable(out: str | os.PathLike) -> bool:
    """Whether ``out`` holds an interrupted KITTI recording with a checkpoint to go on from (callers that
    record a drive of their own, such as the demo, resume it rather than start it again)."""
    try:
        return checkpoint_path(Path(out)).is_file() and not _complete(Path(out))
    except InputError:  # an unreadable meta.yaml: nothing to go on from; the recording starts again
        return False


def _write_checkpoint(out: Path, args: dict, drive: Drive, summary: RecordSummary, last) -> None:
    """The recording's checkpoint: one ``.npz`` of arrays and a JSON record (no pickle: as safe to load as
    the recording), written atomically."""
    import json

    from rangemcl.common.atomic import atomic_write, savez_stable

    state, arrays = drive.state()
    if last is not None:
        arrays = {**arrays, "last_pose": np.asarray(last, np.float64)}
    doc = {
        "version": CHECKPOINT_VERSION,
        "generator": f"simbed {__version__}",
        "args": args,
        "frames": summary.frames,
        "seconds_simulated": summary.seconds_simulated,
        "distance_driven_m": summary.distance_driven_m,
        "drive": state,
    }
    text = json.dumps(doc, sort_keys=True)
    atomic_write(
        checkpoint_path(out), lambda fh: savez_stable(fh, compressed=False, doc=np.array(text), **arrays)
    )


def _read_checkpoint(out: Path, args: dict, frames: int) -> tuple[dict, dict]:
    """The checkpoint a recording in ``out`` left (its record and arrays), checked against this
    recording's arguments; one clear error line where there is none to continue from."""
    import json

    path = checkpoint_path(out)
    if _complete(out):
        raise InputError(f"{out}: the recording is complete; nothing to resume")
    if not path.is_file():
        raise InputError(
            f"{path}: no checkpoint to resume from (none is written before frame {CHECKPOINT_EVERY}, and "
            "none by bag recordings); record again with --overwrite"
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        doc = json.loads(str(arrays.pop("doc")))
        if not isinstance(doc, dict) or doc.get("version") != CHECKPOINT_VERSION:
            raise ValueError("not a checkpoint of this simbed")
        frames_done = int(doc["frames"])
    except Exception as err:  # a damaged or foreign file: one line, never a traceback
        raise InputError(f"{path}: unreadable checkpoint ({err}); record again with --overwrite") from None
    if doc["args"] != args:
        diff = sorted(k for k in args if doc["args"].get(k) != args[k])
        raise InputError(
            f"{path}: the recording was made with other arguments ({', '.join(diff)}: "
            + ", ".join(f"{doc['args'].get(k)!r}" for k in diff)
            + "); resume it with the same ones"
        )
    if frames <= frames_done:
        raise InputError(f"{path}: it holds {frames_done} frames already; ask for more than that to resume")
    if doc["generator"] != f"simbed {__version__}":
        raise InputError(
            f"{path}: written by {doc['generator']}, this is simbed {__version__}; "
            "record again with --overwrite"
        )
    return doc, arrays


BAG_FORMATS = ("mcap", "rosbag2", "rosbag1")


def _actor_boxes(world: World) -> list[dict]:
    """The moving actors' boxes as they stand now (their mocap poses), for a bag's marker topic."""
    out = []
    for a in world.actors:
        kind = ACTOR_KINDS[a.kind]
        out.append(
            {
                "name": a.name,
                "kind": a.kind,
                "xyz": world.data.mocap_pos[a.mocap_id].copy(),
                "quat_wxyz": world.data.mocap_quat[a.mocap_id].copy(),
                "half": kind["half"],
                "rgba": kind["rgba"],
            }
        )
    return out


def scene_route(world: World, route: str, *, loop: bool = False, min_length_m: float = 0.0) -> Route:
    """The route to drive in ``world``: a named route of its road network, or a waypoint file checked
    against the scene (:func:`simbed.scenes.lanes.check_lane`: ground, steps, the car's box) before
    anything is
    written; a loop is repeated lap after lap up to ``min_length_m``."""
    town = world.town
    if not is_waypoint_file(route):
        if town is None:
            raise InputError(
                f"{world.path}: route {route!r} needs a road network, which only generated towns have "
                f"({world.path.with_suffix('.yaml')} is missing); give a waypoint file (x y per line)"
            )
        return make_route(route, world.graph, town.lane_width_m, town.road_width_m)
    wp = read_waypoints(Path(route))
    if town is not None:
        load_waypoints(wp, world.graph, town.road_width_m)
    lane = lane_from_waypoints(wp, loop=loop)
    ground = world.scene_ground.height if world.scene_ground is not None else world.ground_height
    check_lane(lane, ground, world.caster, world.static_handle)
    path = Route(Path(route).stem, lane.points, (), lane.speed)
    if loop and path.length_m > 0:
        laps = max(1, math.ceil(min_length_m / path.length_m))
        path = Route(
            path.name,
            np.concatenate([path.points] * laps),
            (),
            None if path.speeds is None else np.concatenate([path.speeds] * laps),
        )
    return path


class _progress:
    """A rich progress bar with speed and frame rate, or nothing."""

    def __init__(self, enabled: bool, total: int, done: int = 0):
        self.enabled = enabled
        self.total = total
        self.done = done  # frames recorded before (a resumed recording)

    def __enter__(self):
        if not self.enabled:
            return lambda frame: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._p = Progress(
            TextColumn("recording"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
        )
        self._p.__enter__()
        task = self._p.add_task("record", total=self.total, completed=self.done, info="")

        def update(frame) -> None:
            info = f"{frame.speed_mps:4.1f} m/s, {len(frame.sweep.points):6d} pts"
            self._p.update(task, advance=1, info=info)

        return update

    def __exit__(self, *exc):
        if self.enabled:
            self._p.__exit__(*exc)
        return False
