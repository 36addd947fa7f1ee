#!/usr/bin/env python3
"""How much the localizer's accuracy leans on the odometry: the same recorded drive
localized with its odometry miscalibrated on purpose.

    python tools/odometry_sweep.py --seq out/test_run --map out/town_small_map --out out/odo_sweep
    python tools/odometry_sweep.py --seq SEQ --map MAP --out OUT --scales 0.95,1.05 --mode global

For each setting the drive's ``odometry.txt`` is rewritten (:func:`rangemcl.datasets.kitti.perturb_odometry`:
every frame's step with its translation scaled, its yaw change plus a gyro bias x the frame's duration)
into a copy of the sequence whose other files are hard links (or copies) of the original's, and
``rangemcl localize`` runs on it (tracking from the first true pose by default; ``--mode global`` for the
time after global convergence). Reported per setting, over the frames after convergence: location RMSE,
yaw RMSE, mean and largest along-track and cross-track error (signed, in the true pose's frame:
:func:`rangemcl.evaluation.metrics.track_errors`). The table goes to ``OUT/odometry_sweep.json`` and is
printed;
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


def _calibration(run: Path, seq, frames: np.ndarray, scale: float, bias_deg_s: float) -> dict:
    """The online calibration's last estimates (frames.csv) beside the truth of this run's odometry: the
    scale that maps its distance onto the true distance, the bias that maps its yaw change onto the true
    one (over the frames run), and the distance driven until the estimates came within 0.3 % and
    0.05 deg/s of them for good."""
    from rangemcl.se2 import se2_between, xyyaw_of

    cols = (run / "frames.csv").read_text().splitlines()[0].split(",")
    if "odometry_scale" not in cols:
        return {}
    data = np.loadtxt(
        run / "frames.csv",
        delimiter=",",
        skiprows=1,
        usecols=(cols.index("odometry_scale"), cols.index("gyro_bias_deg_s")),
    ).reshape(-1, 2)
    truth = xyyaw_of(seq.poses)[frames]
    odo = xyyaw_of(seq.odometry)[frames]
    true_steps = np.array([se2_between(truth[k - 1], truth[k]) for k in range(1, len(frames))])
    odo_steps = np.array([se2_between(odo[k - 1], odo[k]) for k in range(1, len(frames))])
    true_dist = np.hypot(true_steps[:, 0], true_steps[:, 1])
    odo_dist = scale * np.hypot(odo_steps[:, 0], odo_steps[:, 1])
    dt = np.diff(seq.times[frames])
    scale_truth = float(true_dist.sum() / odo_dist.sum())
    bias_truth = math.degrees(
        float(
            (odo_steps[:, 2].sum() + math.radians(bias_deg_s) * dt.sum() - true_steps[:, 2].sum()) / dt.sum()
        )
    )
    driven = np.concatenate([[0.0], np.cumsum(true_dist)])

    def settled(values: np.ndarray, target: float, tol: float) -> float | None:
        bad = np.flatnonzero(~(np.abs(values - target) <= tol))
        if len(bad) == len(values):
            return None
        return float(driven[bad[-1] + 1]) if len(bad) else 0.0

    return {
        "scale_estimate": float(data[-1, 0]),
        "scale_truth": scale_truth,
        "scale_within_0.3pct_after_m": settled(data[:, 0], scale_truth, 0.003 * scale_truth),
        "bias_estimate_deg_s": float(data[-1, 1]),
        "bias_truth_deg_s": bias_truth,
        "bias_within_0.05_after_m": settled(data[:, 1], bias_truth, 0.05),
        "driven_m": float(driven[-1]),
    }


def _plot(out: Path, rows: list[dict]) -> None:
    """Per-frame calibration estimates of every run against the distance driven."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for r in rows:
        run = out / f"scale{r['scale']:.3f}-bias{r['gyro_bias_deg_s']:.2f}"
        cols = (run / "frames.csv").read_text().splitlines()[0].split(",")
        if "odometry_scale" not in cols or "scale_truth" not in r:
            continue
        d = np.loadtxt(
            run / "frames.csv",
            delimiter=",",
            skiprows=1,
            usecols=(cols.index("odometry_scale"), cols.index("gyro_bias_deg_s")),
        )
        x = np.linspace(0.0, r["driven_m"], len(d))
        label = f"odometry x{r['scale']:.2f}, gyro +{r['gyro_bias_deg_s']:.1f} deg/s"
        line = ax1.plot(x, d[:, 0], label=label)[0]
        ax1.axhline(r["scale_truth"], color=line.get_color(), ls=":", lw=0.8)
        ax2.plot(x, d[:, 1], color=line.get_color())
        ax2.axhline(r["bias_truth_deg_s"], color=line.get_color(), ls=":", lw=0.8)
    ax1.set_ylabel("scale estimate")
    ax2.set_ylabel("gyro bias estimate (deg/s)")
    ax2.set_xlabel("distance driven (m; frames spaced evenly)")
    ax1.legend(fontsize=7)
    ax1.set_title("online odometry calibration (dotted: the truth of each run's odometry)")
    fig.tight_layout()
    fig.savefig(out / "calibration.png", dpi=110)
    plt.close(fig)


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
    from rangemcl.datasets.kitti import load_sequence, perturb_odometry, write_poses_txt
    from rangemcl.evaluation.metrics import pose_errors, track_errors
    from rangemcl.localization import LocalizerSettings
    from rangemcl.localization.pipeline import RunOptions, localize_sequence
    from rangemcl.se2 import xyyaw_of

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
        row.update(_calibration(run, seq, frames, scale, bias))
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
    _plot(out, rows)
    print(
        "| scale | gyro bias | location RMSE | yaw RMSE | along mean / largest | cross mean / largest "
        "| scale est. / truth (settled after) | bias est. / truth (settled after) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "location_rmse_m" not in r:
            print(f"| {r['scale']:.2f} | {r['gyro_bias_deg_s']:.1f}°/s | not converged | | | | | |")
            continue
        print(
            f"| {r['scale']:.2f} | {r['gyro_bias_deg_s']:.1f}°/s | {r['location_rmse_m']:.3f} m | "
            f"{r['yaw_rmse_deg']:.2f}° | {r['along_mean_m']:+.3f} / {r['along_max_m']:.3f} m | "
            f"{r['cross_mean_m']:+.3f} / {r['cross_max_m']:.3f} m | {_cal(r, 'scale')} | {_cal(r, 'bias')} |"
        )


def _cal(r: dict, what: str) -> str:
    if what == "scale" and "scale_estimate" in r:
        after = r["scale_within_0.3pct_after_m"]
        when = "never" if after is None else f"{after:.0f} m"
        return f"{r['scale_estimate']:.4f} / {r['scale_truth']:.4f} ({when})"
    if what == "bias" and "bias_estimate_deg_s" in r:
        after = r["bias_within_0.05_after_m"]
        return (
            f"{r['bias_estimate_deg_s']:+.3f} / {r['bias_truth_deg_s']:+.3f}°/s "
            f"({'never' if after is None else f'{after:.0f} m'})"
        )
    return "off"


if __name__ == "__main__":
    main()
