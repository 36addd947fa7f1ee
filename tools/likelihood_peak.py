#!/usr/bin/env python3
"""How sharp the range model's likelihood is around the true pose of a recorded drive.

For every ``--every``-th scan the localizer's own rays are drawn (chosen, de-skewed and levelled as
``rangemcl localize`` does, with its default settings and the same seeded generator) and their mean
residual ``d`` (Eq. 5) is computed at the true sensor pose and at poses moved from it along the car's
forward axis, its lateral axis and in yaw. Printed per offset: the median ``d`` over the scans and the
median evidence one update gives the true pose over the moved one, ``½ (d² − d_true²) / σ²`` nats.

    python tools/likelihood_peak.py --seq out/demo/test_drive --map out/demo/map
    python tools/likelihood_peak.py --seq SEQ --map MAP --every 10 --first 600 --last 700 --json peak.json

What it answers: how close to the true pose a particle must lie before it fits better than another
place does. A hypothesis of the global search is a cluster of a few dozen particles spread over metres
and degrees; where the peak is narrower than that spread, the true place is judged by particles that fit
worse than a look-alike street's (the MQ-8: ``docs/method.md``, "Where it still falls short").
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

OFFSETS_M = (0.1, 0.2, 0.5, 1.0, 2.0)
OFFSETS_DEG = (0.5, 1.0, 2.0, 5.0)


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="a recorded drive with poses.txt")
    ap.add_argument("--map", required=True, help="its map folder")
    ap.add_argument("--every", type=int, default=10, help="every this many frames")
    ap.add_argument("--first", type=int, default=0, help="first frame")
    ap.add_argument("--last", type=int, default=None, help="frame to stop before (default: the end)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the ray selection")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    if args.every < 1:
        raise SystemExit("likelihood_peak: --every must be >= 1")

    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import odometry_xyyaw, resolve_sensor_height
    from rangemcl.maps.view import open_map
    from rangemcl.se2 import se2_between, xyyaw_of

    seq = load_sequence(args.seq)
    if seq.poses is None:
        raise InputError(f"{args.seq}: the drive has no poses.txt")
    mesh_map, caster = open_map(args.map, None)
    settings = LocalizerSettings()
    height, _ = resolve_sensor_height(seq, mesh_map, settings)
    loc = build_localizer(mesh_map, settings, seed=args.seed, sensor_height_m=height, caster=caster)
    rng = np.random.default_rng(args.seed)
    truth = xyyaw_of(seq.poses @ seq.calib_Tr)
    odo, _source = odometry_xyyaw(seq, False)
    period = float(np.median(np.diff(seq.times))) if seq.times is not None and len(seq) > 1 else 0.1
    sigma = settings.observation.sigma_m

    labels = ["true"]
    moves = [np.zeros(3)]
    for m in OFFSETS_M:
        labels += [f"forward {m:g} m", f"lateral {m:g} m"]
        moves += [np.array([m, 0.0, 0.0]), np.array([0.0, m, 0.0])]
    for a in OFFSETS_DEG:
        labels.append(f"yaw {a:g} deg")
        moves.append(np.array([0.0, 0.0, math.radians(a)]))
    moves = np.array(moves)

    last = len(seq) if args.last is None else min(args.last, len(seq))
    rows = []
    for i in range(max(1, args.first), last, args.every):
        rays = loc.select_rays(
            seq.scan(i),
            rng,
            fire_time_s=seq.point_meta(i).get("time_s"),
            frame_period_s=period,
            frame_motion=se2_between(odo[i - 1], odo[i]),
            roll_pitch=tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None,
            sensor_height_m=loc.sensor_height_m,
        )
        if rays is None:
            continue
        x, y, yaw = truth[i]
        c, s = math.cos(yaw), math.sin(yaw)
        poses = np.column_stack(
            [
                x + c * moves[:, 0] - s * moves[:, 1],
                y + s * moves[:, 0] + c * moves[:, 1],
                yaw + moves[:, 2],
            ]
        )
        rows.append(loc.residuals(rays, poses))
    if not rows:
        raise InputError(f"{args.seq}: no scan with rays between frames {args.first} and {last}")
    d = np.array(rows)
    nats = 0.5 * (d**2 - d[:, :1] ** 2) / sigma**2
    print(f"{args.seq}: {len(d)} scans (frames {args.first}..{last - 1} every {args.every}), sigma {sigma} m")
    print(f"{'pose':>16} {'median d (m)':>13} {'median nats/update':>19} {'share worse':>12}")
    out = {"sequence": args.seq, "map": args.map, "scans": len(d), "sigma_m": sigma, "offsets": {}}
    for j, name in enumerate(labels):
        worse = float((nats[:, j] > 0).mean()) if j else math.nan
        print(f"{name:>16} {np.median(d[:, j]):13.3f} {np.median(nats[:, j]):19.2f} {worse:12.2f}")
        out["offsets"][name] = {
            "median_d_m": float(np.median(d[:, j])),
            "median_nats": float(np.median(nats[:, j])),
            "share_worse": worse,
        }
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


def main() -> None:
    from rangemcl.errors import InputError

    try:
        run()
    except InputError as err:  # a missing or malformed sequence or map: one line, status 2
        print(f"likelihood_peak: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
