#!/usr/bin/env python3
"""A map too large to hold whole, tracked within a memory budget.

Lays ``--copies`` × ``--copies`` copies of a built map's tiles side by side (each shifted by the map's
extent rounded to whole tiles; where two copies meet, their faces share the tile they fall in), with
the coarse level, the ground grid and the drive copied the same way, then tracks a test drive of the
source map in the copy that sits where the source does: once in the source map held whole, once in the
dense map within ``--budget`` MB. Prints the dense map's size and, for both runs, the peak memory of the
whole process, the frame time after convergence (and the ratio, measured in one run), the longest wait on
a tile load and the accuracy.

    python tools/bench_large_map.py --map out/demo/map --seq out/demo/test_drive --copies 10 \\
        --out DATA/dense_map --budget 500

The dense map is written once (``--out``, reused when it is there). Needs a map of format 2 with a
coarse level (``rangemcl build-map`` writes one; older maps: ``rangemcl map-coarse``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_map_memory import run_once

from rangemcl.maps.meshmap import GroundGrid, read_ground_and_drive, read_map_yaml, write_map_files
from rangemcl.maps.store import TileStore, write_index, write_tile


def _faces_in(v, f, g, ij, origin, size):
    """The part of a mesh whose face centroids lie in tile ``ij``, its vertices compacted."""
    tri = v[f, :2]
    c = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3.0
    k = np.floor((c - origin) / size)
    sel = (k[:, 0] == ij[0]) & (k[:, 1] == ij[1])
    if not sel.any():
        return None
    used, inv = np.unique(f[sel], return_inverse=True)
    return v[used], inv.reshape(-1, 3).astype(np.int32), g[used]


def build_dense(src_dir: Path, out: Path, copies: int) -> dict:
    store = TileStore.open(src_dir)
    _, doc = read_map_yaml(src_dir)
    size, origin = store.tile_size_m, store.origin_xy
    ij = store.tiles
    x0, y0, _, x1, y1, _ = store.extent()
    # the shift between copies: the map's extent in whole tiles, rounded (a sliver may overlap the next copy)
    span = np.maximum(1, np.rint(np.array([x1 - x0, y1 - y0]) / size)).astype(int)
    lo = -(copies // 2)
    offsets = [(a, b) for a in range(lo, lo + copies) for b in range(lo, lo + copies)]
    full = [store.read(k) for k in range(len(store.entries))]
    coarse = [store.read(k, coarse=True) for k in range(len(store.entries))]
    targets = sorted({(int(i + a * span[0]), int(j + b * span[1])) for a, b in offsets for i, j in ij})
    tmp = out.with_name(out.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    entries = []
    t0 = time.perf_counter()
    for n, (ti, tj) in enumerate(targets):
        levels = []
        for source in (full, coarse):
            vs, fs, gs, offset = [], [], [], 0
            for a, b in offsets:
                for k, (si, sj) in enumerate(ij):
                    if abs(si + a * span[0] - ti) > 1 or abs(sj + b * span[1] - tj) > 1:
                        continue
                    v, f, g = source[k]
                    v = v + np.array([a * span[0] * size, b * span[1] * size, 0.0])
                    part = _faces_in(v, f, g, (ti, tj), origin, size)
                    if part is None:
                        continue
                    vs.append(part[0])
                    fs.append(part[1] + np.int32(offset))
                    gs.append(part[2])
                    offset += len(part[0])
            levels.append((vs, fs, gs))
        (vs, fs, gs), (cvs, cfs, cgs) = levels
        if not fs:
            continue
        e = write_tile(tmp, (ti, tj), np.concatenate(vs), np.concatenate(fs), np.concatenate(gs))
        if cfs:
            c = write_tile(
                tmp, (ti, tj), np.concatenate(cvs), np.concatenate(cfs), np.concatenate(cgs), coarse=True
            )
            e = replace(e, coarse=c)
        entries.append(e)
        if n % 25 == 0:
            print(f"  tile {n + 1}/{len(targets)}, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    write_index(tmp, size, origin, entries)
    ground, drive = read_ground_and_drive(src_dir)
    step = np.rint(span * size / ground.cell_m).astype(int)
    ny, nx = ground.heights.shape
    heights = np.full((ny + (copies - 1) * step[1], nx + (copies - 1) * step[0]), np.nan, np.float32)
    for a, b in offsets:
        x0, y0 = (a - lo) * step[0], (b - lo) * step[1]
        heights[y0 : y0 + ny, x0 : x0 + nx] = np.fmax(heights[y0 : y0 + ny, x0 : x0 + nx], ground.heights)
    grid = GroundGrid(ground.origin_xy + lo * step * ground.cell_m, ground.cell_m, heights)
    drives = None
    if drive is not None:
        drives = np.concatenate(
            [drive + np.array([a * span[0] * size, b * span[1] * size]) for a, b in offsets]
        )
    meta = {**doc["meta"], "dense_copies": f"{copies} x {copies} copies of {src_dir.resolve()}"}
    write_map_files(tmp, entries, ground=grid, drive_xy=drives, tile_size_m=size, meta=meta)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return {"seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, required=True, help="the source map (format 2, coarse level)")
    ap.add_argument("--seq", type=Path, required=True, help="a test drive in the source map")
    ap.add_argument("--copies", type=int, default=10, help="copies per side")
    ap.add_argument("--out", type=Path, required=True, help="the dense map folder (written once)")
    ap.add_argument("--budget", type=float, default=500.0, help="MB for the dense map")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run both this many times, the order alternating; the table gives the median frame time and "
        "the ratio is the median of the runs' ratios (the machine is shared)",
    )
    args = ap.parse_args()
    if not TileStore.open(args.map).has_coarse:
        sys.exit(f"{args.map}: no coarse level (rangemcl map-coarse {args.map})")
    if not (args.out / "map.yaml").is_file():
        print(f"writing {args.out} ({args.copies} x {args.copies} copies of {args.map}) ...", file=sys.stderr)
        build_dense(args.map, args.out, args.copies)
    dense = TileStore.open(args.out)
    x0, y0, _, x1, y1, _ = dense.extent()
    area = (x1 - x0) * (y1 - y0) / 1e6
    disk = dense.bytes_on_disk + sum(e.coarse.bytes for e in dense.entries if e.coarse is not None)
    print(
        f"dense map {args.out}: {area:.2f} km², {dense.n_triangles:,} triangles in {len(dense.entries)} "
        "tiles, "
        f"{disk / 1e9:.2f} GB on disk; whole, it would take about {dense.n_triangles * 165 / 1e9:.1f} GB "
        f"in the localizer (165 B a triangle)"
    )
    t = time.perf_counter()
    TileStore.open(args.out)
    open_ms = (time.perf_counter() - t) * 1e3
    ns = argparse.Namespace(**{**vars(args), "mode": "tracking"})
    budget_of = {"source, whole": None, "dense, budget": args.budget}
    runs = {name: [] for name in budget_of}
    cases = [("source, whole", args.map, None), ("dense, budget", args.out, args.budget)]
    with tempfile.TemporaryDirectory(prefix="bench_large_map_") as tmp:
        for rep in range(max(1, args.repeats)):
            for name, map_dir, budget in cases if rep % 2 == 0 else cases[::-1]:
                ns.map = map_dir
                runs[name].append(run_once(ns, budget, Path(tmp) / f"{name.replace(', ', '_')}_{rep}"))
    ratios = [
        b["ms_after"] / a["ms_after"]
        for a, b in zip(runs["source, whole"], runs["dense, budget"], strict=True)
    ]
    rows = {}
    for name, rs in runs.items():  # the first run's row, with the median frame time and the worst waits
        rows[name] = {
            **rs[0],
            "ms_after": float(np.median([r["ms_after"] for r in rs])),
            "peak_mib": max(r["peak_mib"] for r in rs),
            "longest_wait_ms": max(r["longest_wait_ms"] for r in rs),
            "waits": max(r["waits"] for r in rs),
        }
    print(
        f"tracking {args.seq}, {args.frames} frames, {args.threads} threads; "
        f"dense index opened in {open_ms:.0f} ms"
    )
    print(
        "| map | peak memory (process) | ms/frame after convergence | load before the first frame | "
        "longest wait of a frame on a load | updates that waited | RMSE |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        held = budget_of[name] is not None
        start = f"{r['startup_load_ms']:.0f} ms" if held else "—"
        wait = f"{r['longest_wait_ms']:.0f} ms" if held else "—"
        waits = str(r["waits"]) if held else "—"
        rmse = "—" if r["rmse_m"] is None else f"{r['rmse_m']:.4f} m"
        cells = [f"{r['peak_mib']:.0f} MiB", f"{r['ms_after']:.1f}", start, wait, waits, rmse]
        print(f"| {name} | " + " | ".join(cells) + " |")
    if len(ratios) > 1:
        print(
            f"frame time ratio dense/source: {float(np.median(ratios)):.2f} (median of {len(ratios)} runs: "
            + ", ".join(f"{r:.2f}" for r in ratios)
            + ")"
        )
    else:
        print(f"frame time ratio dense/source: {ratios[0]:.2f}")
    if args.json:
        out = {k: {kk: vv for kk, vv in v.items() if kk != "estimate"} for k, v in rows.items()}
        out["ratios"] = ratios
        out["dense"] = {
            "area_km2": area,
            "triangles": dense.n_triangles,
            "tiles": len(dense.entries),
            "bytes_on_disk": disk,
        }
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
