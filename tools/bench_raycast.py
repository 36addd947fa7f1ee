#!/usr/bin/env python3
"""Ray-casting benchmark: our Warp core against Open3D's Embree ``RaycastingScene`` and MuJoCo's
``mj_multiRay``, on the same town-like mesh and the same rays.

Two workloads: one OS1-64 sweep (64 × 1024 rays from one pose) and 100 poses × 64 × 360 rays. Each
backend runs on 1 core and on all cores; the figures are medians over ``--repeats`` runs, taken in
interleaved order so that the machine's noise falls on every backend alike. The three backends must
agree on the ranges: the largest difference is printed.

    python tools/bench_raycast.py                 # full size (about 220k triangles)
    python tools/bench_raycast.py --json out.json # also write the figures
    python tools/bench_raycast.py --quick         # a small town and few poses, for a smoke run
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np
import open3d as o3d

from rangemcl import meshgen
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster, default_threads
from rangemcl.sensors import load_spec


def town_mjcf(town: meshgen.TownMesh) -> str:
    """The town as an MJCF scene: each part one static mesh geom (MuJoCo casts against its triangles)."""

    def numbers(a: np.ndarray, fmt: str) -> str:
        return " ".join(format(x, fmt) for x in a.ravel())

    assets, geoms = [], []
    for name, v, f in town.parts:
        assets.append(
            f'<mesh name="{name}" vertex="{numbers(v, ".9g")}" face="{numbers(f, "d")}" inertia="shell"/>'
        )
        geoms.append(f'<geom type="mesh" mesh="{name}" contype="0" conaffinity="0"/>')
    return f"<mujoco><asset>{''.join(assets)}</asset><worldbody>{''.join(geoms)}</worldbody></mujoco>"


def sensor_poses(town: meshgen.TownMesh, n: int, height_m: float, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` sensor positions on the town's roads, ``height_m`` above the ground."""
    along = rng.uniform(-0.45, 0.45, n) * town.size_m
    road = rng.choice(town.road_xy, n) + rng.uniform(-2.0, 2.0, n)
    flip = np.arange(n) % 2 == 1
    x, y = np.where(flip, road, along), np.where(flip, along, road)
    return np.column_stack([x, y, meshgen.town_ground_height(x, y) + height_m])


class Workload:
    """Rays from a few origins, stored origin by origin (each origin's rays contiguous, in sweep order)."""

    def __init__(self, name: str, origins: np.ndarray, directions: np.ndarray, max_range_m: float):
        self.name = name
        self.origins = origins  # (P, 3) float64
        self.directions = directions  # (R, 3) float64 unit, the same for every origin
        self.max_range_m = max_range_m
        self.n_rays = len(origins) * len(directions)

    def flat(self) -> tuple[np.ndarray, np.ndarray]:
        o = np.repeat(self.origins, len(self.directions), axis=0).astype(np.float32)
        d = np.tile(self.directions, (len(self.origins), 1)).astype(np.float32)
        return o, d


def run_warp(caster: RayCaster, w: Workload, flat) -> np.ndarray:
    return caster.cast(flat[0], flat[1], w.max_range_m).ranges


def run_embree(scene, w: Workload, rays: o3d.core.Tensor, threads: int) -> np.ndarray:
    t = scene.cast_rays(rays, nthreads=threads)["t_hit"].numpy()
    t[t > w.max_range_m] = np.inf
    return t


def run_mujoco(model, datas, w: Workload, threads: int, pool) -> np.ndarray:
    """mj_multiRay casts a bundle from one point; the binding releases the GIL, so threads scale."""
    n_dir = len(w.directions)
    vec = np.ascontiguousarray(w.directions, dtype=np.float64).ravel()
    out = np.empty(w.n_rays)
    # split every bundle into `threads` slices so that even one pose keeps all cores busy
    jobs = [(p, lo, hi) for p in range(len(w.origins)) for lo, hi in _slices(n_dir, threads)]

    def job(k: int) -> None:
        p, lo, hi = jobs[k]
        data = datas[k % len(datas)]
        geomid = np.empty(hi - lo, np.int32)
        dist = np.empty(hi - lo)
        mujoco.mj_multiRay(
            model,
            data,
            w.origins[p],
            vec[3 * lo : 3 * hi],
            None,
            1,
            -1,
            geomid,
            dist,
            None,
            hi - lo,
            w.max_range_m,
        )
        out[p * n_dir + lo : p * n_dir + hi] = dist

    if threads == 1:
        for k in range(len(jobs)):
            job(k)
    else:
        list(pool.map(job, range(len(jobs))))
    out[(out < 0) | (out > w.max_range_m)] = np.inf  # cutoff culls geoms by their bounds, not hits by range
    return out


def _slices(n: int, k: int) -> list[tuple[int, int]]:
    b = np.linspace(0, n, k + 1).astype(int)
    return [(int(b[i]), int(b[i + 1])) for i in range(k)]


def agreement(a: np.ndarray, b: np.ndarray) -> dict:
    fa, fb = np.isfinite(a), np.isfinite(b)
    both = fa & fb
    diff = np.abs(a[both] - b[both])
    return {
        "hit_miss_disagree": int((fa != fb).sum()),
        "max_range_diff_m": float(diff.max()) if len(diff) else 0.0,
        "p99_99_range_diff_m": float(np.quantile(diff, 0.9999)) if len(diff) else 0.0,
        "rays_over_1cm": int((diff > 0.01).sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per backend (median reported)")
    ap.add_argument("--poses", type=int, default=100, help="poses of the multi-pose workload")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="'all cores' thread count (0 = every core)")
    ap.add_argument("--quick", action="store_true", help="small town, 5 poses, 2 repeats")
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args()
    all_threads = args.threads or default_threads()
    rng = np.random.default_rng(args.seed)
    if args.quick:
        args.poses, args.repeats = 5, 2
        town = meshgen.town(seed=args.seed, size_m=100.0, n_buildings=15, n_poles=20, facade_cell_m=2.0)
    else:
        town = meshgen.town(seed=args.seed)
    vertices, faces = town.merged()

    spec = dataclasses.replace(load_spec("os1-64"), beam_origin_radius_m=0.0)  # one origin per sweep
    sweep_dirs = RangeImageGeometry.for_spec(spec).directions.reshape(-1, 3)
    coarse_dirs = RangeImageGeometry.for_spec(spec.with_columns(360)).directions.reshape(-1, 3)
    workloads = [
        Workload("sweep 64x1024", sensor_poses(town, 1, 1.73, rng), sweep_dirs, spec.max_range_m),
        Workload(
            f"{args.poses} poses x 64x360",
            sensor_poses(town, args.poses, 1.73, rng),
            coarse_dirs,
            spec.max_range_m,
        ),
    ]
    print(
        f"town: {len(faces):,} triangles in {len(town.parts)} parts, {town.size_m:.0f} m square; "
        f"{all_threads} cores; {platform.processor() or platform.machine()}"
    )

    t0 = time.perf_counter()
    casters = {1: RayCaster(threads=1), all_threads: RayCaster(threads=all_threads)}
    for c in casters.values():
        c.add_mesh(vertices, faces, name="town")
    build_warp = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene(nthreads=all_threads)
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 10, 0, 0, -1]], np.float32)))  # builds its BVH
    build_embree = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = mujoco.MjModel.from_xml_string(town_mjcf(town))
    datas = [mujoco.MjData(model) for _ in range(all_threads)]
    for d in datas:
        mujoco.mj_forward(model, d)
    build_mujoco = time.perf_counter() - t0
    print(f"scene build: warp {build_warp:.2f} s, embree {build_embree:.2f} s, mujoco {build_mujoco:.2f} s")
    pool = ThreadPoolExecutor(all_threads)

    results = {"triangles": len(faces), "cores": all_threads, "repeats": args.repeats, "workloads": {}}
    thread_counts = sorted({1, all_threads})
    for w in workloads:
        flat = w.flat()
        rays = o3d.core.Tensor(np.hstack(flat))
        runners = {}
        for th in thread_counts:
            runners[("warp", th)] = lambda th=th, w=w, flat=flat: run_warp(casters[th], w, flat)
            runners[("embree", th)] = lambda th=th, w=w, rays=rays: run_embree(scene, w, rays, th)
            runners[("mujoco", th)] = lambda th=th, w=w: run_mujoco(model, datas, w, th, pool)
        times = {k: [] for k in runners}
        ranges = {}
        for k, run in runners.items():  # warm-up, and the ranges to compare
            ranges[k[0]] = run()
        for _ in range(args.repeats):
            for k, run in runners.items():
                t0 = time.perf_counter()
                run()
                times[k].append(time.perf_counter() - t0)
        rate = {k: w.n_rays / float(np.median(v)) / 1e6 for k, v in times.items()}
        hit = float(np.isfinite(ranges["warp"]).mean())
        agree = {
            "warp_vs_embree": agreement(ranges["warp"], ranges["embree"]),
            "warp_vs_mujoco": agreement(ranges["warp"], ranges["mujoco"]),
        }
        print(f"\n{w.name}: {w.n_rays:,} rays, {hit:.1%} hit within {w.max_range_m:g} m")
        print(f"  {'backend':<8} " + " ".join(f"{f'{th} core(s) Mrays/s':>20}" for th in thread_counts))
        for b in ("warp", "embree", "mujoco"):
            line = f"  {b:<8} " + " ".join(f"{rate[(b, th)]:>20.2f}" for th in thread_counts)
            if len(thread_counts) > 1:  # how well the machine let each backend use its cores
                line += f"   all-core speed-up {rate[(b, all_threads)] / rate[(b, 1)]:.2f}x"
            print(line)
        ratios = {}
        for th in thread_counts:
            ratios[th] = {
                "warp/embree": rate[("warp", th)] / rate[("embree", th)],
                "warp/mujoco": rate[("warp", th)] / rate[("mujoco", th)],
            }
            print(
                f"  ratio on {th} core(s): warp/embree {ratios[th]['warp/embree']:.2f}x, "
                f"warp/mujoco {ratios[th]['warp/mujoco']:.2f}x"
            )
        for name, a in agree.items():
            print(
                f"  agreement {name}: largest range difference {a['max_range_diff_m'] * 1e3:.3f} mm "
                f"(99.99th percentile {a['p99_99_range_diff_m'] * 1e3:.3f} mm), "
                f"{a['rays_over_1cm']} rays differ by > 1 cm, {a['hit_miss_disagree']} hit/miss disagreements"
            )
        results["workloads"][w.name] = {
            "rays": w.n_rays,
            "hit_share": hit,
            "mrays_per_s": {f"{b}@{th}": r for (b, th), r in rate.items()},
            "ratios": {f"{th} cores": r for th, r in ratios.items()},
            "agreement": agree,
        }
    pool.shutdown()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
