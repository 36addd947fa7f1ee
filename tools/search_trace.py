#!/usr/bin/env python3
"""Where a global search stands against the truth, update by update: replays ``rangemcl localize
--mode global`` on a recorded drive (the same settings, seed and frames, so the same run as a suite's
trial) and writes, after every frame of the search, where the true pose stands in it.

    python tools/search_trace.py --seq SEQ --map MAP --first 622 --frames 100 --seed 8 --csv trace.csv
    python tools/search_trace.py --seq SEQ --map MAP --first 544 --frames 100 --seed 7 --config my.yaml

(A suite trial's seed is its start's index among the starts: ``…-s622-…-r8-…`` ran with ``--seed 8``.)
Per frame while searching: the leader's distance from the truth; the rank of the hypothesis whose centroid
lies nearest the truth (within ``--near`` metres, else none) and how many nats its share trails the
leader's; and, on rays drawn afresh from the scan as the filter draws them (another generator, so the
filter's run is untouched), the mean residual ``d`` (Eq. 5) at the true pose, the smallest ``d`` among
the cloud's particles within ``--near`` metres and ``--near-deg`` degrees of the truth (with that
particle's offset from it) and the smallest over the whole cloud. Prints a summary: frames until the
leader stayed within 5 m, until convergence, and the medians of the three residuals while the true place
did not lead.

It shows whether a slow search lacked the true place, held it only off its likelihood peak
(``tools/likelihood_peak.py``), or held it on the peak and still lost to a place that fits better.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys

import numpy as np


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="a recorded drive with poses.txt and odometry")
    ap.add_argument("--map", required=True, help="its map folder")
    ap.add_argument("--first", type=int, default=0, help="first frame")
    ap.add_argument("--frames", type=int, default=100, help="frames to replay")
    ap.add_argument("--seed", type=int, default=0, help="the run's seed (rangemcl localize --seed)")
    ap.add_argument("--particles", type=int, default=None, help="particles of the spread (default 10000)")
    ap.add_argument("--config", help="YAML localizer settings, as rangemcl localize --config")
    ap.add_argument("--near", type=float, default=3.0, help="metres from the truth that count as near")
    ap.add_argument("--near-deg", type=float, default=20.0, help="... and degrees")
    ap.add_argument("--csv", help="write the frame-by-frame trace here")
    args = ap.parse_args()

    from rangemcl.config import load_config
    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import frame_period, odometry_xyyaw, resolve_sensor_height
    from rangemcl.maps.view import open_map
    from rangemcl.se2 import se2_between, wrap_angle, xyyaw_of

    seq = load_sequence(args.seq)
    if seq.poses is None:
        raise InputError(f"{args.seq}: the drive has no poses.txt")
    if not 0 <= args.first < len(seq) - 1:
        raise InputError(f"{args.seq}: first frame {args.first} out of range ({len(seq)} frames)")
    settings = load_config(LocalizerSettings, args.config)
    mesh_map, caster = open_map(args.map, settings.map_memory_mb)
    height, _ = resolve_sensor_height(seq, mesh_map, settings)
    loc = build_localizer(
        mesh_map, settings, rng=np.random.default_rng(args.seed), sensor_height_m=height, caster=caster
    )
    loc.spread(args.particles)
    probe_rng = np.random.default_rng(args.seed + 1_000_003)  # the trace's own rays
    truth = xyyaw_of(seq.poses)  # as rangemcl localize scores its estimates
    odo, _source = odometry_xyyaw(seq, False)
    period = frame_period(seq)
    last = min(len(seq), args.first + args.frames)
    rows = []
    converged_frame = None
    for i in range(args.first, last):
        delta = se2_between(odo[i - 1], odo[i]) if i > args.first else np.zeros(3)
        points = seq.scan(i)
        fire = seq.point_meta(i).get("time_s")
        rp = tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None
        dt = None
        if i > args.first:
            dt = float(seq.times[i] - seq.times[i - 1]) if seq.times is not None else period
        was_searching = not loc.converged
        info = loc.step(delta, points, fire_time_s=fire, frame_period_s=period, roll_pitch=rp, dt_s=dt)
        if info.converged and converged_frame is None:
            converged_frame = i
        if not (was_searching and info.updated) or not loc.hypotheses:
            continue
        t = truth[i]
        hyps = loc.hypotheses
        cent = np.array([h.centroid[:2] for h in hyps])
        dist = np.hypot(cent[:, 0] - t[0], cent[:, 1] - t[1])
        k = int(np.argmin(dist))
        row = {
            "frame": i,
            "particles": len(loc.particles),
            "hypotheses": len(hyps),
            "leader_error_m": round(float(dist[0]), 3),
            "true_rank": k if dist[k] <= args.near else "",
            "true_gap_nats": round(hyps[0].log_share - hyps[k].log_share, 3) if dist[k] <= args.near else "",
            "converged": int(info.converged),
        }
        rays = loc.select_rays(
            points,
            probe_rng,
            fire_time_s=fire,
            frame_period_s=period,
            frame_motion=delta,
            roll_pitch=rp,
            sensor_height_m=loc.sensor_height_m,
        )
        if rays is not None:
            p = loc.particles
            d = loc.residuals(rays, np.vstack([t[None], p]))
            off = p - t
            off[:, 2] = wrap_angle(off[:, 2])
            near = (np.hypot(off[:, 0], off[:, 1]) <= args.near) & (
                np.abs(off[:, 2]) <= math.radians(args.near_deg)
            )
            row["d_true_m"] = round(float(d[0]), 4)
            row["d_cloud_best_m"] = round(float(d[1:].min()), 4)
            if near.any():
                j = np.flatnonzero(near)[np.argmin(d[1:][near])]
                c, s = math.cos(t[2]), math.sin(t[2])
                row["d_near_best_m"] = round(float(d[1 + j]), 4)
                row["near_forward_m"] = round(float(c * off[j, 0] + s * off[j, 1]), 3)
                row["near_lateral_m"] = round(float(-s * off[j, 0] + c * off[j, 1]), 3)
                row["near_yaw_deg"] = round(math.degrees(off[j, 2]), 2)
        rows.append(row)
    if not rows:
        raise InputError(f"{args.seq}: no search update between frames {args.first} and {last - 1}")
    fields = [
        "frame",
        "particles",
        "hypotheses",
        "leader_error_m",
        "true_rank",
        "true_gap_nats",
        "d_true_m",
        "d_near_best_m",
        "near_forward_m",
        "near_lateral_m",
        "near_yaw_deg",
        "d_cloud_best_m",
        "converged",
    ]
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fields, restval="")
            w.writeheader()
            w.writerows(rows)
    err = np.array([r["leader_error_m"] for r in rows])
    frames = np.array([r["frame"] for r in rows])
    off_lead = np.flatnonzero(err > 5.0)
    settled = None
    if not len(off_lead):
        settled = frames[0]
    elif off_lead[-1] + 1 < len(rows):
        settled = frames[off_lead[-1] + 1]
    behind = [r for r in rows if r["leader_error_m"] > 5.0 and "d_true_m" in r]

    def med(key: str) -> str:
        v = [r[key] for r in behind if key in r]
        return f"{np.median(v):.3f} m ({len(v)} updates)" if v else "-"

    print(f"{args.seq}: frames {args.first}..{last - 1}, seed {args.seed}")
    print(
        f"  the leader within 5 m for good from frame {settled if settled is not None else '-'}; "
        f"converged at frame {converged_frame if converged_frame is not None else '-'}"
    )
    print(
        f"  while another place led: median d at the true pose {med('d_true_m')}, of the best particle "
        f"near it {med('d_near_best_m')}, of the cloud's best {med('d_cloud_best_m')}"
    )


def main() -> None:
    from rangemcl.errors import InputError

    try:
        run()
    except InputError as err:  # a missing or malformed sequence, map or config: one line, status 2
        print(f"search_trace: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
