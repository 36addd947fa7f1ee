#!/usr/bin/env python3
"""kiss-icp LiDAR odometry against the wheel odometry on recorded drives.

    python tools/odometry_drift.py SEQ [SEQ ...] [--frames 300] [--out drift.json]

For each KITTI-layout sequence folder (with ``poses.txt``; ``odometry.txt`` optional) kiss-icp runs over
the first ``--frames`` frames (:class:`rangemcl.datasets.lidar_odometry.KissIcpOdometry`, set up from the
sequence's sensor spec), and both odometries are measured against the truth
(:func:`rangemcl.datasets.lidar_odometry.odometry_drift`): translation error % and rotation error deg/100
m, means
over all 20/50/100 m segments, and the final drift as % of the distance driven. Two markdown tables are
printed: planar (x, y, yaw: what the localizer uses) and 3D (the KITTI benchmark's metric, height and
tilt errors included), with kiss-icp's median seconds per frame (registration only, not reading).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from rangemcl.datasets.kitti import load_sequence
from rangemcl.datasets.lidar_odometry import KissIcpOdometry, odometry_drift
from rangemcl.errors import InputError


def run_kiss_icp(seq, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Poses ``(frames, 4, 4)``, seconds of each registration and points of each scan ``(frames,)``, and
    the frames whose poses were predicted."""
    odo = KissIcpOdometry.for_source(seq)
    poses = np.empty((frames, 4, 4))
    seconds = np.empty(frames)
    points_per_scan = np.empty(frames, np.int64)
    for i in range(frames):
        points, time_s = seq.scan(i), seq.point_meta(i).get("time_s")
        clock = time.perf_counter()
        poses[i] = odo.register_frame(points, time_s)
        seconds[i] = time.perf_counter() - clock
        points_per_scan[i] = len(points)
    return poses, seconds, points_per_scan, odo.predicted


def measure(path: Path, frames: int | None) -> dict:
    seq = load_sequence(path, require_poses=True)
    n = len(seq) if frames is None else min(frames, len(seq))
    clock = time.perf_counter()
    poses, seconds, points_per_scan, predicted = run_kiss_icp(seq, n)
    wall = time.perf_counter() - clock
    if predicted:
        warnings.warn(f"{path}: kiss-icp predicted frames {predicted} (no usable points)", stacklevel=1)
    truth = seq.poses[:n]
    sensor = seq.meta.get("sensor", {}) if isinstance(seq.meta, dict) else {}
    row = {
        "sequence": str(path),
        "sensor": sensor.get("name", "?") if isinstance(sensor, dict) else "?",
        "frames": n,
        "points_per_scan_median": float(np.median(points_per_scan)),
        "kiss_icp_seconds_per_frame_median": float(np.median(seconds)),
        "kiss_icp_seconds_total": wall,
        "kiss_icp_predicted_frames": predicted,
        "kiss_icp": {
            "planar": odometry_drift(poses, truth, planar=True),
            "3d": odometry_drift(poses, truth),
        },
        "wheel": None,
    }
    if seq.odometry is not None:
        wheel = seq.odometry[:n]
        row["wheel"] = {
            "planar": odometry_drift(wheel, truth, planar=True),
            "3d": odometry_drift(wheel, truth),
        }
    row["distance_m"] = row["kiss_icp"]["planar"]["distance_m"]
    return row


def _num(value, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _cells(drift: dict | None) -> list[str]:
    if drift is None:
        return ["–", "–", "–"]
    return [
        _num(drift["t_err_pct"], 2),
        _num(drift["r_err_deg_per_100m"], 2),
        _num(drift["final_drift_pct"], 2),
    ]


def table(rows: list[dict], kind: str) -> str:
    head = (
        "| sequence | sensor | frames | distance m | wheel t % | wheel r °/100 m | wheel final % "
        "| kiss-icp t % | kiss-icp r °/100 m | kiss-icp final % | kiss-icp s/frame |"
    )
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        wheel = r["wheel"][kind] if r["wheel"] is not None else None
        cells = [
            Path(r["sequence"]).name,
            r["sensor"],
            str(r["frames"]),
            f"{r['distance_m']:.0f}",
            *_cells(wheel),
            *_cells(r["kiss_icp"][kind]),
            f"{r['kiss_icp_seconds_per_frame_median']:.3f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+", type=Path, help="KITTI-layout sequence folders")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each (default: all)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON to this file")
    args = parser.parse_args(argv)
    if args.frames is not None and args.frames < 2:
        parser.error("--frames must be >= 2")
    rows = []
    try:
        for path in args.sequences:
            rows.append(measure(path, args.frames))
            print(f"{path}: done", file=sys.stderr)
    except InputError as err:
        print(f"odometry_drift: {err}", file=sys.stderr)
        return 2
    print("Planar (x, y, yaw: what the localizer uses); t, r: means over 20/50/100 m segments\n")
    print(table(rows, "planar"))
    print("\n3D (the KITTI odometry metric: height and roll/pitch errors count too)\n")
    print(table(rows, "3d"))
    if args.out is not None:
        args.out.write_text(json.dumps({"frames": args.frames, "sequences": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
