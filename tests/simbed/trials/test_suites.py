"""Suites of localization trials: a quick suite on a tiny map produces its results, table and figure, is
resumable, and runs on a local Ray instance; trial lists by their definitions."""

from __future__ import annotations

import csv
import json
import re
from dataclasses import replace

import pytest

from rangemcl.errors import InputError
from simbed.trials.suites import (
    METHOD_VERSION,
    SUITES,
    SuiteConfig,
    aggregate,
    run_suite,
    suite_settings,
    suite_trials,
)

CONFIG = SuiteConfig(route="mapping", drive_frames=50, frames=30, actors=2, starts=2)


@pytest.fixture(scope="module")
def tiny_map(small_town_map):
    return small_town_map[1]


def test_suite_definitions():
    for suite in SUITES:
        quick, full = suite_trials(suite, True), suite_trials(suite, False)
        assert 0 < len(quick) < len(full)
        assert len({t.key for t in full}) == len(full)  # every trial has its own results folder
    sizes = sorted({t.particles for t in suite_trials("particles")})
    assert sizes == [1000, 5000, 10000, 50000, 100000]
    assert {t.model for t in suite_trials("particles")} == {
        "range",
        "overlap",
        "likelihood_field",
        "histogram",
    }
    assert {t.sensor for t in suite_trials("sensors")} == {"mq-8", "vlp-16", "hdl-32e", "hdl-64e", "os1-128"}
    assert all(t.kidnap for t in suite_trials("kidnap"))
    starts = [
        t.start_frame for t in suite_trials("kidnap", config=SuiteConfig(drive_frames=1000, frames=250))
    ]
    assert starts[0] == 0 and starts[-1] == 750 and starts == sorted(starts)
    with pytest.raises(InputError, match="suite 'nope'"):
        suite_trials("nope")


def test_suite_subsets_of_counts_and_models():
    c = SuiteConfig(starts=3, particle_counts=(1000, 5000), models=("range", "histogram"))
    got = suite_trials("particles", config=c)
    assert len(got) == 2 * 2 * 3
    assert {(t.particles, t.model) for t in got} == {
        (p, m) for p in (1000, 5000) for m in ("range", "histogram")
    }
    assert {t.model for t in suite_trials("models", config=c)} == {"range", "histogram"}
    some = suite_trials("sensors", config=SuiteConfig(sensors=("os1-128",), starts=10))
    assert {t.sensor for t in some} == {"os1-128"}
    assert {t.key for t in some} <= {t.key for t in suite_trials("sensors", config=SuiteConfig(starts=10))}
    with pytest.raises(InputError, match="observation model 'beam'"):
        suite_trials("particles", config=SuiteConfig(models=("beam",)))
    with pytest.raises(InputError, match="particle counts"):
        suite_trials("particles", config=SuiteConfig(particle_counts=(0,)))


def test_quick_suite_writes_results_table_and_figure_and_resumes(tiny_map, tmp_path):
    out = tmp_path / "sensors"
    lines: list[str] = []
    rows = run_suite("sensors", out, tiny_map, quick=True, config=CONFIG, workers=2, say=lines.append)
    assert len(rows) == 2 and {r["sensor"] for r in rows} == {"vlp-16", "os1-64"}
    assert all(r["success"] == "True" for r in rows), rows  # the drive runs where the map was built
    assert all(float(r["location_rmse_m"]) < 0.5 for r in rows)
    table = (out / "sensors.md").read_text()
    assert "| sensor |" in table and "vlp-16" in table and "paper_location_rmse_m" in table
    assert "| not_converged | converged_failed |" in table and "| vlp-16 | 1 | 1 | 0 | 0 |" in table
    assert (out / "sensors.png").stat().st_size > 1000
    # the place prior was rendered (or found) once before the trials, and every trial loaded it
    assert sum("place prior" in line for line in lines) == 1
    for r in rows:
        assert json.loads((out / "trials" / r["key"] / "summary.json").read_text())["place_prior"][
            "source"
        ] == ("loaded")
    again: list[str] = []
    rows2 = run_suite("sensors", out, tiny_map, quick=True, config=CONFIG, workers=2, say=again.append)
    assert "2 already done" in again[0] and len(rows2) == 2
    with (out / "results.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 2  # nothing ran twice
    # a report of part of the results (a suite stopped part-way): one of the two trials
    lines = (out / "results.csv").read_text().splitlines(keepends=True)
    (out / "results.csv").write_text("".join(lines[:2]))  # the header and the first trial
    (out / "sensors.md").unlink()
    part = run_suite("sensors", out, tiny_map, quick=True, config=CONFIG, say=again.append, report_only=True)
    assert len(part) == 1 and "1 of 2 trials finished" in again[-1]
    assert "1 trials" in (out / "sensors.md").read_text()
    with pytest.raises(InputError, match="no finished trial"):
        run_suite("kidnap", out, tiny_map, quick=True, config=CONFIG, report_only=True)


def test_suite_on_a_local_ray_instance(tiny_map, tmp_path):
    pytest.importorskip("ray")
    rows = run_suite(
        "runtime",
        tmp_path / "rt",
        tiny_map,
        quick=True,
        config=CONFIG,
        workers=1,
        backend="ray",
        say=lambda _: None,
    )
    assert len(rows) == 1 and float(rows[0]["hz_after"]) > 0
    assert (tmp_path / "rt" / "runtime.md").is_file()


def test_aggregate_weights_rmse_by_frames():
    rows = [
        {
            "model": "range",
            "success": "True",
            "frames_after_convergence": "100",
            "location_rmse_m": "0.1",
            "yaw_rmse_deg": "1.0",
            "frames_to_converge": "10",
            "hz_after": "30",
            "seconds_per_frame_before": "2",
        },
        {
            "model": "range",
            "success": "True",
            "frames_after_convergence": "300",
            "location_rmse_m": "0.3",
            "yaw_rmse_deg": "1.0",
            "frames_to_converge": "20",
            "hz_after": "40",
            "seconds_per_frame_before": "3",
        },
        {
            "model": "range",
            "success": "False",
            "frames_after_convergence": "",
            "location_rmse_m": "",
            "yaw_rmse_deg": "",
            "frames_to_converge": "",
            "hz_after": "",
            "seconds_per_frame_before": "4",
        },
    ]
    # converged to a wrong place: counted as a failure, its convergence and cost still in the medians
    rows.append({**rows[0], "success": "False", "frames_to_converge": "15", "seconds_per_frame_before": "3"})
    (a,) = aggregate(rows, ["model"])
    assert a["trials"] == 4 and a["successes"] == 2
    assert a["not_converged"] == 1 and a["converged_failed"] == 1
    assert a["location_rmse_m"] == pytest.approx(((100 * 0.01 + 300 * 0.09) / 400) ** 0.5)
    assert a["frames_to_converge_median"] == 15 and a["seconds_before_median"] == 3
    assert a["fix_seconds_median"] is None  # rows of earlier revisions: not known
    rows[0]["fix_seconds"], rows[1]["fix_seconds"], rows[1]["fix_driven_m"] = "1.5", "4.5", "12"
    (a,) = aggregate(rows, ["model"])  # rows[3] is rows[0]'s copy from before
    assert a["fix_seconds_median"] == 3.0 and a["fix_driven_m_median"] == 12.0


def test_suite_with_localizer_settings(tiny_map, tmp_path):
    """--config: every trial runs with the file's settings, and its key says so (runs with other settings
    never count as done); a bad file is one clear error naming the file and the key."""
    cfg = tmp_path / "elev.yaml"
    cfg.write_text("observation:\n  ray_sampling: elevation\n  rays: 120\n")
    c = replace(CONFIG, settings=suite_settings(cfg))
    plain, tuned = suite_trials("runtime", True, CONFIG), suite_trials("runtime", True, c)
    rev = f"-v{METHOD_VERSION}"  # every key ends with the localizer's method version (major.minor)
    assert all(a.key.endswith(rev) and b.key.endswith(rev) for a, b in zip(plain, tuned, strict=True))
    assert all(
        re.fullmatch(re.escape(a.key[: -len(rev)]) + "-c[0-9a-f]{8}" + rev, b.key)
        for a, b in zip(plain, tuned, strict=True)
    )
    assert all("-c" not in a.key.rsplit("-", 2)[1] for a in plain)  # default keys carry no settings tag
    out = tmp_path / "rt"
    rows = run_suite("runtime", out, tiny_map, quick=True, config=c, workers=1, say=lambda _: None)
    assert [r["key"] for r in rows] == [t.key for t in tuned]
    used = (out / "trials" / tuned[0].key / "config.yaml").read_text()
    assert "ray_sampling: elevation" in used and "rays: 120" in used and "model: range" in used
    with open(out / "results.csv") as fh:
        assert "settings" not in next(csv.reader(fh))  # the columns stay those of a default run
    bad = tmp_path / "bad.yaml"
    bad.write_text("observation:\n  ray_samplin: elevation\n")
    with pytest.raises(InputError, match=r"bad\.yaml.*ray_samplin"):
        suite_settings(bad)


def test_report_sets_methods_side_by_side_with_their_event_counts(tmp_path):
    def row(method, sensor, success, conv, wrong, uncaught, alarms):
        return {
            "method": method,
            "sensor": sensor,
            "success": str(success),
            "frames_to_converge": conv,
            "frames_after_convergence": "50",
            "location_rmse_m": "0.1",
            "yaw_rmse_deg": "0.2",
            "location_median_m": "0.05",
            "hz_after": "30",
            "seconds_per_frame_before": "1",
            "relocalized_after_frames": "",
            "wrong_convergences": str(wrong),
            "wrong_convergences_uncaught": str(uncaught),
            "false_alarms": str(alarms),
        }

    rows = [
        row("default", "vlp-16", True, "20", 0, 0, 0),
        row("default", "vlp-16", True, "24", 1, 0, 0),
        row("paper", "vlp-16", False, "", 2, 1, 0),
        row("paper", "vlp-16", True, "40", 0, 0, 1),
    ]
    from simbed.trials.suites import write_report

    md, _ = write_report("sensors", rows, tmp_path)
    table = md.read_text()
    assert (
        "| method | sensor | trials | successes | not_converged | converged_failed | wrong_convergences |"
        in table
    )
    assert "| default | vlp-16 | 2 | 2 | 0 | 0 | 1 | 0 | 0 |" in table
    assert "| paper | vlp-16 | 2 | 1 | 1 | 0 | 2 | 1 | 1 |" in table
    # rows of earlier versions (no method, no counts) still report, without counts
    old = [{k: v for k, v in r.items() if k not in ("method", "false_alarms")} for r in rows[:2]]
    table = write_report("sensors", old, tmp_path)[0].read_text()
    assert "| vlp-16 | 2 | 2 | 0 | 0 | 1 | 0 | – |" in table
    # --report-only --compare: the same trials of another method join the table (keys of both configs)
    cfg = tmp_path / "paper.yaml"
    cfg.write_text("init:\n  place_prior: false\n")
    paper = replace(CONFIG, sensors=("vlp-16",), settings=suite_settings(cfg), method="paper")
    ours = replace(CONFIG, sensors=("vlp-16",))
    keyed = [
        {**rows[k], "key": t.key}
        for k, t in enumerate(suite_trials("sensors", False, ours) + suite_trials("sensors", False, paper))
    ]
    out = tmp_path / "cmp"
    out.mkdir()
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(keyed[0]))
        w.writeheader()
        w.writerows(keyed)
    got = run_suite("sensors", out, None, config=ours, report_only=True, compare=(paper,), say=lambda _: None)
    assert len(got) == 4
    table = (out / "sensors.md").read_text()
    assert "| default | vlp-16 | 2 | 2 |" in table and "| paper | vlp-16 | 2 | 1 |" in table
    alone = run_suite("sensors", out, None, config=ours, report_only=True, say=lambda _: None)
    assert len(alone) == 2 and "| method |" not in (out / "sensors.md").read_text()


def test_suite_folders_follow_the_output_policy(tmp_path):
    """A new suite folder whose run fails at once leaves nothing; a folder holding something else is
    refused even with --overwrite; --report-only and --overwrite exclude each other."""
    import subprocess
    import sys

    def trials(*args):
        return subprocess.run(
            [sys.executable, "-m", "simbed.cli", "trials", "runtime", *args], capture_output=True, text=True
        )

    r = trials("--out", str(tmp_path / "new" / "suite"), "--map", str(tmp_path / "no_map"))
    assert r.returncode == 2 and "no_map" in r.stderr and not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    for extra in ([], ["--overwrite"]):
        r = trials("--out", str(tmp_path / "mine"), "--map", str(tmp_path / "no_map"), *extra)
        assert r.returncode == 2 and "holds no suite results" in r.stderr, r.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    r = trials("--out", str(tmp_path / "x"), "--map", str(tmp_path / "m"), "--report-only", "--overwrite")
    assert r.returncode == 2 and "--overwrite" in r.stderr


def test_drive_keys_of_scene_and_route_files_stay_under_out(tmp_path):
    """A scene or route given as a path names its drive folder by the file's stem and a hash of its absolute
    path (an absolute --scene used to put the drives outside --out); plain names are kept as they are."""
    from simbed.trials.suites import drive_key

    plain = drive_key("town_small", "os1-64", "test", 1, 10, 7, 800)
    assert plain == "town_small-os1-64-test-v1-a10-d7-n800"
    a = drive_key(str(tmp_path / "my_scene.xml"), "os1-64", str(tmp_path / "loop.txt"), 0, 0, 7, 100)
    assert "/" not in a and a.startswith("my_scene-") and "-os1-64-loop-" in a
    assert (tmp_path / "out" / "drives" / a).parent == tmp_path / "out" / "drives"
    assert a == drive_key(str(tmp_path / "my_scene.xml"), "os1-64", str(tmp_path / "loop.txt"), 0, 0, 7, 100)
    other = drive_key(str(tmp_path / "elsewhere" / "my_scene.xml"), "os1-64", "test", 0, 0, 7, 100)
    assert other.split("-")[1] != a.split("-")[1]  # another file of the same name: another folder


def test_robustness_suite_sets_each_realism_level_on_the_same_starts(tmp_path):
    from rangemcl.datasets.kitti import load_sequence
    from simbed.trials.suites import REALISM_LEVELS, ensure_drive

    full = suite_trials("robustness", config=SuiteConfig(starts=3))
    assert len(full) == 5 * len(REALISM_LEVELS) * 3
    assert {t.realism for t in full} == set(REALISM_LEVELS)
    by_level = {
        lv: sorted((t.sensor, t.start_frame, t.seed) for t in full if t.realism == lv)
        for lv in REALISM_LEVELS
    }
    assert all(v == by_level["ideal"] for v in by_level.values())  # the same trials at every level
    # each level has its own drives; the ideal level's are the sensors suite's
    assert len({t.drive_key for t in full}) == 5 * len(REALISM_LEVELS)
    ideal = {t.drive_key for t in full if t.realism == "ideal"}
    assert ideal == {t.drive_key for t in suite_trials("sensors", config=SuiteConfig(starts=3))}
    with pytest.raises(InputError, match="realism level 'snow'"):
        suite_trials("robustness", config=SuiteConfig(levels=("ideal", "snow")))
    # a level's drive is recorded with its sensor model, weather and dropout
    t = replace(full[0], sensor="vlp-16", realism="fog", drive_frames=2, scene="town_small")
    path = ensure_drive(t, tmp_path)
    meta = load_sequence(path).meta
    assert path.name.endswith("-lfog")
    assert meta["sensor_model"] == "realistic" and meta["weather"] == "fog:200"
    t = replace(t, realism="dropout")
    meta = load_sequence(ensure_drive(t, tmp_path)).meta
    assert meta["sensor"]["dropout_prob"] == 0.5


def test_every_suite_runs_at_a_chosen_realism_level():
    """``realism`` (``--realism``) gives every suite but robustness its test drives' sensor: the same
    trials as the ideal sensor's (sensors, starts, seeds), their own drives and keys, which are the
    robustness suite's drives at that level; the default stays the ideal sensor."""
    from simbed.trials.suites import REALISM_LEVELS

    ideal = suite_trials("sensors", config=SuiteConfig(starts=3))
    assert {t.realism for t in ideal} == {"ideal"}
    robust = suite_trials("robustness", config=SuiteConfig(starts=3))
    for level in REALISM_LEVELS:
        got = suite_trials("sensors", config=SuiteConfig(starts=3, realism=level))
        assert {t.realism for t in got} == {level}
        assert [(t.sensor, t.start_frame, t.seed) for t in got] == [
            (t.sensor, t.start_frame, t.seed) for t in ideal
        ]
        assert {t.drive_key for t in got} == {t.drive_key for t in robust if t.realism == level}
        if level != "ideal":
            assert not {t.key for t in got} & {t.key for t in ideal}
    assert {t.realism for t in suite_trials("particles", config=SuiteConfig(realism="rain"))} == {"rain"}
    with pytest.raises(InputError, match="realism level 'snow'"):
        suite_trials("sensors", config=SuiteConfig(realism="snow"))


def test_robustness_report_draws_a_grid_of_presets_and_realism_levels(tmp_path):
    """The robustness figure: one row per method and preset, one column per realism level present (in
    REALISM_LEVELS' order), each cell its successes over its trials; the table lists every cell."""
    import matplotlib.image as mpimg
    import numpy as np

    from simbed.trials.suites import write_report

    def row(method, sensor, realism, success):
        return {
            "method": method,
            "sensor": sensor,
            "realism": realism,
            "success": str(success),
            "frames_to_converge": "20" if success else "",
            "frames_after_convergence": "50",
            "location_rmse_m": "0.01" if success else "",
            "yaw_rmse_deg": "0.02",
            "location_median_m": "0.01",
            "hz_after": "30",
            "seconds_per_frame_before": "1",
            "relocalized_after_frames": "",
            "wrong_convergences": "0",
            "wrong_convergences_uncaught": "0",
            "false_alarms": "0",
        }

    levels = (("ideal", True), ("rain", False))
    rows = [row("fast", s, lv, ok) for s in ("mq-8", "vlp-16") for lv, ok in levels]
    rows += [row("fast_k2", "mq-8", "rain", True), row("fast_k2", "mq-8", "rain", False)]
    md, png = write_report("robustness", rows, tmp_path)
    table = md.read_text()
    assert "| fast | mq-8 | rain | 1 | 0 |" in table and "| fast_k2 | mq-8 | rain | 2 | 1 |" in table
    import matplotlib

    image = mpimg.imread(png)[..., :3]
    cmap = matplotlib.colormaps["RdYlGn"]
    for rate in (0.0, 0.5, 1.0):  # the cells are coloured by their success rate: 0/2, 1/2 and 2/2 appear
        colour = np.asarray(cmap(rate)[:3])
        assert (np.abs(image - colour).max(axis=2) < 0.02).sum() > 500, rate


def test_realtime_trials_are_their_own_method_and_report_their_dropped_scans(tmp_path):
    """--realtime: every trial's key says so (a trial at the sensor's pace never counts as the offline
    one), the CLI names the method '-realtime' (its --compare methods too), and the table counts the scans
    dropped while the localizer was busy."""
    from simbed.cli import _methods
    from simbed.trials.suites import write_report

    offline = suite_trials("sensors", False, replace(CONFIG, sensors=("vlp-16",)))
    paced = suite_trials("sensors", False, replace(CONFIG, sensors=("vlp-16",), realtime=True))
    rev = f"-v{METHOD_VERSION}"
    assert all(
        b.key == a.key[: -len(rev)] + "-rt" + rev and b.realtime and not a.realtime
        for a, b in zip(offline, paced, strict=True)
    )
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("convergence:\n  method: prior\n")
    mine, others = _methods(replace(CONFIG, realtime=True), cfg, ["default"])
    assert mine.method == "fast-realtime" and mine.realtime
    assert [o.method for o in others] == ["default-realtime"] and others[0].realtime
    assert _methods(CONFIG, cfg, None)[0].method == "fast"

    def row(method, late, realtime):
        return {
            "method": method,
            "sensor": "vlp-16",
            "success": "True",
            "frames_to_converge": "20",
            "frames_after_convergence": "50",
            "location_rmse_m": "0.1",
            "yaw_rmse_deg": "0.2",
            "location_median_m": "0.05",
            "hz_after": "30",
            "seconds_per_frame_before": "0.1",
            "relocalized_after_frames": "",
            "late_scans": str(late),
            "realtime": str(realtime),
        }

    rows = [row("fast-realtime", 3, True), row("fast-realtime", 4, True), row("fast", 0, False)]
    table = write_report("sensors", rows, tmp_path)[0].read_text()
    header = next(x for x in table.splitlines() if x.startswith("| method |")).split("|")
    at = [c.strip() for c in header].index("late_scans")
    paced_row = next(x for x in table.splitlines() if x.startswith("| fast-realtime |")).split("|")
    assert paced_row[at].strip() == "7"
    offline_table = write_report("sensors", rows[2:], tmp_path)[0].read_text()
    lines = offline_table.splitlines()
    assert "late_scans" not in lines[lines.index(next(x for x in lines if x.startswith("|---"))) - 1]
