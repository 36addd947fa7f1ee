#!/usr/bin/env python3
"""Map-building benchmark: build time and peak memory as the mapping drive grows.

Records (or reuses) a mapping drive of a scene, then builds maps from its first K scans for several K,
each build in its own process so that its peak memory is its own. Prints a table (and ``--json``).

    python tools/bench_map.py --scene town_small --frames 2500 --steps 100,200,400,800,0
    python tools/bench_map.py --scene town_large --frames 1000 --steps 250,500,1000

K = 0 means the whole drive. The drive is recorded into ``--work`` (default /tmp/rangemcl-bench-map) once
and reused by later runs with the same scene, frame count and seed.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

BUILD = """
import json, sys, time
from rangemcl.config import load_config
from rangemcl.datasets.kitti import load_sequence, SequenceWriter
from rangemcl.mapping.pipeline import MapSettings, build_map
seq_dir, out, k, depth = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
settings = MapSettings()
settings.poisson.depth = depth
if k:
    # a prefix of the drive: the first k scans (hard links, no copies)
    import os, shutil
    from pathlib import Path
    src, dst = Path(seq_dir), Path(out + "_seq")
    shutil.rmtree(dst, ignore_errors=True)
    (dst / "velodyne").mkdir(parents=True)
    (dst / "points_meta").mkdir()
    for name in ("calib.txt", "meta.yaml"):
        shutil.copy(src / name, dst / name)
    for name in ("poses.txt", "times.txt"):
        lines = (src / name).read_text().splitlines()[:k]
        (dst / name).write_text("\\n".join(lines) + "\\n")
    for i in range(k):
        os.link(src / "velodyne" / f"{i:06d}.bin", dst / "velodyne" / f"{i:06d}.bin")
        os.link(src / "points_meta" / f"{i:06d}.npz", dst / "points_meta" / f"{i:06d}.npz")
    seq_dir = dst
t0 = time.perf_counter()
r = build_map(seq_dir, out, settings)
print(json.dumps({"scans": r.scans_used, "seconds": time.perf_counter() - t0, "triangles": r.triangles,
                  "triangles_before_simplify": r.triangles_before_simplify, "tiles": r.tiles,
                  "points": r.points_used, "stage_seconds": r.seconds,
                  "peak_rss_mb": r.peak_rss_mb,
                  "peak_rss_main_mb": r.peak_rss_main_mb, "peak_rss_tile_jobs_mb": r.peak_rss_tile_jobs_mb}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="town_small")
    ap.add_argument("--frames", type=int, default=2500, help="frames of the mapping drive to record")
    ap.add_argument("--steps", default="100,200,400,0", help="scan counts to build from (0 = all)")
    ap.add_argument("--depth", type=int, default=9, help="Poisson depth")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", default="/tmp/rangemcl-bench-map")
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args()
    work = Path(args.work)
    seq = work / f"{args.scene}_mapping_{args.frames}_s{args.seed}"
    if not (seq / "meta.yaml").exists() or "complete: true" not in (seq / "meta.yaml").read_text():
        from simbed.record import record

        t0 = time.perf_counter()
        s = record(args.scene, "mapping", "os1-64", seq, frames=args.frames, seed=args.seed, overwrite=True)
        print(f"recorded {s.frames} frames ({s.distance_driven_m:.0f} m) in {time.perf_counter() - t0:.0f} s")
    rows = []
    for k in [int(x) for x in args.steps.split(",")]:
        out = work / f"map_{args.scene}_{k or 'all'}"
        proc = subprocess.run(
            [sys.executable, "-c", BUILD, str(seq), str(out), str(k), str(args.depth)],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            print(proc.stderr[-2000:], file=sys.stderr)
            raise SystemExit(f"build with {k} scans failed")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"{row['scans']:>6} scans  {row['points'] / 1e6:6.1f} M points  {row['tiles']:>3} tiles  "
            f"{row['seconds']:7.1f} s  (scans {row['stage_seconds']['scans']:.0f} s, "
            f"tiles {row['stage_seconds']['tiles']:.0f} s)  peak {row['peak_rss_mb']:6.0f} MB "
            f"(main {row['peak_rss_main_mb']:.0f}, tile jobs {row['peak_rss_tile_jobs_mb']:.0f})  "
            f"{row['triangles_before_simplify']:>9,} -> {row['triangles']:>9,} triangles"
        )
    print(f"(this process: peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB)")
    if args.json:
        Path(args.json).write_text(
            json.dumps({"scene": args.scene, "depth": args.depth, "rows": rows}, indent=2)
        )


if __name__ == "__main__":
    main()
