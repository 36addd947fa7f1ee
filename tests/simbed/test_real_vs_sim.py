"""tools/real_vs_sim.py's statistics on rows whose answer is known: depth edges and mixed pixels, the
beam rows of a KITTI-ordered scan, and the fill by beam row."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

TOOL = Path(__file__).resolve().parents[2] / "tools" / "real_vs_sim.py"


def _tool():
    spec = importlib.util.spec_from_file_location("real_vs_sim", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_depth_edges_and_mixed_pixels_on_known_rows():
    t = _tool()
    fg, bg = 10.0, 25.0
    clean = np.array([[fg] * 8 + [bg] * 8])  # one jump between two flat surfaces
    mixed = np.array([[fg] * 8 + [17.0] + [bg] * 7])  # one cell between them
    ramp = np.array([np.linspace(10.0, 11.5, 16)])  # a slanted wall: no edge
    assert t.edges_and_mixed(clean)[1:] == (1, 0)
    assert t.edges_and_mixed(mixed)[1:] == (1, 1)
    assert t.edges_and_mixed(ramp)[1:] == (0, 0)
    assert t.edges_and_mixed(np.vstack([clean, mixed, ramp]))[1:] == (2, 1)


def test_kitti_rows_follow_the_azimuth_wraps():
    t = _tool()
    rng = np.random.default_rng(0)
    rows = []
    for beam in range(4):
        az = np.sort(rng.uniform(-np.pi, np.pi, 900))
        rows.append(np.column_stack([np.cos(az), np.sin(az), np.full(900, 0.1 * beam)]))
    pts = np.vstack(rows)
    got = t.kitti_rows(pts)
    np.testing.assert_array_equal(got, np.repeat(np.arange(4), 900))
