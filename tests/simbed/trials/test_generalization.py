"""The generalization suite: towns drawn from one run seed (fresh, or given to repeat a run), one-line errors
for bad draws, the report's figures and targets on synthetic rows (the held-frames rule included), and a
quick run end to end through the console script that continues without running anything again."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys

import pytest

from rangemcl.errors import InputError
from simbed.trials import generalization as gen
from simbed.trials.generalization import (
    GeneralizationSettings,
    Targets,
    check_generalization,
    check_targets,
    draw_towns,
    generalization_settings,
    parse_sizes,
    parse_styles,
    start_run,
    summarize,
    write_generalization_report,
)
from simbed.trials.suites import ROW_FIELDS, read_results, results_columns, wrong_held_max_frames


@pytest.fixture
def three_styles(monkeypatch):
    """Three named styles, whatever the town generator offers today."""
    from simbed.scenes.towngen import DEFAULT_STYLE

    monkeypatch.setattr(
        gen, "named_styles", lambda: {"a": DEFAULT_STYLE, "b": DEFAULT_STYLE, "c": DEFAULT_STYLE}
    )


def test_a_run_seed_draws_the_same_towns_and_fresh_ones_differ(three_styles):
    s = GeneralizationSettings(towns=5, sizes_m=(200, 500))
    towns = draw_towns(s, 1234)
    assert towns == draw_towns(s, 1234)
    assert draw_towns(s, 1235) != towns
    assert len(towns) == 5 and len({t.name for t in towns}) == 5
    assert all(200 <= t.size_m <= 500 and t.seed >= 0 for t in towns)
    styles = [t.style for t in towns]
    assert sorted(styles[:3]) == ["a", "b", "c"] and styles[3:] == styles[:2]  # cycled in a drawn order
    assert all(t.name == f"t{i + 1:02d}-{t.style}-{t.size_m}m-s{t.seed}" for i, t in enumerate(towns))
    # given town seeds are kept (sizes and styles still drawn); the number of towns follows them
    given = draw_towns(generalization_settings(town_seeds=(12, 873)), 1234)
    assert [t.seed for t in given] == [12, 873]
    assert draw_towns(generalization_settings(sizes="300", styles="b"), 9)[0].size_m == 300
    assert {t.style for t in draw_towns(generalization_settings(styles="b,c"), 9)} == {"b", "c"}
    assert gen.fresh_run_seed() != gen.fresh_run_seed()  # from the OS (equal once in 2**32)


def test_the_run_seed_is_recorded_and_a_folder_continues_its_own_run(tmp_path, three_styles):
    s = GeneralizationSettings(towns=2)
    lines: list[str] = []
    record, towns = start_run(tmp_path, s, None, lines.append)  # a fresh run seed
    seed = record["run_seed"]
    assert lines[0].startswith(f"run seed {seed} (--run-seed {seed} repeats this run)")
    assert all(any(f"seed {t.seed}" in line for line in lines) for t in towns)
    again, towns_again = start_run(tmp_path, s, None, lines.append)  # no seed given: the recorded one
    assert again["run_seed"] == seed and towns_again == towns
    assert gen.read_towns_yaml(tmp_path)["towns"][1]["name"] == towns[1].name
    with pytest.raises(InputError, match="holds another draw of towns"):
        start_run(tmp_path, s, seed + 1, lines.append)
    with pytest.raises(InputError, match="holds another draw of towns"):
        start_run(tmp_path, GeneralizationSettings(towns=3), None, lines.append)


def test_bad_draws_and_options_are_one_line_errors():
    assert parse_sizes("200-500") == (200, 500) and parse_sizes(" 300 ") == (300, 300)
    for bad in ("100-300", "300-200", "a-b", "1-2-3", "", "200-9000"):
        with pytest.raises(InputError, match="--sizes"):
            parse_sizes(bad)
    assert parse_styles("grid") == ("grid",)
    assert gen.town_style("grid") is gen.named_styles()["grid"]
    with pytest.raises(InputError, match="town style 'nope': expected one of grid"):
        parse_styles("grid,nope")
    with pytest.raises(InputError, match="--styles"):
        parse_styles(" , ")
    with pytest.raises(InputError, match="--town-seeds: seeds must be non-negative"):
        draw_towns(generalization_settings(town_seeds=(1, -2)), 0)
    with pytest.raises(InputError, match="--town-seeds: 2 seeds for 3 towns"):
        draw_towns(generalization_settings(towns=3, town_seeds=(1, 2)), 0)
    with pytest.raises(InputError, match="--run-seed"):
        draw_towns(GeneralizationSettings(), -1)
    with pytest.raises(InputError, match="--towns must be >= 1"):
        draw_towns(GeneralizationSettings(towns=0), 0)
    with pytest.raises(InputError, match="--variant must be one of the towns' 2 parked-car variants"):
        check_generalization(generalization_settings(suite={"variant": 2}))
    with pytest.raises(InputError, match="--frames must be >= 1"):
        check_generalization(generalization_settings(suite={"frames": 0}))
    with pytest.raises(InputError, match="nope"):
        check_generalization(generalization_settings(suite={"sensors": ("nope",)}))
    # quick: one town, one sensor, one start; options given replace its values
    quick = generalization_settings(True, suite={"starts": 2})
    assert quick.towns == 1 and quick.suite.sensors == ("os1-64",) and quick.suite.starts == 2
    full = GeneralizationSettings()
    assert (full.suite.drive_frames, full.suite.frames, full.suite.starts) == (800, 100, 5)
    assert (full.suite.variant, full.suite.actors, full.suite.particles) == (1, 10, 10000)


def _row(town, sensor, success=True, conv=20, rmse=0.05, wrong=0, uncaught=0, held="0", alarms=0, method=""):
    return {
        "town": town,
        "town_seed": "1",
        "town_size_m": "200",
        "town_style": "grid",
        "method": method,
        "sensor": sensor,
        "key": f"{town}-{sensor}-{conv}-{rmse}",
        "success": str(success),
        "frames_to_converge": "" if conv is None else str(conv),
        "frames_after_convergence": "80",
        "location_rmse_m": str(rmse) if success else "",
        "yaw_rmse_deg": "0.2" if success else "",
        "location_median_m": "0.04",
        "hz_after": "30",
        "seconds_per_frame_before": "1",
        "relocalized_after_frames": "",
        "wrong_convergences": str(wrong),
        "wrong_convergences_uncaught": str(uncaught),
        "wrong_held_max_frames": held,
        "false_alarms": str(alarms),
    }


TARGETS = ("success", "held", "alarms", "mq8_rmse", "median")  # check_targets' order


def _verdict(rows):
    return dict(zip(TARGETS, (ok for _, ok, _ in check_targets(rows)), strict=True))


def test_report_figures_and_targets_on_synthetic_rows(tmp_path):
    rows = [
        *(_row(f"t0{k}", "mq-8", rmse=0.06 + 0.01 * k) for k in range(1, 4)),
        _row("t01", "os1-64", wrong=1, uncaught=0, held="8"),  # caught within 10 frames: fine
        _row("t02", "os1-64", conv=30),
        _row("t03", "os1-64", success=False, conv=None),
    ]
    by_sensor = {a["sensor"]: a for a in summarize(rows, ["sensor"])}
    mq8, os1 = by_sensor["mq-8"], by_sensor["os1-64"]
    assert mq8["success"] == "3/3" and mq8["location_rmse_max_m"] == pytest.approx(0.09)
    assert mq8["location_rmse_m"] == pytest.approx(((0.07**2 + 0.08**2 + 0.09**2) / 3) ** 0.5)
    assert os1["success"] == "2/3" and os1["frames_to_converge_median"] == 25
    assert (os1["wrong_convergences"], os1["wrong_caught"], os1["wrong_uncaught"]) == (1, 1, 0)
    assert os1["wrong_held_max_frames"] == 8 and os1["trials_held_too_long"] == 0
    per_town = summarize(rows, ["town", "sensor"])
    assert [(a["town"], a["sensor"]) for a in per_town][:2] == [("t01", "mq-8"), ("t01", "os1-64")]

    got = _verdict(rows)
    assert got["success"] is False  # os1-64: 2/3 < 90 %
    assert got["held"] and got["alarms"] and got["mq8_rmse"] and got["median"]
    good = [r for r in rows if r["success"] == "True"]
    assert all(ok for _, ok, _ in check_targets(good))
    # the held-frames rule: a wrong convergence not undone within 10 frames, or held longer, fails
    for held, uncaught in (("12", 0), ("12", 1), ("", 1)):  # "": a row of an earlier revision
        bad = [*good, _row("t04", "os1-64", wrong=1, uncaught=uncaught, held=held)]
        assert _verdict(bad)["held"] is False
    assert _verdict([*good, _row("t04", "os1-64", wrong=2, held="10")])["held"] is True
    # one false alarm; an MQ-8 trial above 0.10 m; a sensor converging slowly; no MQ-8 at all
    assert _verdict([*good, _row("t04", "os1-64", alarms=1)])["alarms"] is False
    assert _verdict([*good, _row("t04", "mq-8", rmse=0.11)])["mq8_rmse"] is False
    assert _verdict([*good, *(_row(f"t{k}", "os1-64", conv=60) for k in range(4))])["median"] is False
    assert _verdict([r for r in good if r["sensor"] != "mq-8"])["mq8_rmse"] is None
    assert Targets().min_success_rate == 0.9

    record = {
        "run_seed": 77,
        "towns": [{"name": f"t0{k}", "seed": k, "size_m": 200, "style": "grid"} for k in range(1, 4)],
    }
    verdicts = write_generalization_report(tmp_path, record, rows, expected=8)
    assert len(verdicts) == 1 and verdicts[0].startswith("targets (default): FAIL")
    md = (tmp_path / "generalization.md").read_text()
    assert "Run seed 77 (`--run-seed 77` repeats this run)" in md and "6 of 8 trials finished" in md
    assert "| sensor | trials | success |" in md and "| town | sensor | trials |" in md
    assert "| t02 | grid | 200 | 2 | – |" in md  # the towns with their seeds
    assert verdicts[0] in md
    with open(tmp_path / "generalization.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 6 and table[0]["town"] == "t01" and list(table[0])[:4] == gen.TOWN_COLUMNS
    # two methods: side by side, a verdict each
    other = [{**r, "method": "paper"} for r in good]
    verdicts = write_generalization_report(tmp_path, record, [*rows, *other], expected=16)
    assert [v.split(":")[0] for v in verdicts] == ["targets (default)", "targets (paper)"]
    assert "| method | sensor | trials |" in (tmp_path / "generalization.md").read_text()


def test_wrong_convergences_held_from_a_trials_metrics():
    def metrics(*wrong, first=100, frames=50):
        return {
            "first_frame": first,
            "frames": frames,
            "wrong_convergences": [{"frame": f, "caught_frame": c} for f, c in wrong],
        }

    assert wrong_held_max_frames(metrics()) == 0
    assert wrong_held_max_frames(metrics((110, 114), (120, 133))) == 13  # to the re-spread that undid it
    assert wrong_held_max_frames(metrics((110, 114), (140, None))) == 10  # never undone: to the trial's end


def test_an_older_results_csv_gets_the_new_columns(tmp_path):
    path = tmp_path / "results.csv"
    old = [c for c in ROW_FIELDS if c != "wrong_held_max_frames"]
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=old)
        w.writeheader()
        w.writerow({c: f"{c}-1" for c in old})
    assert results_columns(path) == ROW_FIELDS
    rows = read_results(path)
    assert len(rows) == 1 and rows[0]["wrong_held_max_frames"] == "" and rows[0]["key"] == "key-1"
    assert results_columns(path) == ROW_FIELDS and results_columns(tmp_path / "new.csv") == ROW_FIELDS


def simbed(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run(
        [sys.executable, "-m", "simbed.cli", *args], capture_output=True, text=True, timeout=900, env=env
    )


def test_quick_run_end_to_end_and_continued(tmp_path):
    """One tiny town drawn from run seed 7: its scene, mapping drive, map and one trial; towns.yaml and the
    report name the seeds; the same command again runs nothing; another run seed is refused."""
    out = tmp_path / "gen"
    args = ["trials", "generalization", "--out", str(out), "--quick", "--run-seed", "7", "--workers", "2"]
    r = simbed(*args)
    assert r.returncode == 0, r.stderr
    (town,) = draw_towns(GeneralizationSettings.quick(), 7)
    assert r.stdout.splitlines()[0] == "run seed 7 (--run-seed 7 repeats this run); towns:"
    assert f"{town.name}: seed {town.seed}, 160 m, style grid" in r.stdout
    record = gen.read_towns_yaml(out)
    assert record["run_seed"] == 7
    entry = record["towns"][0]
    assert {k: entry[k] for k in ("name", "seed", "size_m", "style")} == gen._draw_entry(town)
    assert entry["road_length_m"] > 100 and entry["map"]["triangles"] > 1000
    assert entry["mapping_drive"]["frames"] == GeneralizationSettings.quick().mapping_frames
    with open(out / "generalization.csv") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["town"] == town.name and row["town_seed"] == str(town.seed) and row["sensor"] == "os1-64"
    assert row["success"] == "True" and float(row["location_rmse_m"]) < 0.5  # trials run where it mapped
    assert row["wrong_held_max_frames"] == "0"
    md = (out / "generalization.md").read_text()
    assert "Run seed 7" in md and f"| {town.name} | os1-64 | 1 | 1/1 |" in md and "targets (default): " in md
    suite = out / "towns" / town.name / "suite"
    assert (suite / "sensors.md").is_file()
    trial_dir = suite / "trials" / row["key"]
    stamp = (trial_dir / "metrics.json").stat().st_mtime_ns

    again = simbed(*args[:-4], "--workers", "2")  # no --run-seed: the run that towns.yaml recorded
    assert again.returncode == 0, again.stderr
    assert "every trial of this run is finished; the town is not prepared again" in again.stdout
    assert len(read_results(suite / "results.csv")) == 1
    assert (trial_dir / "metrics.json").stat().st_mtime_ns == stamp

    report = simbed(*args[:-4], "--report-only", "--compare", "default")
    assert report.returncode == 0 and "1 of 1 trials finished" in report.stdout, report.stderr

    # a second method on the same trials in one command: --config's runs, --compare's is already done
    short = tmp_path / "short.yaml"
    short.write_text("observation:\n  cap_short_m: 0.3\n")
    both = simbed(*args[:-4], "--workers", "2", "--config", str(short), "--compare", "default")
    assert both.returncode == 0, both.stderr
    assert "1 trials, 0 already done" in both.stdout and "1 trials, 1 already done" in both.stdout
    for step in ("scene: reusing", "mapping drive: reusing", "map: reusing"):  # a trial left: the town
        assert step in both.stdout, both.stdout
    with open(out / "generalization.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["method"] for r in rows) == ["default", "short"]
    assert len({r["drive_seed"] + r["start_frame"] + r["seed"] for r in rows}) == 1  # the same trial
    assert "short" in (suite / "sensors.md").read_text() and "default" in (suite / "sensors.md").read_text()
    assert (trial_dir / "metrics.json").stat().st_mtime_ns == stamp
    # a run continued from its rows alone (the town's files gone) runs nothing and makes no town again
    town_dir = out / "towns" / town.name
    for made in ("map", "mapping_drive", "suite/drives"):
        shutil.rmtree(town_dir / made)
    rows_only = simbed(*args[:-4], "--workers", "2")
    assert rows_only.returncode == 0, rows_only.stderr
    assert "every trial of this run is finished; the town is not prepared again" in rows_only.stdout
    assert not (town_dir / "map").exists() and not (town_dir / "mapping_drive").exists()
    assert "1/1 trials successful" in rows_only.stdout
    other = simbed(*args[:-3], "8")
    assert other.returncode == 2 and "holds another draw of towns (run seed 7" in other.stderr
    assert len(other.stderr.strip().splitlines()) == 1
