#!/usr/bin/env python3
"""How a suite's trials failed, from a finished (or stopped) `simbed trials` folder: per setting (model and
particle count), the failed trials' errors where they converged, each "lost" alarm's error 5 frames
before it (a real wrong convergence, or a false alarm at the true place), and the cost before convergence.

    python tools/suite_failures.py SUITE_DIR

Reads ``SUITE_DIR/results.csv``, each trial's ``trials/KEY/frames.csv`` and the test drives' true poses
(``drives/DRIVE/poses.txt``). Columns: ``conv_failed`` (trials whose last convergence was wrong), their
median errors (min / max, and how many were over 60 m), ``respreads`` (the filter's "lost" alarms),
``false_alarms`` (alarms raised while the estimate was within 5 m of the truth), the alarms' error range,
and the median seconds per frame before convergence.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from rangemcl.datasets.kitti import read_poses_txt
from rangemcl.errors import InputError
from simbed.trials.suites import DRIVE_FIELDS, drive_key

FAR_M = 60.0  # a wrong convergence this far off is another street, not a settling filter
NEAR_M = 5.0  # the suites' success radius


def alarm_errors(trial_dir: Path, truth: np.ndarray) -> list[float]:
    """Location error 5 frames before each re-spread of one trial (its frames.csv, absolute frame ids;
    ``truth``: the drive's (N, 4, 4) poses)."""
    with (trial_dir / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    out = []
    for i, r in enumerate(rows):
        if r["recovered"] == "1":
            before = rows[max(0, i - 5)]
            f = int(before["frame"])
            dx, dy = float(before["x"]) - truth[f, 0, 3], float(before["y"]) - truth[f, 1, 3]
            out.append(float(np.hypot(dx, dy)))
    return out


def fail(message: str) -> None:
    """Bad input: one line naming the file and the problem, exit status 2."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite_dir", type=Path)
    a = ap.parse_args()
    results = a.suite_dir / "results.csv"
    if not results.is_file():
        fail(f"{results}: no such file (not a simbed trials folder?)")
    with results.open() as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("kidnap") != "True"]
    if not rows:
        fail(f"{results}: no finished trial")
    truths: dict[str, np.ndarray] = {}
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["sensor"], r["model"], int(r["particles"]))].append(r)
    print(
        "sensor   model             particles trials conv_failed  wrong_median_err_m(min/max, >60m)  "
        "respreads false_alarms alarm_err_m(min/max)  s/frame_before  trial_hours"
    )
    for (sensor, model, n), rs in sorted(groups.items()):
        wrong = [
            float(r["location_median_m"])
            for r in rs
            if r["frames_to_converge"] and r["success"] != "True" and r["location_median_m"]
        ]
        alarms: list[float] = []
        for r in rs:
            key = drive_key(**{k: r[k] for k in DRIVE_FIELDS if r.get(k) not in (None, "")})
            if key not in truths:
                try:
                    truths[key] = read_poses_txt(a.suite_dir / "drives" / key / "poses.txt")
                except InputError as err:
                    fail(str(err))
            trial = a.suite_dir / "trials" / r["key"]
            if not (trial / "frames.csv").is_file():
                fail(f"{trial / 'frames.csv'}: missing (the trial's folder was removed?)")
            alarms += alarm_errors(trial, truths[key])
        before = [float(r["seconds_per_frame_before"]) for r in rs if r["seconds_per_frame_before"]]
        span = lambda v: f"{min(v):.1f} / {max(v):.1f}" if v else "–"  # noqa: E731
        print(
            f"{sensor:8s} {model:17s} {n:9d} {len(rs):6d} {len(wrong):11d}  "
            f"{span(wrong):>22s}, {sum(e > FAR_M for e in wrong):2d}         "
            f"{len(alarms):9d} {sum(e < NEAR_M for e in alarms):12d} {span(alarms):>20s}  "
            f"{np.median(before) if before else float('nan'):14.2f}  "
            f"{sum(float(r['seconds']) for r in rs) / 3600:11.2f}"
        )


if __name__ == "__main__":
    main()
