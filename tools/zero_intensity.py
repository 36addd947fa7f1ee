#!/usr/bin/env python3
"""How much of a recorded drive's returns report zero intensity: for every ``--every``-th frame, the share
of all returns, and of those above the road (more than 0.4 m above the sensor's ground), with intensity 0,
and the median range of those returns; medians over the frames. In fog the fog's own echoes report zero
(``init.prior_skip_zero_intensity`` leaves them out of the place prior's match); an ideal sensor's
returns all do.

    python tools/zero_intensity.py DRIVE [DRIVE ...] [--every 25] [--height 1.73]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("drives", nargs="+", help="recorded drives (KITTI layout)")
    ap.add_argument("--every", type=int, default=25, help="every n-th frame")
    ap.add_argument("--height", type=float, default=1.73, help="the sensor's height above the ground (m)")
    args = ap.parse_args()

    from rangemcl.datasets.kitti import load_sequence

    print("| drive | frames | zero intensity, all returns | above the road | their median range (m) |")
    print("|---|---|---|---|---|")
    for drive in args.drives:
        seq = load_sequence(drive)
        share, above, rng = [], [], []
        for i in range(0, len(seq), args.every):
            p, it = seq.scan_with_intensity(i)
            zero = it == 0
            up = p[:, 2] + args.height > 0.4
            share.append(zero.mean())
            above.append(zero[up].mean() if up.any() else np.nan)
            if zero.any():
                rng.append(np.median(np.linalg.norm(p[zero], axis=1)))
        med = f"{np.median(rng):.2f}" if rng else "-"
        name, n = Path(drive).name, len(share)
        print(f"| {name} | {n} | {np.median(share):.3f} | {np.nanmedian(above):.3f} | {med} |", flush=True)


if __name__ == "__main__":
    main()
