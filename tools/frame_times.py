#!/usr/bin/env python3
"""Per-frame compute of a trial suite, by method: how many frames kept the sensor's pace.

    python tools/frame_times.py out/medium            # a suite folder: results.csv and trials/
    python tools/frame_times.py out/medium --md frame_times.md

Reads every trial row of the suite's ``results.csv`` and its ``trials/<key>/frames.csv`` (the ``seconds``
each frame took), and splits the frames by what the filter did: a *search* frame began with the filter
not converged (the frame that converges is the search's last), a *converged* frame began with it
converged (tracking, and the lost watch's second opinions during a probation or a suspicion); the scans
a run at the sensor's pace dropped (``late``) are left out. For each
method and kind: the number of frames, the median, 95th percentile and worst seconds, and how many took
more than the sensor's period (100 ms) and more than 1 s. Two trials ran side by side on the 2 cores in
the suites: compare methods measured alike, within one machine.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

PERIOD_S = 0.1  # a LiDAR's scan period at 10 Hz


def frame_seconds(frames_csv: Path) -> tuple[list[float], list[float]]:
    """The seconds of the search frames and of the converged frames of one trial."""
    search, tracked = [], []
    converged_before = False
    with open(frames_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            if row.get("late") != "1":  # (a scan dropped at the sensor's pace was not localized)
                (tracked if converged_before else search).append(float(row["seconds"]))
            converged_before = row["converged"] == "1"
    return search, tracked


def summary(seconds: list[float]) -> dict:
    a = np.asarray(seconds, np.float64)
    if len(a) == 0:
        return dict(frames=0)
    return dict(
        frames=len(a),
        median=float(np.median(a)),
        p95=float(np.percentile(a, 95)),
        worst=float(a.max()),
        over_period=int((a > PERIOD_S).sum()),
        over_1s=int((a > 1.0).sum()),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", type=Path, help="a suite folder (results.csv, trials/)")
    ap.add_argument("--md", type=Path, help="also write the table here (markdown)")
    args = ap.parse_args(argv)
    results = args.suite / "results.csv"
    if not results.is_file():
        print(f"frame_times: {results}: no such file (a suite folder holds results.csv)", file=sys.stderr)
        return 2
    by_method: dict[str, tuple[list[float], list[float], int]] = {}
    missing = 0
    with open(results, newline="") as fh:
        for row in csv.DictReader(fh):
            frames = args.suite / "trials" / row["key"] / "frames.csv"
            if not frames.is_file():
                missing += 1
                continue
            search, tracked = frame_seconds(frames)
            s, t, n = by_method.setdefault(row["method"], ([], [], 0))
            by_method[row["method"]] = (s + search, t + tracked, n + 1)
    lines = [
        "| method | trials | frames | kind | median | 95th percentile | worst | over 100 ms | over 1 s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for method in sorted(by_method):
        search, tracked, n = by_method[method]
        for kind, seconds in (("search", search), ("converged", tracked), ("all", search + tracked)):
            f = summary(seconds)
            if not f["frames"]:
                continue
            lines.append(
                f"| {method} | {n} | {f['frames']} | {kind} | {f['median']:.3f} s | {f['p95']:.3f} s | "
                f"{f['worst']:.3f} s | {f['over_period']} | {f['over_1s']} |"
            )
    table = "\n".join(lines) + "\n"
    print(table, end="")
    if missing:
        print(f"({missing} rows without their trial's frames.csv left out)")
    if args.md:
        args.md.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
