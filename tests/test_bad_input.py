"""Bad input across the CLIs (issue 18): each case is one line on stderr naming the problem, exit status
2, and nothing created or changed. Cases that need no recording or map run here; those that do are in
the end-to-end tests."""

from __future__ import annotations

import subprocess
import sys

import pytest

CONFIGS = {
    "neg_tile.yaml": "tiles:\n  size_m: -5\n",
    "zero_tile.yaml": "tiles:\n  size_m: 0\n",
    "neg_depth.yaml": "poisson:\n  depth: -1\n",
    "bad_quantile.yaml": "poisson:\n  density_quantile: 1.5\n",
    "bad_gate.yaml": "refine:\n  gate_m: -1\n",
    "bad_window.yaml": "motion:\n  calibration_window_m: 0\n",
    "bad_settle.yaml": "motion:\n  calibration_settle_updates: -2\n",
}

# (program and arguments; {d} is the test's folder) -> words the one line must hold
CASES = [
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --frames -5", ["frames", "-5"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --first-frame -1", ["first frame", "-1"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --threads 0", ["threads"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --particles 0", ["particles"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --init-pose 1,2,0", ["tracking"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/o --mode sideways", ["sideways"]),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/a_file", ["a_file", "not a folder"]),
    (
        "rangemcl localize {d}/seq --map {d}/map --out {d}/o --config {d}/bad_gate.yaml",
        ["bad_gate.yaml", "refine.gate_m"],
    ),
    (
        "rangemcl localize {d}/seq --map {d}/map --out {d}/o --config {d}/bad_window.yaml",
        ["calibration_window_m"],
    ),
    (
        "rangemcl localize {d}/seq --map {d}/map --out {d}/o --config {d}/bad_settle.yaml",
        ["calibration_settle_updates"],
    ),
    ("rangemcl build-map {d}/seq --out {d}/o --config {d}/neg_tile.yaml", ["neg_tile.yaml", "tiles.size_m"]),
    (
        "rangemcl build-map {d}/seq --out {d}/o --config {d}/zero_tile.yaml",
        ["zero_tile.yaml", "tiles.size_m"],
    ),
    (
        "rangemcl build-map {d}/seq --out {d}/o --config {d}/neg_depth.yaml",
        ["neg_depth.yaml", "poisson.depth"],
    ),
    ("rangemcl build-map {d}/seq --out {d}/o --config {d}/bad_quantile.yaml", ["density_quantile"]),
    ("rangemcl build-map {d}/seq --out {d}/o --workers -3", ["workers"]),
    ("simbed record --scene town_small --route test --out {d}/o --actors -1", ["actors", "-1"]),
    ("simbed record --scene town_small --route test --out {d}/o --frames 0", ["frames"]),
    ("simbed render --scene {d}/bad.xml --out {d}/o.png", ["bad.xml", "Line number=3"]),
]


def _tree(root):
    return sorted((str(p.relative_to(root)), p.stat().st_mtime_ns) for p in root.rglob("*"))


@pytest.fixture
def folder(tmp_path):
    for name, text in CONFIGS.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "bad.xml").write_text(
        '<mujoco>\n<worldbody>\n<geom type="box" size="1 1"\n</worldbody></mujoco>\n'
    )
    return tmp_path


@pytest.mark.parametrize(
    ("command", "words"), CASES, ids=[c[0].split(" {d}")[0] + f"#{i}" for i, c in enumerate(CASES)]
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(folder, command, words):
    args = command.format(d=folder).split()
    before = _tree(folder)
    code = "import sys; from {m}.cli import main; sys.argv[0] = '{m}'; main()".format(m=args[0])
    out = subprocess.run([sys.executable, "-c", code, *args[1:]], capture_output=True, text=True, timeout=120)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, out.stderr
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert _tree(folder) == before  # nothing created or changed
