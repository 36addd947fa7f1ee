"""The console scripts as a user runs them: subprocesses, exit codes, files written."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from rangemcl.datasets.scanio import read_scan_bin, write_scan_bin
from rangemcl.errors import InputError
from rangemcl.sensors import load_spec, preset_names, spec_from_dict


def run(*args: str, cwd=None) -> subprocess.CompletedProcess:
    code = "import sys; from {m}.cli import main; sys.argv[0] = '{m}'; main()".format(m=args[0])
    return subprocess.run(
        [sys.executable, "-c", code, *args[1:]], capture_output=True, text=True, cwd=cwd, timeout=300
    )


@pytest.mark.parametrize("prog", ["rangemcl", "simbed"])
def test_help_and_version(prog):
    from importlib import import_module

    version = import_module(prog).__version__
    out = run(prog, "--version")
    assert out.returncode == 0 and out.stdout.strip() == version
    out = run(prog, "--help")
    assert out.returncode == 0 and "Usage" in out.stdout


def test_sensors_table_lists_every_preset():
    out = run("rangemcl", "sensors")
    assert out.returncode == 0, out.stderr
    for name in preset_names():
        assert name in out.stdout


def test_sensors_one_prints_a_loadable_spec():
    out = run("rangemcl", "sensors", "vlp-16")
    assert out.returncode == 0, out.stderr
    spec = spec_from_dict(yaml.safe_load(out.stdout))
    ref = load_spec("vlp-16")
    assert spec.beams == 16 and np.array_equal(spec.elevation_deg, ref.elevation_deg)


def test_unknown_sensor_is_one_line_and_exit_2():
    out = run("rangemcl", "sensors", "velodyne-999")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "velodyne-999" in lines[0] and "Traceback" not in out.stderr


def test_malformed_sensor_file_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nelevation_deg: [1, 2\n")
    out = run("rangemcl", "sweep", "--sensor", str(bad), "--out", str(tmp_path / "o"))
    assert out.returncode == 2
    assert str(bad) in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_sweep_writes_range_image_and_scan(tmp_path):
    out = run("rangemcl", "sweep", "--sensor", "vlp-16", "--out", str(tmp_path), "--seed", "3")
    assert out.returncode == 0, out.stderr
    points, _ = read_scan_bin(tmp_path / "scan_vlp-16.bin")
    spec = load_spec("vlp-16")
    assert 0.3 * 16 * spec.columns < len(points) <= 16 * spec.columns  # a street: most rays return
    r = np.linalg.norm(points, axis=1)
    assert r.min() >= spec.min_range_m - 0.2 and r.max() <= spec.max_range_m + 0.2
    assert (tmp_path / "range_vlp-16.png").stat().st_size > 1000
    assert "M rays/s" in out.stdout


def test_scan_bin_round_trip_and_truncation(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    path = write_scan_bin(tmp_path / "velodyne" / "000000.bin", pts, np.arange(50))
    got, inten = read_scan_bin(path)
    assert np.array_equal(got, pts) and np.array_equal(inten, np.arange(50, dtype=np.float32))
    assert not list(path.parent.glob("*.tmp"))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(InputError, match="truncated"):
        read_scan_bin(path)
    with pytest.raises(InputError, match="no such"):
        read_scan_bin(tmp_path / "missing.bin")
