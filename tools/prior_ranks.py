#!/usr/bin/env python3
"""How well the place prior finds the true place of a recorded drive's scans: for every ``--every``-th
frame, the rank of the true place among the prior's cells (how many cells match the scan better than the
best cell within 2.5 m of the true position; 0: a true cell is the best), for each value of
``init.prior_profile_returns`` asked (and, with ``--skip-zero-intensity on``, with the returns that report
zero intensity left out, as ``init.prior_skip_zero_intensity`` does). A search draws its hypotheses from
the prior's best few dozen places (its first draw from the best 300), so the share of frames ranked
within those is what it can use.

    python tools/prior_ranks.py --map MAP DRIVE [DRIVE ...] --returns 1,3 [--every 25] [--md table.md]

The prior is the one the localizer matches the drive's scans with (its own decision at the first scan:
the map's band prior, or for a scan with nothing in the band prior's high band, every beam below the
horizon as the MQ-8's, the prior of its top beam, loaded from the map folder or rendered there once),
at the sensor height it takes (the drive's mount); the scans are levelled with the drive's IMU roll and
pitch, as the localizer levels them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

TRUE_RADIUS_M = 2.5  # a cell within this of the true position is a true cell (cells are 2 m apart)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("drives", nargs="+", help="recorded drives (KITTI layout, with poses)")
    ap.add_argument("--map", required=True, help="the drives' map folder")
    ap.add_argument("--returns", default="1,3", help="init.prior_profile_returns values, comma-separated")
    ap.add_argument("--every", type=int, default=25, help="every n-th frame")
    ap.add_argument(
        "--min-range",
        type=float,
        default=0.0,
        help="leave out the returns nearer than this (m; a what-if for near clutter such as fog's echoes)",
    )
    ap.add_argument(
        "--skip-zero-intensity",
        default="off",
        help="init.prior_skip_zero_intensity values, comma-separated (off, on)",
    )
    ap.add_argument("--md", help="also write the table here")
    args = ap.parse_args()

    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import resolve_sensor_height
    from rangemcl.localization.place_prior import elevations_deg, scan_profile
    from rangemcl.localization.scan_prep import lit_returns
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.se2 import rotation_roll_pitch, xyyaw_of

    ks = [int(k) for k in args.returns.split(",")]
    skips = [v.strip() for v in args.skip_zero_intensity.split(",")]
    if not set(skips) <= {"off", "on"}:
        raise SystemExit(f"--skip-zero-intensity {args.skip_zero_intensity!r}: expected off, on or both")
    mesh_map = MeshMap.load(args.map)
    lines = [
        "| drive | returns | zero intensity | frames | rank median | within 32 | within 300 |",
        "|---|---|---|---|---|---|---|",
    ]

    def levelled(seq, i, skip="off"):
        p, intensity = seq.scan_with_intensity(i)
        p = p.astype(np.float64)
        if skip == "on":
            p = p[lit_returns(intensity, len(p))]
        if args.min_range > 0:
            p = p[np.linalg.norm(p, axis=1) >= args.min_range]
        roll_pitch = None if seq.imu_roll_pitch is None else seq.imu_roll_pitch[i]
        return p, (p if roll_pitch is None else p @ rotation_roll_pitch(*roll_pitch).T)

    caster = None  # the map's BVH, built once for all the drives
    near_cut = f" (returns from {args.min_range:g} m)" if args.min_range > 0 else ""
    for drive in args.drives:
        seq = load_sequence(drive)
        truth = xyyaw_of(seq.poses)
        settings = LocalizerSettings()
        height, _source = resolve_sensor_height(seq, mesh_map, settings)
        loc = build_localizer(mesh_map, settings, seed=0, sensor_height_m=height, caster=caster)
        caster = loc.caster
        frames = range(0, len(seq), args.every)
        raw, p = levelled(seq, frames[0])
        prior = loc.prior_for(p, raw)  # the localizer's own choice: the band prior or the top beam's
        for k, skip in [(k, s) for k in ks for s in skips]:
            ranks = []
            for i in frames:
                raw, p = levelled(seq, i, skip)
                prof, kn = scan_profile(p, height, prior.params, elevations_deg(raw), returns=k)
                m = prior.match(prof, kn)
                near = np.hypot(prior.xy[:, 0] - truth[i, 0], prior.xy[:, 1] - truth[i, 1]) < TRUE_RADIUS_M
                ranks.append(int((m.cost < m.cost[near].min()).sum()) if near.any() else len(prior.xy))
            r = np.asarray(ranks)
            line = (
                f"| {Path(drive).name}{near_cut} | {k} | {'left out' if skip == 'on' else 'kept'} | "
                f"{len(r)} | {np.median(r):g} | "
                f"{np.mean(r < 32):.2f} | {np.mean(r < 300):.2f} |"
            )
            lines.append(line)
            print(line, flush=True)
    if args.md:
        Path(args.md).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
