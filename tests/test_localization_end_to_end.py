"""The whole pipeline on the small town: a recorded mapping drive becomes a map, a second drive along the
same roads (other parked cars, moving actors, its own seed) is localized in it, globally and by
tracking, and the estimates are checked against the recording's ground truth; the demo's plumbing on a
few frames; and the CLI's answers."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from rangemcl.datasets.kitti import load_sequence
from rangemcl.localization import LocalizerSettings
from rangemcl.localization.pipeline import RunOptions, localize_sequence
from rangemcl.se2 import xyyaw_of
from simbed.record import record


@pytest.fixture(scope="module")
def town(small_town_map):
    root, _ = small_town_map
    record(
        "town_small",
        "mapping",
        "os1-64",
        root / "test_run",
        frames=60,
        seed=8,
        variant=1,
        actors=4,
        progress=False,
    )
    return root


def small() -> LocalizerSettings:
    s = LocalizerSettings()
    s.particles.global_count = 3000
    s.observation.rays = 200
    return s


def test_tracking_in_a_built_map_against_ground_truth(town):
    out = town / "tracking"
    summary = localize_sequence(
        town / "test_run",
        town / "map",
        out,
        small(),
        RunOptions(mode="tracking", seed=0, threads=2, plots=False),
    )
    m = json.loads((out / "metrics.json").read_text())
    assert summary["recoveries"] == 0
    assert m["success"] and m["location_rmse_m"] < 0.25 and m["yaw_rmse_deg"] < 1.0


def test_realtime_replay_drops_the_scans_that_arrive_while_the_localizer_is_busy(town, monkeypatch):
    """--realtime with a localizer whose every step takes 0.25 s of a 0.1 s frame period (the steps' timing
    patched; the filter itself runs): after each scan it takes, the next two arrive while it is busy and are
    dropped (prediction only, `late` in frames.csv, counted in the summary), the third is taken; the
    tracking still holds the truth; and a resumed run carries on the pattern."""
    import csv
    from dataclasses import replace

    from rangemcl.localization.filter import MonteCarloLocalizer

    step = MonteCarloLocalizer.step
    calls = {"n": 0, "stop_at": 17}

    def slow(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == calls["stop_at"]:  # an interruption (Ctrl-C) at the 17th frame
            raise KeyboardInterrupt
        return replace(step(self, *args, **kwargs), seconds=0.25)

    monkeypatch.setattr(MonteCarloLocalizer, "step", slow)
    out = town / "realtime"
    opts = RunOptions(mode="tracking", seed=0, threads=2, plots=False, realtime=True, frames=30)
    with pytest.raises(KeyboardInterrupt):
        localize_sequence(town / "test_run", town / "map", out, small(), opts)
    summary = localize_sequence(town / "test_run", town / "map", out, small(), replace(opts, resume=True))
    assert summary["resumed_at_frames"] == [10]  # the last checkpoint: frames 10-29 again
    rows = list(csv.DictReader((out / "frames.csv").open()))
    late = [r["late"] == "1" for r in rows]
    assert late == [k % 3 != 0 for k in range(30)]
    assert summary["late_scans"] == 20 and summary["skipped_scans"] == 0
    assert summary["frames_localized_from_scans"] == 10
    assert all(r["updated"] == "0" for r, dropped in zip(rows, late, strict=True) if dropped)
    m = json.loads((out / "metrics.json").read_text())
    assert m["success"] and m["location_rmse_m"] < 0.25
    offline = localize_sequence(
        town / "test_run", town / "map", town / "offline", small(), replace(opts, realtime=False)
    )
    assert offline["late_scans"] == 0 and offline["frames_localized_from_scans"] == 30


def test_global_localization_in_a_built_map_against_ground_truth(town):
    out = town / "global"
    summary = localize_sequence(
        town / "test_run", town / "map", out, small(), RunOptions(mode="global", seed=1, threads=2)
    )
    m = json.loads((out / "metrics.json").read_text())
    assert summary["converged_frame"] is not None and summary["converged_frame"] < 45
    assert m["success"] and m["final_location_error_m"] < 0.5
    assert (out / "particles.png").is_file() and (out / "trajectory.png").is_file()
    # the first correct fix: the convergence frame's compute from frames.csv and the distance driven
    assert m["first_fix_frame"] == summary["converged_frame"] == m["converged_frame"]
    frames = np.genfromtxt(out / "frames.csv", delimiter=",", names=True)
    k = m["first_fix_frame"] - m["first_frame"]
    assert "first_fix_seconds" not in m  # a timing: in summary.json, not in the repeatable metrics.json
    assert summary["first_fix_seconds"] == pytest.approx(frames["seconds"][: k + 1].sum(), rel=1e-3)
    seq = load_sequence(town / "test_run")
    truth = xyyaw_of(seq.poses[: k + 1] @ seq.calib_Tr)[:, :2]
    assert m["first_fix_driven_m"] == pytest.approx(np.linalg.norm(np.diff(truth, axis=0), axis=1).sum())
    # before the first frame: the map opened, the filter built, the place prior loaded (stored in the map)
    parts = summary["startup"]
    assert summary["startup_seconds"] == pytest.approx(parts["load_s"] + parts["filter_s"] + parts["prior_s"])
    assert frames["seconds"][0] < 5 * np.median(frames["seconds"][: k + 1]) + 0.5  # no start-up in frame 0


def test_cli_localize_and_evaluate(town):
    out = town / "cli"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "rangemcl.cli",
            "localize",
            str(town / "test_run"),
            "--map",
            str(town / "map"),
            "--out",
            str(out),
            "--mode",
            "tracking",
            "--frames",
            "15",
            "--no-plots",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "frames" in r.stdout and "metrics: success" in r.stdout
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "rangemcl.cli",
            "evaluate",
            str(out),
            "--gt",
            str(town / "test_run" / "poses.txt"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.splitlines()[0])["success"] is True
    # bad input: one line, exit status 2
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "rangemcl.cli",
            "localize",
            str(town / "test_run"),
            "--map",
            str(town / "nope"),
            "--out",
            str(town / "x"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "nope" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "rangemcl.cli", "evaluate", str(town / "nothing"), "--gt", "poses.txt"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "summary.json" in r.stderr


def test_demo_plumbing_on_a_few_frames(tmp_path):
    from simbed.demo import DemoSettings, run_demo

    lines: list[str] = []
    s = DemoSettings(mapping_frames=30, map_every_nth=3, test_frames=20, actors=2, particles=300)
    summary = run_demo(tmp_path / "demo", s, say=lines.append)
    for name in (
        "mapping_drive/meta.yaml",
        "map/map.yaml",
        "test_drive/meta.yaml",
        "results/summary.json",
        "results/metrics.json",
        "results/trajectory.png",
        "demo_summary.json",
        "demo.yaml",
    ):
        assert (tmp_path / "demo" / name).is_file(), name
    assert summary["frames"] == 20 and set(summary["demo_seconds"]) >= {"map", "localize", "total"}
    assert any(line.startswith("[localize]") for line in lines)
    # a finished demo is not run over without a word, nor one with other settings
    from rangemcl.errors import InputError
    from simbed.demo import check_demo_folder

    with pytest.raises(InputError, match=r"finished.*--overwrite"):
        run_demo(tmp_path / "demo", s, say=lines.append)
    with pytest.raises(InputError, match=r"other settings \(seed\).*--overwrite"):
        run_demo(tmp_path / "demo", DemoSettings(**{**s.__dict__, "seed": 5}), say=lines.append)
    assert check_demo_folder(tmp_path / "demo", s, overwrite=True) is False  # would replace it
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="holds no demo results"):
        run_demo(tmp_path / "other", s, say=lines.append)
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"
    # an interrupted demo (its localization not finished) continues: the finished steps are reused
    (tmp_path / "demo" / "demo_summary.json").unlink()
    again: list[str] = []
    run_demo(tmp_path / "demo", s, say=again.append)
    assert any("continuing" in line for line in again)
    assert sum("reusing" in line for line in again) == 3


def _localize_cmd(town, out, *extra) -> list[str]:
    config = town / "small.yaml"
    config.write_text("particles:\n  global_count: 3000\nobservation:\n  rays: 200\n")
    return [
        sys.executable,
        "-m",
        "rangemcl.cli",
        "localize",
        str(town / "test_run"),
        "--map",
        str(town / "map"),
        "--out",
        str(out),
        "--config",
        str(config),
        "--seed",
        "1",
        "--threads",
        "1",
        "--no-plots",
        *extra,
    ]


def _run_until(cmd: list[str], frames_csv, rows: int, sig) -> int:
    """Start ``cmd``, send ``sig`` once ``frames_csv`` holds ``rows`` frames; its exit status."""
    import time

    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            if len(frames_csv.read_text().splitlines()) > rows:
                break
        except OSError:
            pass
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before frame {rows}: {proc.stderr.read()}"
    proc.send_signal(sig)
    proc.wait(timeout=60)
    return proc.returncode


def test_localize_resumes_after_sigterm_and_sigkill_to_the_same_results(town):
    """A global localization stopped by SIGTERM during the search, resumed, killed by SIGKILL after
    convergence, resumed again: the same estimate_kitti.txt, metrics and particle snapshots as one
    uninterrupted run with the same seed; the folder's checkpoint is gone once the run finishes."""
    import signal

    full = town / "resume_full"
    r = subprocess.run(_localize_cmd(town, full), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr

    part = town / "resume_part"
    status = _run_until(_localize_cmd(town, part), part / "frames.csv", 14, signal.SIGTERM)
    assert status == 130
    summary = json.loads((part / "summary.json").read_text())
    assert summary["interrupted"] and summary["frames"] >= 14 and (part / ".resume" / "state.npz").is_file()
    # the folder is not taken for a new run without a word
    r = subprocess.run(_localize_cmd(town, part), capture_output=True, text=True)
    assert r.returncode == 2 and "--resume" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    # another seed is not the same run
    r = subprocess.run(_localize_cmd(town, part, "--resume", "--seed", "2"), capture_output=True, text=True)
    assert r.returncode == 2 and "seed" in r.stderr

    status = _run_until(_localize_cmd(town, part, "--resume"), part / "frames.csv", 41, signal.SIGKILL)
    assert status == -signal.SIGKILL
    r = subprocess.run(_localize_cmd(town, part, "--resume"), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for name in ("estimate_kitti.txt", "estimate_tum.txt", "metrics.json", "particles.npz"):
        assert (part / name).read_bytes() == (full / name).read_bytes(), name
    rows = [line.split(",")[:12] for line in (part / "frames.csv").read_text().splitlines()]
    assert rows == [line.split(",")[:12] for line in (full / "frames.csv").read_text().splitlines()]
    summary = json.loads((part / "summary.json").read_text())
    assert not summary["interrupted"] and len(summary["resumed_at_frames"]) == 2
    assert not (part / ".resume").exists()
    r = subprocess.run(_localize_cmd(town, part, "--resume"), capture_output=True, text=True)
    assert r.returncode == 2 and "finished" in r.stderr


def _refuses_a_missing_drive(tool, town) -> None:
    """A tool given a drive that does not exist: one error line naming it, exit status 2."""
    r = subprocess.run(
        [sys.executable, str(tool), "--seq", str(town / "nope"), "--map", str(town / "map")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "nope" in r.stderr, r.stderr


def test_likelihood_peak_tool_finds_the_true_pose_best(town, tmp_path):
    """tools/likelihood_peak.py on the test drive: the true pose fits better (a smaller mean residual) than
    every moved pose at the median, and the evidence against a pose grows with its offset."""
    from pathlib import Path

    tool = Path(__file__).resolve().parents[1] / "tools" / "likelihood_peak.py"
    out = tmp_path / "peak.json"
    args = ["--seq", str(town / "test_run"), "--map", str(town / "map"), "--every", "10", "--last", "50"]
    r = subprocess.run(
        [sys.executable, str(tool), *args, "--json", str(out)], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr
    peak = json.loads(out.read_text())
    assert peak["scans"] == 5
    off = peak["offsets"]
    true_d = off["true"]["median_d_m"]
    assert all(v["median_d_m"] > true_d for k, v in off.items() if k != "true")
    for axis in ("forward", "lateral"):
        assert off[f"{axis} 1 m"]["median_nats"] > off[f"{axis} 0.1 m"]["median_nats"] > 0
    assert off["yaw 5 deg"]["median_nats"] > off["yaw 0.5 deg"]["median_nats"] > 0
    _refuses_a_missing_drive(tool, town)


def test_search_trace_tool_follows_a_global_search(town, tmp_path):
    """tools/search_trace.py replays a global search on the test drive and says where the truth stands at
    every update of it; bad input is one line and exit status 2."""
    import csv
    from pathlib import Path

    tool = Path(__file__).resolve().parents[1] / "tools" / "search_trace.py"
    out = tmp_path / "trace.csv"
    args = ["--seq", str(town / "test_run"), "--map", str(town / "map"), "--frames", "30", "--seed", "1"]
    r = subprocess.run(
        [sys.executable, str(tool), *args, "--particles", "2000", "--csv", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(out.open()))
    # the same run as rangemcl localize's with these settings: it converges at the same frame
    run = tmp_path / "run"
    seq, m = str(town / "test_run"), str(town / "map")
    cli = [sys.executable, "-m", "rangemcl.cli", "localize", seq, "--map", m]
    opts = ["--out", str(run), "--frames", "30", "--seed", "1", "--particles", "2000", "--no-plots"]
    c = subprocess.run([*cli, *opts], capture_output=True, text=True, timeout=600)
    assert c.returncode == 0, c.stderr
    frame = json.loads((run / "summary.json").read_text())["converged_frame"]
    assert frame is not None and f"converged at frame {frame}" in r.stdout, r.stdout
    # one row per search update up to the convergence, which is at the true place
    assert [int(x["converged"]) for x in rows] == [0] * (len(rows) - 1) + [1]
    assert int(rows[-1]["frame"]) == frame
    assert float(rows[-1]["leader_error_m"]) < 1.0 and rows[-1]["true_rank"] == "0"
    assert all(float(x["d_cloud_best_m"]) <= float(x["d_near_best_m"]) for x in rows if x["d_near_best_m"])
    _refuses_a_missing_drive(tool, town)


def test_ray_breakdown_tool_classes_every_ray_and_costs_it_as_the_kernel_does(town, tmp_path):
    """tools/ray_breakdown.py on the test drive (parked-car set 1 against the map's 0): every ray in one
    class, the classes' shares adding up, and the mean of the per-ray costs it computes equal to the
    localizer's own mean residual at the same pose (the kernel's), and the scan's likelihood along the
    street peaking at the true pose; a scene without parked cars is one error line and exit status 2."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    tool = root / "tools" / "ray_breakdown.py"
    seq, m = str(town / "test_run"), str(town / "map")
    for config in ([], ["--config", str(root / "configs" / "v0.17.yaml")]):
        args = [
            "--seq",
            seq,
            "--map",
            m,
            "--scene",
            str(root / "scenes" / "town_small.xml"),
            "--frames",
            "20",
        ]
        r = subprocess.run(
            [
                sys.executable,
                str(tool),
                *args,
                "--particles",
                "500",
                "--along",
                "0.5",
                "--draws",
                "2",
                *config,
            ],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert r.returncode == 0, r.stderr
        head = re.search(r"d at the truth ([\d.]+) m, best of 500 spread poses ([\d.]+) m", r.stdout)
        assert head, r.stdout
        costs = [float(x) for x in re.findall(r"mean cost ([\d.]+) m", r.stdout)]
        assert costs == [pytest.approx(float(head[1]), abs=2e-3), pytest.approx(float(head[2]), abs=2e-3)]
        peaks = re.search(
            r"peaks at ([-+\d.]+) m \(all rays\), (\S+)(?: m)? \(the (\d+)% on parked cars\)", r.stdout
        )
        assert peaks, r.stdout
        # the test drive's map comes from the same street: the scan's likelihood peaks at the true pose
        # (within a step of 0.05 m), for all its rays
        assert abs(float(peaks[1])) <= 0.05, r.stdout
        blocks = r.stdout.split("  best ")
        for block in blocks:
            shares = [int(x) for x in re.findall(r"(\d+)% of the rays", block)]
            assert 98 <= sum(shares) <= 102, r.stdout  # each share rounded to a whole per cent
    bare = tmp_path / "bare.xml"
    bare.write_text("<mujoco><worldbody/></mujoco>\n")
    r = subprocess.run(
        [sys.executable, str(tool), "--seq", seq, "--map", m, "--scene", str(bare), "--frames", "20"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "bare.xml" in r.stderr, r.stderr
