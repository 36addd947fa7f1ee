#!/usr/bin/env python3
"""How well the place prior singles out the true place over a drive: for every ``--every``-th scan of a
recorded drive, the rank of the true place among all the prior's cells (0 = the best match) and the yaw
error of the aligned yaw there.

    python tools/prior_rank.py --seq out/demo/test_drive --map out/demo/map
    python tools/prior_rank.py --seq SEQ --map MAP --every 5 --json prior_rank.json
    python tools/prior_rank.py --seq SEQ --map BIG_MAP --map-memory 700   # a map too large to hold whole
    python tools/prior_rank.py --seq SEQ --map BIG_MAP --map-memory 700 --two-stage off   # one stage
    python tools/prior_rank.py --seq SEQ --map MAP --sequence 4 --spacing 3   # with the last 4 scans
    python tools/prior_rank.py --seq SEQ --map MAP --beam off   # the band prior even for an MQ-8

"The true place" is the best-matching cell within ``--radius`` (1.5 m: a 2 m grid has a cell centre
within 1.42 m of any point) of the true sensor position; its rank counts the cells farther than
``--radius`` that match better. The prior is loaded from the map folder (or rendered there first, which
is timed). Prints the rank distribution (share of scans with the true place first, in the best 10, 100,
300 = the particles' candidates by default) and the yaw errors. With ``--two-stage`` (automatic for
priors of 50,000 cells and more) a true place left out of the shortlist ranks behind every shortlisted
cell. With ``--sequence N`` each cell is ranked by its mean cost over today's scan and the N scans
taken every ``--spacing`` metres of odometry before it, each scored where the drive's odometry puts it
behind the cell (:func:`rangemcl.localization.place_prior.sequence_costs`); the one-scan ranks are
printed beside. As the localizer, a drive whose scans have nothing in the prior's high band (the MQ-8) is
matched with the prior of its sensor's top beam (``--beam off``: with the band prior's low band).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="a recorded drive with poses.txt")
    ap.add_argument("--map", required=True, help="its map folder")
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--radius", type=float, default=1.5)
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument(
        "--map-memory",
        type=float,
        help="open the map within this many MB (a map too large to hold whole); default: as localize does",
    )
    ap.add_argument(
        "--two-stage",
        choices=("auto", "on", "off"),
        default="auto",
        help="match in two stages (coarse bins, then a shortlist; auto: for priors of 50,000 cells and more)",
    )
    ap.add_argument("--sequence", type=int, default=0, help="also rank over this many past scans")
    ap.add_argument("--spacing", type=float, default=3.0, help="metres of odometry between those scans")
    ap.add_argument(
        "--beam",
        choices=("auto", "off"),
        default="auto",
        help="auto: as the localizer, a sensor that sees nothing in the high band uses its top beam's prior",
    )
    args = ap.parse_args()

    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import odometry_xyyaw, resolve_sensor_height
    from rangemcl.localization.place_prior import (
        circular_distance_deg,
        elevations_deg,
        scan_profile,
        sequence_costs,
    )
    from rangemcl.maps.view import open_map
    from rangemcl.se2 import rotation_roll_pitch, se2_between, xyyaw_of

    seq = load_sequence(args.seq)
    mesh_map, caster = open_map(args.map, args.map_memory)
    if seq.poses is None:
        raise InputError(f"{args.seq}: the drive has no poses.txt")
    settings = LocalizerSettings()
    settings.init.beam_prior = args.beam == "auto"
    height, _ = resolve_sensor_height(seq, mesh_map, settings)
    loc = build_localizer(mesh_map, settings, seed=0, sensor_height_m=height, caster=caster)
    t0 = time.perf_counter()

    def scan_at(i: int):
        raw = np.asarray(seq.scan(i), np.float64)
        if seq.imu_roll_pitch is not None:
            return raw, raw @ rotation_roll_pitch(*seq.imu_roll_pitch[i]).T
        return raw, raw

    prior = loc.prior_for(*scan_at(0)[::-1])
    ready_s = time.perf_counter() - t0
    truth = xyyaw_of(seq.poses @ seq.calib_Tr)
    odo, _source = odometry_xyyaw(seq, False)
    ranks, seq_ranks, yaw_err, match_s = [], [], [], []
    history: list = []  # (the scan's match, odometry pose) every --spacing metres

    def remember(i: int, m) -> None:
        nonlocal history
        moved = not history or np.hypot(*(odo[i, :2] - history[-1][1][:2])) >= args.spacing
        if args.sequence > 0 and moved:
            history = [*history, (m, odo[i])][-args.sequence :]

    step = args.every if args.sequence <= 0 else 1
    for i in range(0, len(seq), step):
        raw, pts = scan_at(i)
        prof, known = scan_profile(pts, height, prior.params, elevations_deg(raw))
        t1 = time.perf_counter()
        m = prior.match(prof, known, two_stage={"auto": None, "on": True, "off": False}[args.two_stage])
        if args.sequence > 0 and i % args.every:  # only kept for the sequence
            remember(i, m)
            continue
        match_s.append(time.perf_counter() - t1)
        d = np.hypot(prior.xy[:, 0] - truth[i, 0], prior.xy[:, 1] - truth[i, 1])
        near = d <= args.radius
        if near.any():  # else off the drivable area of the map
            j = np.flatnonzero(near)[np.argmin(m.cost[near])]
            ranks.append(int((m.cost[~near] < m.cost[j]).sum()))
            yaw_err.append(float(circular_distance_deg(m.yaw[j], truth[i, 2])))
            if args.sequence > 0 and len(history) == args.sequence:
                past = [(pm, se2_between(odo[i], o)) for pm, o in history]
                c = sequence_costs(prior, m, past)
                j = np.flatnonzero(near)[np.argmin(c[near])]
                seq_ranks.append(int((c[~near] < c[j]).sum()))
        remember(i, m)
    r = np.array(ranks)
    out = {
        "sequence": args.seq,
        "map": args.map,
        "cells": len(prior.xy),
        "two_stage": args.two_stage,
        "prior": loc.beam_prior_source if prior is loc.beam_prior else loc.prior_source,
        "beam_deg": prior.params.beam_deg,
        "prior_ready_s": ready_s,
        "scans": len(r),
        "rank_median": float(np.median(r)),
        "rank_p90": float(np.quantile(r, 0.9)),
        "share_first": float(np.mean(r == 0)),
        "share_top10": float(np.mean(r < 10)),
        "share_top100": float(np.mean(r < 100)),
        "share_top300": float(np.mean(r < 300)),
        "yaw_error_median_deg": float(np.median(yaw_err)),
        "yaw_error_p90_deg": float(np.quantile(yaw_err, 0.9)),
        "match_median_s": float(np.median(match_s)),
    }
    if seq_ranks:
        q = np.array(seq_ranks)
        out["sequence"] = {
            "scans": args.sequence,
            "spacing_m": args.spacing,
            "ranked": len(q),
            "share_first": float(np.mean(q == 0)),
            "share_top10": float(np.mean(q < 10)),
            "share_top100": float(np.mean(q < 100)),
            "share_top300": float(np.mean(q < 300)),
            "rank_median": float(np.median(q)),
        }
    print(
        f"{out['scans']} scans, {out['cells']:,} cells ("
        + (
            "band prior"
            if prior.params.beam_deg is None
            else f"prior of the {prior.params.beam_deg:g} deg beam"
        )
        + f" {out['prior']} in {ready_s:.1f} s): true place "
        f"first in {100 * out['share_first']:.0f} %, in the best 10 in {100 * out['share_top10']:.0f} %, "
        f"100: {100 * out['share_top100']:.0f} %, 300: {100 * out['share_top300']:.0f} %; rank median "
        f"{out['rank_median']:.0f}, p90 {out['rank_p90']:.0f}; aligned yaw error median "
        f"{out['yaw_error_median_deg']:.1f} deg, p90 {out['yaw_error_p90_deg']:.1f} deg; "
        f"match {1000 * out['match_median_s']:.0f} ms per scan"
    )
    if seq_ranks:
        q = out["sequence"]
        print(
            f"with the last {args.sequence} scans every {args.spacing:g} m ({q['ranked']} scans with a full "
            f"history): true place first in {100 * q['share_first']:.0f} %, in the best 10 in "
            f"{100 * q['share_top10']:.0f} %, 100: {100 * q['share_top100']:.0f} %, 300: "
            f"{100 * q['share_top300']:.0f} %; rank median {q['rank_median']:.0f}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)


def main() -> None:
    import sys

    from rangemcl.errors import InputError

    try:
        run()
    except InputError as err:  # a missing or malformed sequence or map: one line, status 2
        print(f"prior_rank: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
