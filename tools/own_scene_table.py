#!/usr/bin/env python3
"""The table of ``tools/own_scene_examples.sh``: per example scene, the map's quality against
the scene's true surface and global localization from 5 start points of the test drive.

    python tools/own_scene_table.py /work/data/own_scenes
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _load(p: Path) -> dict | None:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    rows = [
        "| scene | map: triangles, vertex → true surface median / p90, completeness | localizations "
        "succeeded | converged at frame (median) | location RMSE (median, worst) | yaw RMSE (median) | "
        "wrong convergences (uncaught) | false alarms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scene in sorted(p for p in args.out.iterdir() if (p / "map").is_dir()):
        q = _load(scene / "quality.json")
        if q is None:  # not measured yet
            continue
        report = _load(scene / "map" / "report.json") or {}
        runs = sorted(scene.glob("loc_*"), key=lambda p: int(p.name.split("_")[1]))
        ms = [m for m in (_load(r / "metrics.json") for r in runs) if m]
        ok = [m for m in ms if m.get("success")]
        conv = [
            m["converged_frame"] - m.get("first_frame", 0) for m in ms if m.get("converged_frame") is not None
        ]
        rmse = [m["location_rmse_m"] for m in ok]
        yaw = [m["yaw_rmse_deg"] for m in ok]
        wrong = sum(m.get("wrong_convergences_count", 0) for m in ms)
        uncaught = sum(m.get("wrong_convergences_uncaught", 0) for m in ms)
        alarms = sum(m.get("false_alarms_count", 0) for m in ms)
        quality = (
            f"{report.get('triangles', 0):,}, {q.get('vertex_dist_median_m', float('nan')):.3f} / "
            f"{q.get('vertex_dist_p90_m', float('nan')):.3f} m, {q.get('completeness', float('nan')):.2f}"
        )
        rows.append(
            f"| {scene.name} | {quality} | {len(ok)}/{len(ms)} | "
            f"{np.median(conv) if conv else '-'} | "
            + (f"{np.median(rmse):.3f} m, {max(rmse):.3f} m" if rmse else "-")
            + f" | {np.median(yaw):.2f}°" * bool(yaw)
            + ("" if yaw else " | -")
            + f" | {wrong} ({uncaught}) | {alarms} |"
        )
    print("\n".join(rows))


if __name__ == "__main__":
    main()
