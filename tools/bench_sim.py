#!/usr/bin/env python3
"""Simulated recording throughput, as a user gets it from ``simbed record``.

A drive is set up exactly as ``simbed record`` sets it up (``World(scene, n_actors=…)``, the ``mapping``
route, ``Drive(world, route, load_spec(sensor), rng)``) and ``drive.next_frame()`` is timed frame by
frame: physics, controller, odometry and the LiDAR are all included; writing files is not (the cost of
writing one frame with ``rangemcl.datasets.kitti.SequenceWriter`` is measured on its own). Timing wrappers on
``RayCaster.cast``, ``mujoco.mj_step`` and the drive's other steps split the frame time by where it goes;
no library code is changed.

Then the rays the LiDAR cast in a few more frames are replayed, call by call, through our caster, through
Open3D's Embree ``RaycastingScene`` (the world's static triangles and the actor meshes at their current
poses) and through MuJoCo's ``mj_multiRay`` on the world's own model (one call per distinct ray origin:
one per LiDAR column), interleaved, and their ranges compared.

    python tools/bench_sim.py                  # 50 frames after 5 warm-up ones (about 20 s, 2 vCPUs)
    python tools/bench_sim.py --json out.json  # also write the figures
    python tools/bench_sim.py --quick          # 10 frames, a smoke run
    python tools/bench_sim.py --realistic      # also the realistic sensor model on the same drive: its
                                               # frames/s against the ideal one's, in this run

With ``--realistic`` the same drive (a fresh world, the same seed) is timed again with
``sensor_model="realistic"`` (materials, footprints at depth edges, glass; ``--weather`` for weather), right
after the ideal one, and the ratio of their median frame times is reported.
"""

from __future__ import annotations

import argparse
import copy
import gc
import json
import platform
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import mujoco
import numpy as np
import open3d as o3d
import warp as wp

from rangemcl.datasets.kitti import SequenceWriter
from rangemcl.raycast import default_threads
from rangemcl.sensors import load_spec
from simbed.scenes.routes import make_route
from simbed.sim.drive import Drive
from simbed.sim.geometry import body_pose, split_static_dynamic
from simbed.sim.world import World

# MuJoCo geom groups: 0 static scene, 1 and 2 the ego car, 3 actors. mj_multiRay sees groups 0 and 3.
GEOMGROUP = np.array([1, 0, 0, 1, 0, 0], np.uint8)
FLAT_TYPES = {
    int(mujoco.mjtGeom.mjGEOM_BOX),
    int(mujoco.mjtGeom.mjGEOM_PLANE),
    int(mujoco.mjtGeom.mjGEOM_HFIELD),
}
FLAT_TYPES.add(int(mujoco.mjtGeom.mjGEOM_MESH))  # triangles in MuJoCo too
CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
WORLD_SEGMENTS = 24  # World's default tessellation of curved geoms


# ---------------------------------------------------------------------- timing
class Clock:
    """Accumulates wall time and call counts of wrapped callables, by key."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def wrap(self, key: str, fn):
        seconds, calls, now = self.seconds, self.calls, time.perf_counter

        def timed(*args, **kwargs):
            t0 = now()
            try:
                return fn(*args, **kwargs)
            finally:
                seconds[key] += now() - t0
                calls[key] += 1

        return timed

    def snapshot(self) -> tuple[dict[str, float], dict[str, int]]:
        return dict(self.seconds), dict(self.calls)


def wrapper_overhead_s(n: int = 20000) -> float:
    """Seconds one :class:`Clock` wrapper adds to a call (median of 5 loops of ``n`` calls)."""

    def noop():
        return None

    timed = Clock().wrap("x", noop)
    per = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            noop()
        t1 = time.perf_counter()
        for _ in range(n):
            timed()
        t2 = time.perf_counter()
        per.append(((t2 - t1) - (t1 - t0)) / n)
    return max(0.0, float(np.median(per)))


# Exclusive categories of a frame's time: (key, label)
CATEGORIES = (
    ("raycast", "LiDAR ray casting (RayCaster.cast)"),
    ("physics", "physics (mujoco.mj_step)"),
    ("ray_prep", "ray set-up: pose interpolation, rotation, labels"),
    ("sync", "actors and caster poses (World.sync_caster)"),
    ("controller", "controller (RouteFollower.control)"),
    ("odometry", "odometry (WheelGyroOdometry.step)"),
    ("sensor_pose", "sensor pose per physics step (Drive.sensor_pose)"),
    ("finish", "sweep finish: noise, points (SimLidar.finish)"),
    ("other", "other (loop, World.step bookkeeping, Frame)"),
)


def instrument(drive: Drive, clock: Clock) -> Callable[[], None]:
    """Wrap the drive's steps with ``clock``; returns a function that undoes it."""
    world, lidar = drive.world, drive.lidar
    targets = [
        (world.caster, "cast", "cast"),
        (lidar, "cast_columns", "cast_columns"),
        (world, "sync_caster", "sync"),
        (drive.controller, "control", "controller"),
        (drive.odometry, "step", "odometry"),
        (drive, "sensor_pose", "sensor_pose"),
        (lidar, "finish", "finish"),
    ]
    for obj, name, key in targets:
        setattr(obj, name, clock.wrap(key, getattr(obj, name)))  # instance attribute shadows the method
    original_step = mujoco.mj_step
    mujoco.mj_step = clock.wrap("mj_step", original_step)  # simbed.sim.world calls mujoco.mj_step

    def undo() -> None:
        mujoco.mj_step = original_step
        for obj, name, _ in targets:
            delattr(obj, name)

    return undo


def exclusive(frame_s: float, sec: dict[str, float]) -> dict[str, float]:
    """One frame's time split into the exclusive CATEGORIES (seconds)."""
    g = lambda k: sec.get(k, 0.0)  # noqa: E731
    out = {
        "raycast": g("cast"),
        "physics": g("mj_step"),
        "ray_prep": g("cast_columns") - g("cast"),
        "sync": g("sync"),
        "controller": g("controller"),
        "odometry": g("odometry"),
        "sensor_pose": g("sensor_pose"),
        "finish": g("finish"),
    }
    out["other"] = frame_s - sum(out.values())
    return out


def time_frames(drive: Drive, n_warmup: int, n_frames: int) -> dict:
    """Run warm-up frames, then ``n_frames`` timed frames with the timing wrappers on."""
    for _ in range(n_warmup):
        drive.next_frame()
    clock = Clock()
    undo = instrument(drive, clock)
    rows, calls_per_frame, speeds, points, returns = [], [], [], [], []
    try:
        t_all = time.perf_counter()
        for _ in range(n_frames):
            s0, c0 = clock.snapshot()
            t0 = time.perf_counter()
            frame = drive.next_frame()
            dt = time.perf_counter() - t0
            s1, c1 = clock.snapshot()
            rows.append((dt, exclusive(dt, {k: s1[k] - s0.get(k, 0.0) for k in s1})))
            calls_per_frame.append({k: c1[k] - c0.get(k, 0) for k in c1})
            speeds.append(frame.speed_mps)
            points.append(len(frame.sweep.points))
            returns.append(float((frame.sweep.ranges > 0).mean()))
        total = time.perf_counter() - t_all
    finally:
        undo()
    frame_s = np.array([r[0] for r in rows])
    cats = {k: np.array([r[1][k] for r in rows]) for k, _ in CATEGORIES}
    calls = {k: float(np.mean([c.get(k, 0) for c in calls_per_frame])) for k in calls_per_frame[0]}
    return {
        "frame_s": frame_s,
        "total_s": total,
        "cats": cats,
        "calls": calls,
        "speed": (min(speeds), max(speeds)),
        "points": float(np.median(points)),
        "return_share": float(np.median(returns)),
    }


# ---------------------------------------------------------------------- ray capture and replay
class Capture:
    """The LiDAR's cast calls of a few frames: rays, max range, and what our caster returned then."""

    def __init__(self):
        self.calls: list[dict] = []

    def wrap(self, fn):
        def capturing(origins, directions, max_range=np.inf, **kwargs):
            hits = fn(origins, directions, max_range, **kwargs)
            self.calls.append(
                {
                    "origins": np.array(origins, dtype=np.float64, copy=True),
                    "directions": np.array(directions, dtype=np.float64, copy=True),
                    "max_range": np.array(max_range, dtype=np.float64, copy=True),
                    "ranges": hits.ranges.copy(),
                    "mesh_ids": hits.mesh_ids.copy(),
                }
            )
            return hits

        return capturing


def capture_frames(drive: Drive, n: int) -> tuple[list[dict], list]:
    cap = Capture()
    caster = drive.world.caster
    caster.cast = cap.wrap(caster.cast)
    frames = []
    try:
        for _ in range(n):
            frames.append(drive.next_frame())
    finally:
        del caster.cast
    return cap.calls, frames


def origin_groups(origins: np.ndarray) -> list[slice | np.ndarray]:
    """The rays of each distinct origin, in order of first appearance: a slice where they are contiguous
    (one LiDAR column when the column's beams share an origin), else an index array."""
    _, first, inverse = np.unique(origins, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(inverse))])
    groups = []
    for u in np.argsort(first):
        idx = order[starts[u] : starts[u + 1]]
        contiguous = idx[-1] - idx[0] == len(idx) - 1
        groups.append(slice(int(idx[0]), int(idx[-1]) + 1) if contiguous else idx)
    return groups


class Replay:
    """The captured calls, prepared once for each backend."""

    def __init__(self, calls: list[dict], beams: int):
        self.calls = calls
        self.n_rays = sum(len(c["directions"]) for c in calls)
        self.offsets = np.cumsum([0] + [len(c["directions"]) for c in calls])
        self.max_range = np.concatenate(
            [np.broadcast_to(c["max_range"].reshape(-1), len(c["directions"])) for c in calls]
        )
        self.orig_ranges = np.concatenate([c["ranges"] for c in calls])
        self.orig_mesh = np.concatenate([c["mesh_ids"] for c in calls])
        # Embree: (N, 6) float32 tensors, directions normalised as our caster normalises them
        self.embree_rays = []
        # MuJoCo: one job per distinct origin of a call:
        # (origin (3,), unit directions flattened, where its rays go (slice or indices), cutoff)
        self.mj_jobs = []
        spreads, col_shared, runs = [], True, 0
        for k, c in enumerate(self.calls):
            o = np.asarray(c["origins"], np.float64).reshape(-1, 3)
            d = c["directions"]
            if len(o) == 1:
                o = np.broadcast_to(o, d.shape)
            unit = d / np.linalg.norm(d, axis=1, keepdims=True)
            self.embree_rays.append(
                o3d.core.Tensor(np.hstack([o, unit]).astype(np.float32))  # rows stay contiguous
            )
            if len(o) % beams == 0:  # the LiDAR casts whole columns of `beams` rays
                cols = o.reshape(-1, beams, 3)
                spread = float(np.abs(cols - cols[:, :1]).max())
                spreads.append(spread)
                col_shared &= spread == 0.0
            groups = origin_groups(o)
            mr = np.broadcast_to(c["max_range"].reshape(-1), len(d))
            base = int(self.offsets[k])
            for g in groups:
                cutoff = mr[g].max()  # mj_multiRay takes one cutoff; per-ray max ranges are applied after
                where = slice(g.start + base, g.stop + base) if isinstance(g, slice) else g + base
                first = g.start if isinstance(g, slice) else g[0]
                self.mj_jobs.append((o[first].copy(), np.ascontiguousarray(unit[g]).ravel(), where, cutoff))
            runs += len(groups)
        self.all_origins = np.concatenate(
            [np.broadcast_to(np.reshape(c["origins"], (-1, 3)), c["directions"].shape) for c in calls]
        )
        self.all_directions = np.concatenate([c["directions"] for c in calls])
        self.column_origin_spread_m = max(spreads) if spreads else float("nan")
        self.columns_share_origin = bool(col_shared and spreads)
        self.rays_per_origin = self.n_rays / max(runs, 1)


def replay_ours(caster, rp: Replay) -> dict:
    ranges, mesh, face = [], [], []
    for c in rp.calls:
        h = caster.cast(c["origins"], c["directions"], c["max_range"])
        ranges.append(h.ranges)
        mesh.append(h.mesh_ids)
        face.append(h.face_ids)
    return {"ranges": np.concatenate(ranges), "mesh": np.concatenate(mesh), "face": np.concatenate(face)}


def replay_ours_one_call(caster, rp: Replay) -> None:
    caster.cast(rp.all_origins, rp.all_directions, rp.max_range)


def replay_embree(scene, rp: Replay, threads: int) -> dict:
    t, geo, prim = [], [], []
    for rays in rp.embree_rays:
        out = scene.cast_rays(rays, nthreads=threads)
        t.append(out["t_hit"].numpy())
        geo.append(out["geometry_ids"].numpy())
        prim.append(out["primitive_ids"].numpy())
    r = np.concatenate(t).astype(np.float64)
    r[~(r <= rp.max_range)] = np.inf  # inf misses, and hits beyond max range
    return {"ranges": r, "geometry": np.concatenate(geo), "prim": np.concatenate(prim)}


def replay_mujoco(model, datas, rp: Replay, pool) -> dict:
    """One mj_multiRay call per origin; jobs split in contiguous slices, one per thread and MjData."""
    dist = np.empty(rp.n_rays)
    geomid = np.empty(rp.n_rays, np.int32)
    jobs = rp.mj_jobs
    bounds = np.linspace(0, len(jobs), len(datas) + 1).astype(int)

    def work(k: int) -> None:
        data = datas[k]
        for origin, vec, where, cutoff in jobs[bounds[k] : bounds[k + 1]]:
            n = len(vec) // 3
            contiguous = isinstance(where, slice)  # write in place, else gather afterwards
            g_out = geomid[where] if contiguous else np.empty(n, np.int32)
            d_out = dist[where] if contiguous else np.empty(n)
            mujoco.mj_multiRay(model, data, origin, vec, GEOMGROUP, 1, -1, g_out, d_out, None, n, cutoff)
            if not contiguous:
                geomid[where] = g_out
                dist[where] = d_out

    if pool is None:
        work(0)
    else:
        list(pool.map(work, range(len(datas))))
    # cutoff culls geoms by their bounds, not hits by range: a hit beyond max range is a miss
    miss = (dist < 0) | (dist > rp.max_range)
    dist[miss] = np.inf
    geomid[miss] = -1
    return {"ranges": dist, "geom": geomid}


# ---------------------------------------------------------------------- agreement
def _stats(d: np.ndarray) -> dict:
    if len(d) == 0:
        return {"rays": 0, "p99_m": None, "max_m": None}
    return {"rays": len(d), "p99_m": float(np.quantile(d, 0.99)), "max_m": float(d.max())}


def classify_static(model, data, geom_of_face, face_normals, face_orig) -> tuple[np.ndarray, np.ndarray]:
    """Geom id and 'flat surface' flag of each of our static hits (by original face index)."""
    gid = geom_of_face[face_orig]
    gtype = model.geom_type[gid]
    flat = np.isin(gtype, list(FLAT_TYPES))
    cyl = gtype == CYLINDER
    if cyl.any():  # a cylinder's caps are flat, its side is not
        axis = data.geom_xmat[gid[cyl]].reshape(-1, 3, 3)[:, :, 2]
        cap = np.abs(np.einsum("ij,ij->i", axis, face_normals[face_orig[cyl]])) > 0.999
        flat[np.flatnonzero(cyl)[cap]] = True
    return gid, flat


def agreement(ours, peer, flat, cos_inc) -> dict:
    """Range differences between our hits and a peer's. ``ours``/``peer``: dicts of ``ranges``, ``static``
    and ``actor`` (bool per ray) and ``geom`` (geom id of static hits, or None without the per-geom map)."""
    o_r, p_r = ours["ranges"], peer["ranges"]
    fo, fp = np.isfinite(o_r), np.isfinite(p_r)
    both_static = fo & fp & ours["static"] & peer["static"]
    diff = np.where(fo & fp, np.abs(np.where(fo, o_r, 0.0) - np.where(fp, p_r, 0.0)), np.inf)
    mixed = (ours["static"] & peer["actor"]) | (ours["actor"] & peer["static"])
    out = {
        "hit_miss_disagree": int((fo != fp).sum()),
        "static_vs_actor": int((fo & fp & mixed).sum()),
        "both_static": _stats(diff[both_static]),
        "actors": _stats(diff[fo & fp & ours["actor"] & peer["actor"]]),
    }
    if ours["geom"] is None:
        return out
    same = ours["geom"] == peer["geom"]
    flat_rays = both_static & same & flat
    out["flat_same_geom"] = _stats(diff[flat_rays])
    out["flat_same_geom_below_80deg"] = _stats(diff[flat_rays & (cos_inc > np.cos(np.radians(80.0)))])
    out["curved_same_geom"] = _stats(diff[both_static & same & ~flat])
    out["different_geom"] = _stats(diff[both_static & ~same])
    for key, sel in (("worst_flat_ray", flat_rays), ("worst_different_geom_ray", both_static & ~same)):
        idx = np.flatnonzero(sel)
        if len(idx):
            out[key] = int(idx[np.argmax(diff[idx])])
    return out


def geom_label(model, g: int) -> str:
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(g)) or f"geom{int(g)}"
    return f"{name} ({mujoco.mjtGeom(int(model.geom_type[int(g)])).name.removeprefix('mjGEOM_').lower()})"


def describe_ray(model, i: int, ours: dict, peer: dict, cos_incidence: np.ndarray) -> dict:
    """The geoms, ranges and incidence of ray ``i`` (for the largest differences)."""
    return {
        "ray": i,
        "ours": geom_label(model, ours["geom"][i]),
        "peer": geom_label(model, peer["geom"][i]),
        "ours_range_m": float(ours["ranges"][i]),
        "peer_range_m": float(peer["ranges"][i]),
        "incidence_deg": float(np.degrees(np.arccos(np.clip(cos_incidence[i], 0.0, 1.0)))),
    }


# ---------------------------------------------------------------------- writing
def write_cost(frames: list, spec, n: int, folder: str | None) -> dict:
    """Median seconds of ``SequenceWriter.add_frame`` for one frame, as ``simbed record`` calls it."""
    times = []
    with tempfile.TemporaryDirectory(dir=folder, prefix="bench_sim_") as tmp:
        root = Path(tmp) / "seq"
        meta = {"generator": "tools/bench_sim.py", "sensor": spec.to_dict()}
        with SequenceWriter(root, meta=meta) as writer:
            for i in range(n):
                frame = frames[i % len(frames)]
                s = frame.sweep
                t0 = time.perf_counter()
                writer.add_frame(
                    s.points,
                    pose=frame.T_world_sensor,
                    time_s=i * spec.sweep_period_s,  # frames are reused: keep time increasing
                    odometry=frame.T_odom_sensor,
                    imu_roll_pitch=frame.imu_roll_pitch,
                    point_meta={"ring": s.ring, "column": s.column, "time_s": s.time_s, "label": s.label},
                )
                times.append(time.perf_counter() - t0)
        size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file()) / n  # scans, npz, text lines
        where = str(Path(tmp).parent)
    return {
        "median_s": float(np.median(times)),
        "frames": n,
        "bytes_per_frame": int(size),
        "dir": where,
    }


# ---------------------------------------------------------------------- main
def ms(x: float) -> str:
    return f"{x * 1e3:.1f} ms"


def mm(x) -> str:
    return "n/a" if x is None else f"{x * 1e3:.3f} mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=50, help="timed frames (default 50)")
    ap.add_argument("--warmup", type=int, default=5, help="untimed frames first (default 5)")
    ap.add_argument("--actors", type=int, default=10, help="moving actors (default 10)")
    ap.add_argument("--sensor", default="os1-64", help="LiDAR preset or YAML file (default os1-64)")
    ap.add_argument("--scene", default="town_small", help="scene name or MJCF path (default town_small)")
    ap.add_argument("--route", default="mapping", help="route name (default mapping)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="ray-caster threads (0 = every core)")
    ap.add_argument("--capture", type=int, default=5, help="frames whose rays are replayed (default 5)")
    ap.add_argument("--repeats", type=int, default=5, help="timed replays per backend (median reported)")
    ap.add_argument("--write-frames", type=int, default=20, help="frames written for the write cost")
    ap.add_argument("--write-dir", help="folder for the write test's temporary sequence (default: temp)")
    ap.add_argument("--quick", action="store_true", help="10 frames, 2 warm-up, 2 captured, 2 repeats")
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--realistic", action="store_true", help="also time the realistic sensor model")
    ap.add_argument("--weather", default="clear", help="the realistic model's weather (default clear)")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.warmup, args.capture, args.repeats, args.write_frames = 10, 2, 2, 2, 5
    if min(args.frames, args.capture, args.repeats, args.write_frames) < 1 or args.warmup < 0:
        ap.error("--frames, --capture, --repeats and --write-frames must be >= 1, --warmup >= 0")
    cores = args.threads or default_threads()

    # ---- set up as `simbed record` does
    spec = load_spec(args.sensor)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    world = World(args.scene, n_actors=args.actors, rng=rng, threads=args.threads or None)
    t_world = time.perf_counter() - t0
    town = world.town
    route = make_route(args.route, world.graph, town.lane_width_m, town.road_width_m)
    t0 = time.perf_counter()
    drive = Drive(world, route, spec, rng)
    t_drive = time.perf_counter() - t0
    h, w = drive.lidar.geometry.shape
    rays_per_frame = h * w
    target_fps = 1.0 / spec.sweep_period_s
    n_static = len(world.static_triangles[1])
    print(
        f"scene {world.path.stem}, {args.actors} actors, {spec.name} ({h} x {w} rays at {target_fps:g} Hz), "
        f"route {args.route}, seed {args.seed}"
    )
    print(
        f"machine: {cores} cores for the caster ({default_threads()} available), "
        f"{platform.processor() or platform.machine()}; Python {platform.python_version()}, "
        f"Warp {wp.config.version}, MuJoCo {mujoco.__version__}, Open3D {o3d.__version__}"
    )
    print(
        f"setup: World {t_world:.2f} s ({n_static:,} static triangles, {len(world.dynamic_handles)} "
        f"moving meshes), Drive {t_drive:.2f} s (settling), physics step {drive.dt * 1e3:g} ms"
    )

    # ---- timed frames
    per_call = wrapper_overhead_s()
    res = time_frames(drive, args.warmup, args.frames)
    frame_s, cats, total = res["frame_s"], res["cats"], res["total_s"]
    med = float(np.median(frame_s))
    fps_med, fps_total = 1.0 / med, args.frames / total
    wrapped_calls = sum(v for k, v in res["calls"].items())
    overhead = per_call * wrapped_calls
    print(
        f"\n{args.frames} timed frames after {args.warmup} warm-up; car speed {res['speed'][0]:.1f} to "
        f"{res['speed'][1]:.1f} m/s; {res['points']:,.0f} points per frame ({res['return_share']:.0%} of "
        f"rays return)"
    )
    verdict = "met" if fps_med >= target_fps else "NOT met"
    print(
        f"throughput: median frame {ms(med)} = {fps_med:.2f} frames/s; total {args.frames} frames in "
        f"{total:.2f} s = {fps_total:.2f} frames/s (min {ms(frame_s.min())}, max {ms(frame_s.max())})"
    )
    print(
        f"target {target_fps:g} frames/s (real time for a {target_fps:g} Hz LiDAR) on this machine: "
        f"{verdict} (real-time factor {fps_med / target_fps:.2f}x by median, {fps_total / target_fps:.2f}x "
        f"in total)"
    )
    print(
        f"\nwhere a frame's time goes ({int(res['calls'].get('mj_step', 0))} physics steps and "
        f"{int(res['calls'].get('cast', 0))} cast calls per frame):"
    )
    print(f"  {'':<52} {'share of total':>14} {'median/frame':>13}")
    shares = {}
    for key, label in CATEGORIES:
        share = float(cats[key].sum() / frame_s.sum())
        shares[key] = share
        print(f"  {label:<52} {share:>14.1%} {ms(float(np.median(cats[key]))):>13}")
    rest = 1.0 - shares["raycast"] - shares["physics"]
    cast_rate = rays_per_frame / float(np.median(cats["raycast"])) / 1e6
    step_us = float(np.median(cats["physics"])) / max(res["calls"].get("mj_step", 1), 1) * 1e6
    print(
        f"  => LiDAR {shares['raycast']:.1%} ({cast_rate:.2f} M rays/s inside the drive), physics "
        f"{shares['physics']:.1%} ({step_us:.0f} us/step), rest (Python) {rest:.1%}"
    )
    print(
        f"  (the timing wrappers' own cost, {wrapped_calls:.0f} calls x {per_call * 1e6:.2f} us = "
        f"{ms(overhead)} per frame, is in these figures)"
    )

    realistic = None
    if args.realistic:  # the same drive again, with the realistic sensor
        rng_r = np.random.default_rng(args.seed)
        world_r = World(args.scene, n_actors=args.actors, rng=rng_r, threads=args.threads or None)
        drive_r = Drive(world_r, route, spec, rng_r, sensor_model="realistic", weather=args.weather)
        res_r = time_frames(drive_r, args.warmup, args.frames)
        med_r = float(np.median(res_r["frame_s"]))
        realistic = {
            "weather": args.weather,
            "frame_s_median": med_r,
            "frames_per_s_median": 1.0 / med_r,
            "points_per_frame": res_r["points"],
            "realistic_over_ideal_frame_time": med_r / med,
        }
        print(
            f"\nrealistic sensor ({args.weather}): median frame {ms(med_r)} = {1.0 / med_r:.2f} frames/s, "
            f"{res_r['points']:,.0f} points per frame; {med_r / med:.2f}x the ideal sensor's frame time "
            f"(same drive, this run)"
        )

    # ---- capture rays
    calls, frames = capture_frames(drive, args.capture)
    wc = write_cost(frames, spec, args.write_frames, args.write_dir)
    print(
        f"\nwriting one frame with SequenceWriter (not in the figures above): median {ms(wc['median_s'])} "
        f"over {wc['frames']} frames, {wc['bytes_per_frame'] / 1e3:.0f} kB per frame, in {wc['dir']}; "
        f"simulate + write: {1.0 / (med + wc['median_s']):.2f} frames/s"
    )

    # ---- replay through the three backends
    rp = Replay(calls, h)
    caster = world.caster
    t0 = time.perf_counter()
    parts = split_static_dynamic(
        world.model,
        world.data,
        exclude_bodies=[world.car.body],
        include_geom=lambda g: g not in set(world.hidden_geoms.tolist()),
        segments=WORLD_SEGMENTS,
    )
    sv, sf = world.static_triangles
    geom_map_ok = np.array_equal(parts.static[1], sf) and np.allclose(parts.static[0], sv)
    scene = o3d.t.geometry.RaycastingScene(nthreads=cores)
    static_geo = scene.add_triangles(
        o3d.core.Tensor(np.asarray(sv, np.float32)), o3d.core.Tensor(np.asarray(sf, np.uint32))
    )
    for bm in parts.dynamic:
        T = body_pose(world.data, bm.body_id)
        v = bm.vertices @ T[:3, :3].T + T[:3, 3]
        scene.add_triangles(
            o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(bm.faces.astype(np.uint32))
        )
    scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 10, 0, 0, -1]], np.float32)))  # builds its BVH
    t_embree = time.perf_counter() - t0
    datas = []
    for _ in range(cores):
        d = copy.copy(world.data)
        mujoco.mj_forward(world.model, d)
        datas.append(d)
    pool = ThreadPoolExecutor(cores) if cores > 1 else None
    runners = {
        "ours": lambda: replay_ours(caster, rp),
        "ours_one_call": lambda: replay_ours_one_call(caster, rp),
        "embree": lambda: replay_embree(scene, rp, cores),
        "mujoco": lambda: replay_mujoco(world.model, datas, rp, pool),
    }
    out = {k: run() for k, run in runners.items()}  # warm-up, and the ranges to compare
    times = {k: [] for k in runners}
    order = list(runners)
    for r in range(args.repeats):  # interleaved, the order turned each round
        for k in order[r % len(order) :] + order[: r % len(order)]:
            t0 = time.perf_counter()
            runners[k]()
            times[k].append(time.perf_counter() - t0)
    if pool is not None:
        pool.shutdown()
    rate = {k: rp.n_rays / float(np.median(v)) / 1e6 for k, v in times.items()}

    # ---- agreement
    static_handle = world.static_handle
    o_r, o_mesh = out["ours"]["ranges"].astype(np.float64), out["ours"]["mesh"]
    ours = {"ranges": o_r, "static": o_mesh == static_handle, "actor": np.isin(o_mesh, world.actor_handles)}
    e_static = out["embree"]["geometry"] == static_geo
    embree = {
        "ranges": out["embree"]["ranges"],
        "static": e_static,
        "actor": np.isfinite(out["embree"]["ranges"]) & ~e_static,
    }
    mj_geom = out["mujoco"]["geom"]
    mj_body = world.model.geom_bodyid[np.maximum(mj_geom, 0)]
    m_static = (mj_geom >= 0) & (world.model.body_weldid[mj_body] == 0)
    mj = {"ranges": out["mujoco"]["ranges"], "static": m_static, "actor": (mj_geom >= 0) & ~m_static}
    flat = cos_inc = None
    for d in (ours, embree, mj):
        d["geom"] = None
    if geom_map_ok:  # which geom (and which kind of surface) each static hit is on
        geom_of_face = parts.static[2]
        face_map = caster.meshes[static_handle].face_map
        face_orig = np.where(ours["static"], face_map[np.maximum(out["ours"]["face"], 0)], 0)
        a, b, c = (sv[sf[:, i]] for i in range(3))
        nrm = np.cross(b - a, c - a)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        ours["geom"], flat = classify_static(world.model, datas[0], geom_of_face, nrm, face_orig)
        embree["geom"] = geom_of_face[np.clip(out["embree"]["prim"].astype(np.int64), 0, len(sf) - 1)]
        mj["geom"] = mj_geom
        dirs = np.concatenate([c["directions"] for c in calls])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        cos_inc = np.abs(np.einsum("ij,ij->i", dirs, nrm[face_orig]))
    agree = {}
    for name, peer in (("embree", embree), ("mujoco", mj)):
        a = agree[name] = agreement(ours, peer, flat, cos_inc)
        for key in ("worst_flat_ray", "worst_different_geom_ray"):
            if key in a:
                a[key] = describe_ray(world.model, a[key], ours, peer, cos_inc)
    both = ours["static"] & (rp.orig_mesh == static_handle)
    replay_same = int((out["ours"]["ranges"][both] == rp.orig_ranges[both]).sum())

    print(
        f"\nreplay of the LiDAR's rays from {args.capture} more frames: {rp.n_rays:,} rays in {len(calls)} "
        f"cast calls, median of {args.repeats} interleaved runs, {cores} cores each"
    )
    shared = "yes" if rp.columns_share_origin else f"NO (spread {rp.column_origin_spread_m:.3g} m)"
    print(
        f"  each column's {h} rays share one origin: {shared}; mj_multiRay calls: {len(rp.mj_jobs):,} "
        f"({rp.rays_per_origin:.1f} rays each); Embree scene build {t_embree:.2f} s"
    )
    print(f"  {'backend':<42} {'M rays/s':>9} {'ours / peer':>12}")
    labels = {
        "ours": "Warp (ours), calls as the LiDAR made them",
        "ours_one_call": "Warp (ours), all rays in one call",
        "embree": "Embree (Open3D RaycastingScene)",
        "mujoco": "MuJoCo mj_multiRay",
    }
    for k in runners:
        ratio = "" if k.startswith("ours") else f"{rate['ours'] / rate[k]:.2f}x"
        print(f"  {labels[k]:<42} {rate[k]:>9.2f} {ratio:>12}")
    print(
        f"  our replay reproduces the LiDAR's own static hits bit for bit on {replay_same:,} of "
        f"{int(both.sum()):,} rays that hit static geometry both times (actors have moved since)"
    )
    row = "      {:<48} {:>8,} rays  p99 {:>11}  max {:>11}"
    for k, a in agree.items():
        print(
            f"  ours vs {k}: {a['hit_miss_disagree']} hit/miss disagreements, {a['static_vs_actor']} "
            f"static/actor disagreements; {a['both_static']['rays']:,} rays hit static geometry in both, "
            f"largest difference {mm(a['both_static']['max_m'])}"
        )
        if geom_map_ok:
            for key, label in (
                ("flat_same_geom", "flat surfaces, same geom"),
                ("flat_same_geom_below_80deg", "  of which incidence < 80 deg"),
                ("curved_same_geom", "curved surfaces (tessellated), same geom"),
                ("different_geom", "different geoms (seams, overlaps, silhouettes)"),
            ):
                s = a[key]
                print(row.format(label, s["rays"], mm(s["p99_m"]), mm(s["max_m"])))
            for key, label in (("worst_flat_ray", "flat"), ("worst_different_geom_ray", "different-geom")):
                if key in a:
                    r = a[key]
                    print(
                        f"        largest {label} difference: ours {r['ours']} at {r['ours_range_m']:.3f} m, "
                        f"{k} {r['peer']} at {r['peer_range_m']:.3f} m, incidence {r['incidence_deg']:.1f} "
                        "deg"
                    )
        s = a["actors"]
        print(row.format("both hit an actor", s["rays"], mm(s["p99_m"]), mm(s["max_m"])))
    if not geom_map_ok:
        print("  (the world's static triangles differ from a fresh triangulation: no per-geom split)")

    # ---- summary
    print("\nsummary:")
    print(
        f"  {fps_med:.2f} frames/s by median frame ({fps_total:.2f} in total) against {target_fps:g} "
        f"frames/s real time on {default_threads()} cores: {verdict}"
    )
    print(
        f"  LiDAR ray casting takes {shares['raycast']:.0%} of the frame, physics {shares['physics']:.0%}, "
        f"Python rest {rest:.0%}; writing adds {ms(wc['median_s'])} per frame"
    )
    print(
        f"  ray replay: ours {rate['ours']:.2f} M rays/s = {rate['ours'] / rate['embree']:.2f}x Embree, "
        f"{rate['ours'] / rate['mujoco']:.2f}x mj_multiRay"
    )

    if args.json:
        figures = {
            "scene": world.path.stem,
            "actors": args.actors,
            "sensor": spec.name,
            "seed": args.seed,
            "cores": cores,
            "versions": {"warp": wp.config.version, "mujoco": mujoco.__version__, "open3d": o3d.__version__},
            "setup_s": {"world": t_world, "drive": t_drive},
            "frames": args.frames,
            "warmup": args.warmup,
            "frame_s_median": med,
            "frames_per_s_median": fps_med,
            "frames_per_s_total": fps_total,
            "target_frames_per_s": target_fps,
            "target_met": fps_med >= target_fps,
            "share_of_total": shares,
            "median_s_per_frame": {k: float(np.median(v)) for k, v in cats.items()},
            "calls_per_frame": res["calls"],
            "lidar_mrays_per_s_in_drive": cast_rate,
            "timing_wrapper_overhead_s_per_frame": overhead,
            "write": wc,
            "realistic": realistic,
            "replay": {
                "frames": args.capture,
                "rays": rp.n_rays,
                "repeats": args.repeats,
                "columns_share_origin": rp.columns_share_origin,
                "mj_multiray_calls": len(rp.mj_jobs),
                "mrays_per_s": rate,
                "times_s": times,
                "ours_over_embree": rate["ours"] / rate["embree"],
                "ours_over_mujoco": rate["ours"] / rate["mujoco"],
                "replay_static_identical": [replay_same, int(both.sum())],
                "agreement": agree,
            },
        }
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=2)
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
    gc.collect()  # collect reference cycles while the modules are intact (RayCaster.__del__ needs them)
