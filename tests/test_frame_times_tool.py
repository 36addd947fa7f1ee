"""tools/frame_times.py: the frames of a suite's trials split into search and converged ones, per method."""

from __future__ import annotations

import csv
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "tools" / "frame_times.py"


def _write_trial(folder: Path, seconds, converged, late) -> None:
    folder.mkdir(parents=True)
    with open(folder / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "converged", "seconds", "late"])
        for k, (s, c, d) in enumerate(zip(seconds, converged, late, strict=True)):
            w.writerow([k, int(c), f"{s:.4f}", int(d)])


def test_frames_split_by_the_state_each_began_in_and_dropped_scans_left_out(tmp_path):
    rng = np.random.default_rng(0)
    rows, expect = [], {"a": ([], []), "b": ([], [])}
    for t in range(6):
        method = "ab"[t % 2]
        n = 40
        seconds = rng.uniform(0.01, 2.0, n)
        # converged from frame 10 on, lost at frame 25 (a recovery), converged again at 30
        conv = np.zeros(n, bool)
        conv[10:25] = True
        conv[30:] = True
        began_converged = np.concatenate([[False], conv[:-1]])
        late = rng.random(n) < 0.2  # scans dropped at the sensor's pace: left out
        expect[method][0].extend(seconds[~began_converged & ~late].round(4))
        expect[method][1].extend(seconds[began_converged & ~late].round(4))
        key = f"trial{t}"
        _write_trial(tmp_path / "trials" / key, seconds, conv, late)
        rows.append({"method": method, "key": key})
    rows.append({"method": "b", "key": "never_ran"})  # a row without its trial folder is left out
    with open(tmp_path / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, ["method", "key"])
        w.writeheader()
        w.writerows(rows)
    spec = importlib.util.spec_from_file_location("frame_times", TOOL)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    md = tmp_path / "t.md"
    assert tool.main([str(tmp_path), "--md", str(md)]) == 0
    table = md.read_text().splitlines()
    for method, (search, tracked) in expect.items():
        for kind, sec in (("search", search), ("converged", tracked)):
            line = next(x for x in table if x.startswith(f"| {method} | 3 | {len(sec)} | {kind} |"))
            cells = [c.strip() for c in line.strip("|").split("|")]
            assert cells[4] == f"{np.median(sec):.3f} s" and cells[6] == f"{max(sec):.3f} s"
            assert int(cells[7]) == sum(s > 0.1 for s in sec) and int(cells[8]) == sum(s > 1.0 for s in sec)


def test_a_folder_without_results_is_one_line_and_status_2(tmp_path):
    r = subprocess.run([sys.executable, str(TOOL), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "results.csv" in r.stderr
