#!/usr/bin/env python3
"""Does a scan single out the car's true place in the map? The range model's residual (paper Eq. 5, the
localizer's own settings) at the true pose, against the best of a few hundred poses around it and of many
poses spread over the map as global localization spreads them, per frame of a drive with ground truth.

    python tools/probe_residuals.py --seq SEQ --map MAP --frames 150,172,190,210

Columns: ``truth`` (residual at the true pose), ``near`` (best of ``--near`` poses within about 0.3 m and
2 deg of it), ``global`` (best of ``--particles`` spread poses) and how far that one is from the truth,
``beaten`` (share of the spread poses with a lower residual than the truth: 0 where the scan is
discriminative), and the truth's rays by kind: ``short`` (measured at least ``--tol`` shorter than the
map's range at the true pose: something in front of the mapped surface, e.g. a car or actor the map does
not hold), ``long`` (measured at least ``--tol`` longer, or the map has nothing within the margin there:
the map holds something the scene no longer has, or lacks a surface), ``agree`` (the rest).
When ``beaten`` is well above 0, global localization will prefer other places for as long as it lasts,
and a filter declared lost there has nothing to find its way back with.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="sequence with poses.txt (ground truth)")
    ap.add_argument("--map", required=True)
    ap.add_argument("--frames", required=True, help="comma-separated frame numbers")
    ap.add_argument("--particles", type=int, default=20000, help="poses spread over the map")
    ap.add_argument("--near", type=int, default=400, help="poses around the true pose")
    ap.add_argument("--config", help="localizer settings YAML (default: the localizer's defaults)")
    ap.add_argument("--tol", type=float, default=0.3, help="metres: a ray agrees within this")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args()

    from rangemcl.config import load_config
    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import frame_rays, odometry_xyyaw, resolve_sensor_height
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.se2 import xyyaw_of

    seq = load_sequence(a.seq, require_poses=True)
    settings = load_config(LocalizerSettings, a.config)
    settings.observation.model = "range"
    o = settings.observation
    mesh_map = MeshMap.load(a.map)
    height, _ = resolve_sensor_height(seq, mesh_map, settings)
    loc = build_localizer(mesh_map, settings, seed=a.seed, threads=a.threads, sensor_height_m=height)
    truths = xyyaw_of(seq.poses)
    odo, _ = odometry_xyyaw(seq, False)
    rng = np.random.default_rng(a.seed)
    frames = [int(f) for f in a.frames.split(",") if f.strip()]
    print(
        f"{'frame':>6} {'truth':>6} {'near':>6} {'global':>6} {'at_m':>6} {'beaten':>7}"
        f" {'short':>6} {'long':>6} {'agree':>6}"
    )
    for f in frames:
        if not 0 <= f < len(seq):
            raise InputError(f"{a.seq}: frame {f} is outside the sequence (0..{len(seq) - 1})")
        truth = truths[f]
        # the scan as the localizer prepares it: de-skewed with the frame's odometry, levelled by the IMU
        rays = frame_rays(seq, f, o, np.random.default_rng(a.seed + f), odo)
        near = truth + rng.normal(0.0, 1.0, (a.near, 3)) * [0.3, 0.3, math.radians(2.0)]
        d_truth = float(loc.residuals(rays, truth[None])[0])
        d_near = float(loc.residuals(rays, near).min())
        loc.spread(a.particles)
        d_all = loc.residuals(rays)
        k = int(np.argmin(d_all))
        away = math.hypot(*(loc.particles[k, :2] - truth[:2]))
        beaten = float(np.mean(d_all < d_truth))
        # the truth's rays one by one: where does the map disagree with the scan?
        c, s = math.cos(truth[2]), math.sin(truth[2])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([truth[0], truth[1], float(loc.sensor_z(truth[None, :2])[0])])
        hits = loc.caster.cast(origin, rays.directions @ R.T, float(o.max_range_m + o.margin_m))
        rendered = np.where(hits.hit, hits.ranges, np.inf)
        short = float(np.mean(rays.ranges < rendered - a.tol))
        long_ = float(np.mean(rays.ranges > rendered + a.tol))
        print(
            f"{f:>6} {d_truth:>6.3f} {d_near:>6.3f} {float(d_all[k]):>6.3f} {away:>6.0f} {beaten:>7.3f}"
            f" {short:>6.2f} {long_:>6.2f} {1 - short - long_:>6.2f}",
            flush=True,
        )


if __name__ == "__main__":
    from rangemcl.errors import InputError

    try:
        main()
    except InputError as err:  # a missing or malformed sequence, map or config: one line, status 2
        print(f"probe_residuals: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
