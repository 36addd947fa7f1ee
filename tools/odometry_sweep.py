#!/usr/bin/env python3
"""How much the localizer's accuracy leans on the odometry (issue 19, step 1): the same recorded drive
localized with its odometry miscalibrated on purpose.

    python tools/odometry_sweep.py --seq out/test_run --map out/town_small_map --out out/odo_sweep
    python tools/odometry_sweep.py --seq SEQ --map MAP --out OUT --scales 0.95,1.05 --mode global

For each setting the drive's ``odometry.txt`` is rewritten (:func:`rangemcl.dataset.perturb_odometry`:
every frame's step with its translation scaled, its yaw change plus a gyro bias x the frame's duration)
into a copy of the sequence whose other files are hard links (or copies) of the original's, and
``rangemcl localize`` runs on it (tracking from the first true pose by default; ``--mode global`` for the
time after global convergence). Reported per setting, over the frames after convergence: location RMSE,
yaw RMSE, mean and largest along-track and cross-track error (signed, in the true pose's frame:
:func:`rangemcl.evaluate.track_errors`). The table goes to ``OUT/odometry_sweep.json`` and is printed;
runs whose ``summary.json`` exists are reused.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _copy_sequence(src: Path, dst: Path) -> None:
    """``dst`` with every file of ``src`` hard-linked (copied across file systems), odometry.txt aside."""
    for root, _dirs, files in os.walk(src):
        rel = Path(root).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for f in files:
            if rel == Path(".") and f == "odometry.txt":
                continue
            a, b = Path(root) / f, dst / rel / f
            try:
                os.link(a, b)
            except OSError:
                shutil.copy2(a, b)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True)
    ap.add_argument("--map", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--scales", default="0.95,0.97,1.0,1.03,1.05", help="translation scales")
    ap.add_argument("--gyro-biases", default="0.5", help="gyro biases in deg/s (each with scale 1)")
    ap.add_argument("--mode", default="tracking", choices=["tracking", "global"])
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", help="localizer settings YAML")
    args = ap.parse_args()

    from rangemcl.config import load_config
    from rangemcl.dataset import load_sequence, perturb_odometry, write_poses_txt
    from rangemcl.evaluate import pose_errors, track_errors, xyyaw_of
    from rangemcl.localize import RunOptions, localize_sequence
    from rangemcl.mcl import LocalizerSettings

    seq = load_sequence(args.seq, require_poses=True)
    if seq.odometry is None or seq.times is None:
        raise SystemExit(f"odometry_sweep.py: error: {seq.root} needs odometry.txt and times.txt")
    truth = xyyaw_of(seq.poses)
    settings = [(s, 0.0) for s in _floats(args.scales)] + [(1.0, b) for b in _floats(args.gyro_biases)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scale, bias in settings:
        name = f"scale{scale:.3f}-bias{bias:.2f}"
        run = out / name
        if not (run / "summary.json").is_file():
            seq_copy = out / "sequences" / name
            if seq_copy.exists():
                shutil.rmtree(seq_copy)
            _copy_sequence(seq.root, seq_copy)
            odo = perturb_odometry(seq.odometry, seq.times, scale=scale, yaw_bias_rad_s=math.radians(bias))
            write_poses_txt(seq_copy / "odometry.txt", odo)
            localize_sequence(
                seq_copy,
                args.map,
                run,
                load_config(LocalizerSettings, args.config),
                RunOptions(mode=args.mode, seed=args.seed, frames=args.frames, plots=False),
            )
            shutil.rmtree(seq_copy)
        s = json.loads((run / "summary.json").read_text())
        est = np.loadtxt(run / "frames.csv", delimiter=",", skiprows=1, usecols=(0, 2, 3, 4))
        frames = est[:, 0].astype(int)
        conv = s["converged_frame"]
        keep = frames >= (conv if conv is not None else frames[-1] + 1)
        row = {"scale": scale, "gyro_bias_deg_s": bias, "converged_frame": conv, "frames": int(keep.sum())}
        if keep.any():
            e, t = est[keep, 1:], truth[frames[keep]]
            loc, yaw = pose_errors(e, t)
            along, cross = track_errors(e, t)
            row.update(
                location_rmse_m=float(np.sqrt(np.mean(loc**2))),
                yaw_rmse_deg=float(np.sqrt(np.mean(yaw**2))),
                along_mean_m=float(along.mean()),
                along_max_m=float(np.abs(along).max()),
                cross_mean_m=float(cross.mean()),
                cross_max_m=float(np.abs(cross).max()),
            )
        rows.append(row)
        print(json.dumps(row), flush=True)
    table = {"sequence": str(seq.root), "map": args.map, "mode": args.mode, "rows": rows}
    (out / "odometry_sweep.json").write_text(json.dumps(table, indent=2) + "\n")
    print("| scale | gyro bias | location RMSE | yaw RMSE | along mean / largest | cross mean / largest |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        if "location_rmse_m" not in r:
            print(f"| {r['scale']:.2f} | {r['gyro_bias_deg_s']:.1f}°/s | not converged | | | |")
            continue
        print(
            f"| {r['scale']:.2f} | {r['gyro_bias_deg_s']:.1f}°/s | {r['location_rmse_m']:.3f} m | "
            f"{r['yaw_rmse_deg']:.2f}° | {r['along_mean_m']:+.3f} / {r['along_max_m']:.3f} m | "
            f"{r['cross_mean_m']:+.3f} / {r['cross_max_m']:.3f} m |"
        )


if __name__ == "__main__":
    main()
