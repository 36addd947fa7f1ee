#!/usr/bin/env python3
"""Localization accuracy on a recorded drive: global localization from several start points along it,
and the kidnapped car (teleported mid-run), with the paper's metrics.

    python tools/accuracy_localize.py --seq SEQ --map MAP --out out/accuracy
    python tools/accuracy_localize.py --seq SEQ --map MAP --out out/accuracy_plain --config plain.yaml
    python tools/accuracy_localize.py --seq SEQ --map MAP --out out/kidnap --kidnap

* global (default): ``--starts`` runs, each from a start frame evenly spread along the drive, ``--frames``
  frames long, with no prior (``--particles``, default 10,000), seed = run index. Success, location RMSE
  and yaw RMSE per run (``rangemcl.evaluation.metrics``), then over the runs: successes, and the RMSE over all
  frames of the successful runs (as the paper reports one figure per sensor).
* ``--kidnap``: each run starts tracking at its start frame; halfway, the scans jump to another part of
  the drive (half the drive ahead) while the odometry carries on as if nothing happened. A run
  relocalizes when the filter notices (a recovery), converges again and then passes the success check.

Each run writes a ``rangemcl localize`` results folder under ``--out``; the table goes to
``OUT/accuracy.json`` and is printed. Runs whose ``summary.json`` exists are reused (resumable).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True)
    ap.add_argument("--map", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--starts", type=int, default=10)
    ap.add_argument("--frames", type=int, default=250, help="frames per run (kidnap: twice --half)")
    ap.add_argument("--half", type=int, default=150, help="kidnap: frames before and after the jump")
    ap.add_argument("--particles", type=int, default=None)
    ap.add_argument("--config", help="localizer settings YAML")
    ap.add_argument("--kidnap", action="store_true")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()

    from rangemcl.config import load_config
    from rangemcl.datasets.kitti import load_sequence, splice_kidnapped
    from rangemcl.localization import LocalizerSettings
    from rangemcl.localization.pipeline import RunOptions, localize_sequence

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seq = load_sequence(args.seq)
    n = len(seq)
    runs = []
    frames_after: dict[int, int] = {}  # frames from convergence to the end, per run
    for k in range(args.starts):
        settings = load_config(LocalizerSettings, args.config)
        run_dir = out / f"run_{k:02d}"
        if args.kidnap:
            a = int(round(k * (n - args.half) / args.starts)) % max(1, n - args.half)
            b = (a + n // 2) % max(1, n - args.half)
            opts = RunOptions(
                mode="tracking", seed=k, device=args.device, plots=k == 0, particles=args.particles
            )
            if not (run_dir / "summary.json").is_file():
                seq_k = out / f"kidnap_seq_{k:02d}"
                splice_kidnapped(args.seq, seq_k, a, b, args.half)
                localize_sequence(seq_k, args.map, run_dir, settings, opts)
                shutil.rmtree(seq_k)
            start = {"frames": [a, b], "jump_at": args.half}
        else:
            first = int(round(k * (n - args.frames) / max(1, args.starts - 1))) if args.starts > 1 else 0
            opts = RunOptions(
                mode="global",
                seed=k,
                device=args.device,
                first_frame=first,
                frames=args.frames,
                particles=args.particles,
                plots=k == 0,
            )
            if not (run_dir / "summary.json").is_file():
                localize_sequence(args.seq, args.map, run_dir, settings, opts)
            start = {"first_frame": first}
        s = json.loads((run_dir / "summary.json").read_text())
        m = json.loads((run_dir / "metrics.json").read_text())
        ok = bool(m["success"]) and (not args.kidnap or s["recoveries"] >= 1)
        row = {
            "run": k,
            **start,
            "success": ok,
            "converged_frame": s["converged_frame"],
            "frames_to_converge": None
            if s["converged_frame"] is None
            else s["converged_frame"] - s["first_frame"],
            "recoveries": s["recoveries"],
            "recovery_frames": s["recovery_frames"],
            "location_rmse_m": m["location_rmse_m"],
            "location_median_m": m.get("location_median_m"),
            "yaw_rmse_deg": m["yaw_rmse_deg"],
            "wrong_convergences": m.get("wrong_convergences_count", 0),
            "false_alarms": m.get("false_alarms_count", 0),
            "seconds_before_convergence_median": s["seconds_per_frame_before_convergence_median"],
            "hz_after_convergence": s["hz_after_convergence"],
        }
        runs.append(row)
        if ok:
            frames_after[k] = m["frames"] - (m["converged_frame"] - m["first_frame"])
        print(json.dumps(row), flush=True)
    good = [r for r in runs if r["success"]]
    w = np.array([frames_after[r["run"]] for r in good], float)
    loc = np.array([r["location_rmse_m"] for r in good], float)
    yaw = np.array([r["yaw_rmse_deg"] for r in good], float)
    table = {
        "sequence": args.seq,
        "map": args.map,
        "kind": "kidnapped car" if args.kidnap else "global localization",
        "config": args.config,
        "runs": len(runs),
        "successes": len(good),
        # RMSE over all frames after convergence of the successful runs
        "location_rmse_m": float(np.sqrt(np.sum(w * loc**2) / w.sum())) if len(good) else None,
        "yaw_rmse_deg": float(np.sqrt(np.sum(w * yaw**2) / w.sum())) if len(good) else None,
        "frames_to_converge_median": float(np.median([r["frames_to_converge"] for r in good]))
        if good
        else None,
        "location_median_m": float(np.median([r["location_median_m"] for r in good])) if good else None,
        "wrong_convergences": int(sum(r["wrong_convergences"] for r in runs)),
        "false_alarms": int(sum(r["false_alarms"] for r in runs)),
        "per_run": runs,
    }
    (out / "accuracy.json").write_text(json.dumps(table, indent=2) + "\n")

    def fmt(x, digits):
        return "n/a" if x is None else f"{x:.{digits}f}"

    print(
        f"{table['kind']}: {table['successes']}/{table['runs']} successes, location RMSE "
        f"{fmt(table['location_rmse_m'], 3)} m, yaw RMSE {fmt(table['yaw_rmse_deg'], 2)} deg, "
        f"median frames to converge {table['frames_to_converge_median']}, median error after convergence "
        f"{fmt(table['location_median_m'], 3)} m; wrong convergences {table['wrong_convergences']}, "
        f"false alarms {table['false_alarms']}"
    )


if __name__ == "__main__":
    main()
