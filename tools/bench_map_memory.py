#!/usr/bin/env python3
"""The localizer with the whole map against the localizer within memory budgets
(``rangemcl localize --map-memory MB``): peak memory of the whole process, frame time, the longest wait on
a tile load, the updates that went without a wanted tile, and the accuracy, on the same drive and seed.

Each run is a fresh ``rangemcl localize`` process under ``/usr/bin/time -v`` (its peak resident size is
the process's own, Python, Warp and the sequence included; in MiB, 1,048,576 bytes, where the budget's
MB are 1,000,000 bytes), the runs alternating over ``--repeats``:

    python tools/bench_map_memory.py --seq out/demo/test_drive --map out/demo/map --budgets 10 20 40
    python tools/bench_map_memory.py --seq DRIVE --map MAP --mode global --frames 100 --budgets 500

The map must be of format 2 (``rangemcl map-upgrade`` rewrites an older one). Medians of the repeats;
the machine is shared, so compare within one run.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def run_once(args, budget: float | None, out: Path) -> dict:
    cmd = [
        "/usr/bin/time",
        "-v",
        sys.executable,
        "-m",
        "rangemcl.cli",
        "localize",
        str(args.seq),
        "--map",
        str(args.map),
        "--out",
        str(out),
        "--mode",
        args.mode,
        "--frames",
        str(args.frames),
        "--seed",
        str(args.seed),
        "--threads",
        str(args.threads),
        "--no-plots",
    ]
    if budget is not None:
        cmd += ["--map-memory", str(budget)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr).group(1))
    summary = json.loads((out / "summary.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    after = [float(r["seconds"]) for r in rows if r["converged"] == "1"]
    updates = [r for r in rows if int(r["map_tiles"]) >= 0]
    mem = summary.get("map_memory", {})
    return {
        "peak_mib": peak_kb / 1024,  # MiB: /usr/bin/time's kbytes are KiB
        "ms_after": 1e3 * statistics.median(after) if after else float("nan"),
        "longest_wait_ms": mem.get("longest_wait_ms", float("nan")),
        "startup_load_ms": mem.get("startup_load_ms", float("nan")),
        "waits": sum(float(r["map_load_ms"]) > 0 for r in updates),
        "left_out_updates": mem.get("updates_with_tiles_left_out", 0),
        "held_mb_max": max((float(r["map_mb"]) for r in updates), default=float("nan")),
        "tile_loads": mem.get("tile_loads", 0),
        "converged_frame": summary.get("converged_frame"),
        "success": metrics.get("success"),
        "rmse_m": metrics.get("location_rmse_m"),
        "estimate": (out / "estimate_kitti.txt").read_bytes(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seq", type=Path, required=True)
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--budgets", type=float, nargs="+", required=True, help="MB, each a run")
    ap.add_argument("--mode", default="tracking", choices=("tracking", "global"))
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    variants = [None, *args.budgets]
    results: dict = {v: [] for v in variants}
    with tempfile.TemporaryDirectory(prefix="bench_map_memory_") as tmp:
        for rep in range(args.repeats):
            for v in variants:
                out = Path(tmp) / f"{'whole' if v is None else v}-{rep}"
                results[v].append(run_once(args, v, out))
    whole = results[None][0]["estimate"]
    print(f"{args.mode}, {args.frames} frames, seed {args.seed}, {args.threads} threads; map {args.map}")
    print(
        "| map held | peak memory (process) | ms/frame after convergence | load before the first frame | "
        "longest wait of a frame on a load | updates that waited | updates with tiles left out | "
        "most held (MB) | tile loads | "
        "converged at | success | RMSE | estimates = whole map's |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    table = {}
    for v in variants:
        rs = results[v]

        def med(key, rs=rs):
            xs = [r[key] for r in rs if r[key] is not None]
            return statistics.median(xs) if xs else float("nan")

        r0 = rs[0]
        row = {
            "peak_mib": med("peak_mib"),
            "ms_after": med("ms_after"),
            "longest_wait_ms": max(r["longest_wait_ms"] for r in rs),
            "startup_load_ms": med("startup_load_ms"),
            "waits": max(r["waits"] for r in rs),
            "left_out_updates": r0["left_out_updates"],
            "held_mb_max": r0["held_mb_max"],
            "tile_loads": r0["tile_loads"],
            "converged_frame": r0["converged_frame"],
            "success": r0["success"],
            "rmse_m": r0["rmse_m"],
            "same_as_whole": r0["estimate"] == whole,
        }
        table["whole" if v is None else str(v)] = row
        name = "whole map" if v is None else f"`--map-memory {v:g}`"
        if v is None:
            cells = [f"{row['peak_mib']:.0f} MiB", f"{row['ms_after']:.1f}", "—", "—", "—", "—", "—", "—"]
        else:
            cells = [
                f"{row['peak_mib']:.0f} MiB ({row['peak_mib'] / table['whole']['peak_mib']:.2f}×)",
                f"{row['ms_after']:.1f} ({row['ms_after'] / table['whole']['ms_after']:.2f}×)",
                f"{row['startup_load_ms']:.0f} ms",
                f"{row['longest_wait_ms']:.0f} ms",
                str(row["waits"]),
                str(row["left_out_updates"]),
                f"{row['held_mb_max']:.1f}",
                str(row["tile_loads"]),
            ]
        rmse = "—" if row["rmse_m"] is None else f"{row['rmse_m']:.4f} m"
        same = "—" if v is None else ("yes" if row["same_as_whole"] else "no")
        print(
            f"| {name} | "
            + " | ".join([*cells, str(row["converged_frame"]), str(row["success"]), rmse, same])
            + " |"
        )
    if args.json:
        args.json.write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
