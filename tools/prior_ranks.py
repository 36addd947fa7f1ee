#!/usr/bin/env python3
"""How well the place prior finds the true place of a recorded drive's scans: for every ``--every``-th
frame, the rank of the true place among the prior's cells (how many cells match the scan better than the
best cell within 2.5 m of the true position; 0: a true cell is the best), for each value of
``init.prior_profile_returns`` asked. A search draws its hypotheses from the prior's best few dozen
places (its first draw from the best 300), so the share of frames ranked within those is what it can use.

    python tools/prior_ranks.py --map MAP DRIVE [DRIVE ...] --returns 1,2 [--every 25] [--md table.md]

A scan with nothing in the prior's high band (every beam below the horizon: the MQ-8) is matched with
the map's beam prior of its top beam, as the localizer does (the map folder must hold it: it is written
at the first search of such a sensor, or by ``rangemcl place-prior``). The scans are levelled with the
drive's IMU roll and pitch, at the sensor height the localizer takes (the drive's mount).
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
    ap.add_argument("--returns", default="1,2", help="init.prior_profile_returns values, comma-separated")
    ap.add_argument("--every", type=int, default=25, help="every n-th frame")
    ap.add_argument("--md", help="also write the table here")
    args = ap.parse_args()

    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.localization import LocalizerSettings
    from rangemcl.localization.pipeline import resolve_sensor_height
    from rangemcl.localization.place_prior import (
        PRIOR_FILE,
        PlacePrior,
        beam_params,
        elevations_deg,
        scan_profile,
        top_beam_deg,
    )
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.se2 import rotation_roll_pitch, xyyaw_of

    ks = [int(k) for k in args.returns.split(",")]
    mesh_map = MeshMap.load(args.map)
    band = PlacePrior.load(Path(args.map) / PRIOR_FILE)
    if band is None:
        raise SystemExit(f"{args.map}: no place prior ({PRIOR_FILE}); run rangemcl place-prior first")
    lines = [
        "| drive | returns | frames | rank median | within 32 | within 300 |",
        "|---|---|---|---|---|---|",
    ]
    for drive in args.drives:
        seq = load_sequence(drive)
        truth = xyyaw_of(seq.poses)
        height, _source = resolve_sensor_height(seq, mesh_map, LocalizerSettings())
        frames = range(0, len(seq), args.every)
        first = seq.scan(frames[0]).astype(np.float64)
        prior = band
        _p, known = scan_profile(first, height, band.params)
        if known[1].sum() < band.params.min_known_share * band.params.bins:  # as the filter decides
            top = top_beam_deg(first, band.params.min_range_m)
            params = beam_params(band.params, top, height)
            files = sorted(Path(args.map).glob("place_prior_beam*.npz"))
            prior = next((q for q in (PlacePrior.load(f) for f in files) if q and q.params == params), None)
            if prior is None:
                raise SystemExit(f"{args.map}: no beam prior for {top:.2f} deg; run a search there first")
        for k in ks:
            ranks = []
            for i in frames:
                p = seq.scan(i).astype(np.float64)
                el = elevations_deg(p)
                if seq.imu_roll_pitch is not None:
                    p = p @ rotation_roll_pitch(*seq.imu_roll_pitch[i]).T
                prof, kn = scan_profile(p, height, prior.params, el, returns=k)
                m = prior.match(prof, kn)
                near = np.hypot(prior.xy[:, 0] - truth[i, 0], prior.xy[:, 1] - truth[i, 1]) < TRUE_RADIUS_M
                ranks.append(int((m.cost < m.cost[near].min()).sum()) if near.any() else len(prior.xy))
            r = np.asarray(ranks)
            line = (
                f"| {Path(drive).name} | {k} | {len(r)} | {np.median(r):g} | {np.mean(r < 32):.2f} | "
                f"{np.mean(r < 300):.2f} |"
            )
            lines.append(line)
            print(line, flush=True)
    if args.md:
        Path(args.md).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
