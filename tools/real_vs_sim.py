#!/usr/bin/env python3
"""A real HDL-64E scan beside simulated ones: how full the beam x column grid is (overall and by beam row),
ranges, intensities by range band and mixed pixels at depth edges, for the ideal and the realistic sensor.

The real scan is a KITTI ``.bin`` (float32 x, y, z, intensity records), e.g. the first scan of a KITTI
odometry sequence kept as public test data (``arsjindal/Lidar-Points-Representation``, commit 7c168a7,
``data/000000.bin``, from SemanticKITTI). The simulated scans are frames of a drive in a generated town
(``town_small`` by default: a grid of streets with parked cars, houses and trees, as a residential KITTI
street), through the ``hdl-64e-nominal`` preset (KITTI's unit spans +2.5 to -23.5 degrees in nearly even
steps, as the nominal table does), once with each sensor model on the same drive.

    python tools/real_vs_sim.py --real kitti_000000.bin --out docs/results/realism

Writes ``OUT/table.md`` (statistic by source), ``OUT/stats.csv`` (the same, and the curves behind the
figure), ``OUT/realism.png`` and ``OUT/command.txt``.

Definitions (the same code for every source): each point goes to its beam's row (the simulated scans
know it; a KITTI scan stores its points beam by beam, each beam in azimuth order, so a row ends where the
azimuth wraps around) and to the column of its azimuth (2,083 per turn); a cell keeps its nearest point.
The grid's fill counts points (returns per beam and turn, over the preset's 64 x 2,083); depth edges
are found in the cells (a real point's column is its azimuth's, a simulated one's its firing column).
A **depth edge** is a place in a row where the range jumps by more than ``EDGE_JUMP_M`` across one or
two cells while the cells on either side are locally flat (their own steps below ``FLAT`` of the
range); a **mixed pixel** is a cell within such a two-cell jump whose range lies between the two sides,
more than ``MIXED_MARGIN_M`` from both.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import shlex
import sys
from pathlib import Path

import numpy as np

from rangemcl.datasets.scanio import read_scan_bin
from rangemcl.sensors import load_spec

EDGE_JUMP_M = 1.0
MIXED_MARGIN_M = 0.25
FLAT = 0.03  # a step of less than 3 % of the range is flat
RANGE_BANDS_M = (0, 10, 20, 40, 80, 120)
RANGE_BINS_M = np.arange(0, 82, 2.0)
SENSOR = "hdl-64e-nominal"


def kitti_rows(points: np.ndarray) -> np.ndarray:
    """Row of each point of a KITTI scan: its points come beam by beam (highest first), each beam in
    increasing azimuth, so a beam ends where the azimuth wraps from +pi to -pi (wraps closer than 500
    points to the previous one are a beam's jitter at the seam, not a new beam)."""
    az = np.arctan2(points[:, 1], points[:, 0])
    wraps = np.flatnonzero(np.diff(az) < -np.pi) + 1
    starts, last = [], 0
    for b in wraps:
        if b - last >= 500:
            starts.append(b)
            last = b
    row = np.zeros(len(points), np.int64)
    row[starts] = 1
    return np.cumsum(row)


def grid_of(points, intensity, rows, cols, n_rows: int, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges (H, W), intensity (H, W))``; 0 = empty; a cell keeps its nearest point. ``cols`` None:
    the column of each point's azimuth."""
    r = np.linalg.norm(points, axis=1)
    ok = (r > 0.5) & (rows < n_rows)
    p, r, inten, rows = points[ok], r[ok], intensity[ok], rows[ok]
    if cols is None:
        az = np.mod(np.degrees(np.arctan2(p[:, 1], p[:, 0])), 360.0)
        col = np.minimum((az / 360.0 * columns).astype(int), columns - 1)
    else:
        col = cols[ok]
    order = np.argsort(-r)  # the nearest point written last wins its cell
    rng_img = np.zeros((n_rows, columns))
    int_img = np.zeros((n_rows, columns))
    rng_img[rows[order], col[order]] = r[order]
    int_img[rows[order], col[order]] = inten[order]
    return rng_img, int_img


def edges_and_mixed(ranges: np.ndarray) -> tuple[int, int, int]:
    """``(cells compared, depth edges, mixed pixels)`` along the rows (see the module docstring)."""
    r = ranges
    a, b, c, d, e = (r[:, k : r.shape[1] - 4 + k] for k in range(5))  # five cells in a row, c in the middle
    full = (a > 0) & (b > 0) & (c > 0) & (d > 0) & (e > 0)

    def flat(x, y):
        return np.abs(x - y) < FLAT * np.minimum(x, y)

    # one-cell jump between b and c, flat a-b and c-d
    jump1 = full & flat(a, b) & flat(c, d) & (np.abs(b - c) > EDGE_JUMP_M)
    # two-cell jump from b to d across c, flat a-b and d-e; c between them is mixed
    jump2 = full & flat(a, b) & flat(d, e) & (np.abs(b - d) > EDGE_JUMP_M) & ~flat(b, c) & ~flat(c, d)
    lo, hi = np.minimum(b, d), np.maximum(b, d)
    mixed = jump2 & (c > lo + MIXED_MARGIN_M) & (c < hi - MIXED_MARGIN_M)
    return int(full.sum()), int((jump1 | jump2).sum()), int(mixed.sum())


def statistics(points, intensity, rows, spec, unit_intensity: bool, cols=None) -> dict:
    ranges, _ = grid_of(points, intensity, rows, cols, spec.beams, spec.columns)
    r = np.linalg.norm(points, axis=1)
    i = intensity.copy()
    if not unit_intensity:  # an 8-bit scale: to 0..1 as KITTI stores it
        i = i / 255.0
    compared, edges, mixed = edges_and_mixed(ranges)
    out = {
        "points": len(points),
        "grid_filled": len(points) / (spec.beams * spec.columns),
        "fill_by_row": np.bincount(rows, minlength=spec.beams)[: spec.beams] / spec.columns,
        "range_median_m": float(np.median(r)),
        "range_p95_m": float(np.percentile(r, 95)),
        "range_hist": np.histogram(r, RANGE_BINS_M)[0] / len(r),
        "intensity_median": float(np.median(i)),
        "intensity_p10": float(np.percentile(i, 10)),
        "intensity_p90": float(np.percentile(i, 90)),
        "intensity_zero_share": float((i == 0).mean()),
        "intensity_hist": np.histogram(np.clip(i, 0, 0.999), np.linspace(0, 1, 21))[0] / len(i),
        "depth_edges_share": edges / max(compared, 1),
        "mixed_share_of_edges": mixed / max(edges, 1),
    }
    for a, b in itertools.pairwise(RANGE_BANDS_M):
        band = (r >= a) & (r < b)
        out[f"share_{a}_{b}m"] = float(band.mean())
        out[f"intensity_median_{a}_{b}m"] = float(np.median(i[band])) if band.any() else float("nan")
    return out


def simulated(spec_name: str, scene: str, model: str, frames: list[int], seed: int, actors: int):
    """The scans of ``frames`` of the test drive in ``scene`` (parked-car variant 1, ``actors``)."""
    from simbed.scenes.routes import make_route
    from simbed.sim.drive import Drive
    from simbed.sim.world import World

    rng = np.random.default_rng(seed)
    world = World(scene, variant=1, n_actors=actors, rng=rng)
    t = world.town
    route = make_route("test", world.graph, t.lane_width_m, t.road_width_m)
    spec = load_spec(spec_name)
    drive = Drive(world, route, spec, rng, sensor_model=model)
    out = []
    for k in range(max(frames) + 1):
        f = drive.next_frame()
        if k in frames:
            s = f.sweep
            rows = spec.row_of_beam[s.ring.astype(np.int64)]
            cols = s.column.astype(np.int64)
            out.append((s.points.astype(np.float64), s.intensity.astype(np.float64), rows, cols))
    return out


def pooled(stats: list[dict]) -> dict:
    """The median of each figure over frames (curves element by element)."""
    return {k: np.median(np.array([s[k] for s in stats]), axis=0) for k in stats[0]}


SCALARS = [
    ("points", "points per scan", "{:,.0f}"),
    ("grid_filled", "returns per beam and turn, over 2,083", "{:.3f}"),
    ("range_median_m", "median range (m)", "{:.1f}"),
    ("range_p95_m", "95th percentile range (m)", "{:.1f}"),
    ("share_0_10m", "share of points within 10 m", "{:.2f}"),
    ("share_10_20m", "share 10-20 m", "{:.2f}"),
    ("share_20_40m", "share 20-40 m", "{:.2f}"),
    ("share_40_80m", "share 40-80 m", "{:.3f}"),
    ("intensity_median", "median intensity (0..1)", "{:.2f}"),
    ("intensity_p10", "10th percentile intensity", "{:.2f}"),
    ("intensity_p90", "90th percentile intensity", "{:.2f}"),
    ("intensity_zero_share", "share of intensity exactly 0", "{:.3f}"),
    ("intensity_median_0_10m", "median intensity within 10 m", "{:.2f}"),
    ("intensity_median_10_20m", "median intensity 10-20 m", "{:.2f}"),
    ("intensity_median_20_40m", "median intensity 20-40 m", "{:.2f}"),
    ("intensity_median_40_80m", "median intensity 40-80 m", "{:.2f}"),
    ("depth_edges_share", "share of cells at depth edges", "{:.3f}"),
    ("mixed_share_of_edges", "mixed pixels among depth-edge cells", "{:.3f}"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", required=True, help="a real HDL-64E scan, KITTI .bin")
    ap.add_argument("--out", required=True, help="folder for table.md, stats.csv, realism.png")
    ap.add_argument("--scene", default="town_small")
    ap.add_argument("--frames", default="20,40,60,80,100", help="frames of the test drive compared")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--actors", type=int, default=10)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_spec(SENSOR)
    pts, inten = read_scan_bin(args.real)
    pts = pts.astype(np.float64)
    real = statistics(pts, inten.astype(np.float64), kitti_rows(pts), spec, unit_intensity=True)
    frames = [int(f) for f in args.frames.split(",")]
    sources = {"real (KITTI)": real}
    for model in ("ideal", "realistic"):
        scans = simulated(SENSOR, args.scene, model, frames, args.seed, args.actors)
        stats = [statistics(p, i, rows, spec, True, cols) for p, i, rows, cols in scans]
        sources[f"simulated, {model}"] = pooled(stats)

    names = list(sources)
    lines = ["| statistic | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for key, label, fmt in SCALARS:
        lines.append(f"| {label} | " + " | ".join(fmt.format(float(sources[n][key])) for n in names) + " |")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    with open(out / "stats.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["statistic", *names])
        for key, _, _ in SCALARS:
            wr.writerow([key, *(f"{float(sources[n][key]):.6g}" for n in names)])
        for key in ("fill_by_row", "range_hist", "intensity_hist"):
            for k in range(len(real[key])):
                wr.writerow([f"{key}[{k}]", *(f"{float(sources[n][key][k]):.6g}" for n in names)])
    (out / "command.txt").write_text("python " + " ".join(shlex.quote(a) for a in sys.argv) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    for n in names:
        s = sources[n]
        ax[0].plot(np.arange(spec.beams), s["fill_by_row"], label=n)
        ax[1].plot(RANGE_BINS_M[:-1] + 1, s["range_hist"], label=n)
        ax[2].plot(np.linspace(0.025, 0.975, 20), s["intensity_hist"], label=n)
    ax[0].set(
        xlabel="beam row (0: highest)", ylabel="returns per column of the turn", title="returns by beam row"
    )
    ax[1].set(xlabel="range (m)", ylabel="share of points per 2 m", title="ranges")
    ax[2].set(xlabel="intensity (0..1)", ylabel="share of points per 0.05", title="intensities")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(out / "realism.png", dpi=110)
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()
