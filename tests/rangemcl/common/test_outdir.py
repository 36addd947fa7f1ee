"""The output policy: results are refused without --overwrite, replaced whole with it, put back
when the replacing run fails, and a failed or refused run leaves nothing it created."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.common.outdir import RESULT_MARKERS, check_output, has_frames, output_folder
from rangemcl.errors import InputError


def _results(folder, tag="old"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "summary.json").write_text(tag)
    (folder / "trajectory.png").write_text(tag)
    return folder


def test_results_are_refused_without_overwrite(tmp_path):
    out = _results(tmp_path / "run")
    with pytest.raises(InputError, match="--overwrite"):
        check_output(out, overwrite=False, kind="localization results", markers=RESULT_MARKERS)
    with (
        pytest.raises(InputError, match="--overwrite"),
        output_folder(out, overwrite=False, kind="localization results", markers=RESULT_MARKERS),
    ):
        pass
    assert (out / "summary.json").read_text() == "old"


def test_foreign_files_are_refused_even_with_overwrite(tmp_path):
    (tmp_path / "thesis.tex").write_text("years of work")
    for overwrite in (False, True):
        with pytest.raises(InputError, match="holds no localization results"):
            check_output(tmp_path, overwrite=overwrite, kind="localization results", markers=RESULT_MARKERS)
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        check_output(tmp_path / "file", overwrite=True, kind="map", markers=("map.yaml",))
    assert (tmp_path / "thesis.tex").read_text() == "years of work"


def test_overwrite_replaces_the_folder_whole(tmp_path):
    out = _results(tmp_path / "run")
    with output_folder(out, overwrite=True, kind="results", markers=RESULT_MARKERS) as d:
        assert list(d.iterdir()) == []  # the new run starts empty
        (d / "summary.json").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]  # the old PNG is gone
    assert (out / "summary.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing set aside is left


def test_a_failed_replacement_puts_the_earlier_results_back(tmp_path):
    out = _results(tmp_path / "run")
    with (
        pytest.raises(InputError, match="bad map"),
        output_folder(out, overwrite=True, kind="results", markers=RESULT_MARKERS) as d,
    ):
        (d / "config.yaml").write_text("half")
        raise InputError("bad map")
    assert sorted(p.name for p in out.iterdir()) == ["summary.json", "trajectory.png"]
    assert (out / "summary.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_failed_run_leaves_nothing_it_created(tmp_path):
    out = tmp_path / "a" / "b" / "run"
    with (
        pytest.raises(RuntimeError),
        output_folder(out, overwrite=False, kind="results", markers=RESULT_MARKERS),
    ):
        (out / "config.yaml").write_text("x")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []  # the parents it made are gone too
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(KeyboardInterrupt), output_folder(empty, overwrite=False, kind="r", markers=("x",)):
        (empty / "config.yaml").write_text("x")
        raise KeyboardInterrupt
    assert empty.is_dir() and list(empty.iterdir()) == []  # the user's folder stays, empty


def test_results_computed_before_a_failure_are_kept(tmp_path):
    out = tmp_path / "run"
    with (
        pytest.raises(KeyboardInterrupt),
        output_folder(out, overwrite=False, kind="results", markers=RESULT_MARKERS, keep_if=has_frames),
    ):
        (out / "frames.csv").write_text("frame,x\n0,1.0\n")
        raise KeyboardInterrupt
    assert has_frames(out)
    assert not has_frames(tmp_path / "nowhere")


def test_cli_import_mesh_follows_the_policy(tmp_path):
    from simbed.sim.geometry import write_ply

    v, f = meshgen.merge([meshgen.grid_patch((0, 0, 0), (50.0, 0, 0), (0, 50.0, 0), 4, 4)])
    mesh = tmp_path / "ground.ply"
    write_ply(mesh, np.asarray(v), np.asarray(f))
    out = tmp_path / "map"

    def run(*extra):
        return subprocess.run(
            [sys.executable, "-m", "rangemcl.cli", "import-mesh", str(mesh), "--out", str(out), *extra],
            capture_output=True,
            text=True,
        )

    assert run().returncode == 0
    (out / "stale.png").write_text("from an earlier run")
    refused = run()
    assert refused.returncode == 2 and "--overwrite" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    assert (out / "stale.png").exists()
    assert run("--overwrite").returncode == 0
    assert not (out / "stale.png").exists() and (out / "map.yaml").exists()
