"""`simbed record` stopped by SIGTERM or killed by SIGKILL: what it has written is a readable
sequence of whole frames, every per-frame file the same length, and no process of it is left behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rangemcl.datasets.kitti import load_sequence


def _start(out: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "simbed.cli",
            "record",
            "--scene",
            "town_small",
            "--route",
            "mapping",
            "--frames",
            "400",
            "--actors",
            "3",
            "--seed",
            "2",
            "--out",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for_scans(proc: subprocess.Popen, out: Path, n: int) -> None:
    deadline = time.monotonic() + 240
    while proc.poll() is None and time.monotonic() < deadline:
        if (out / "velodyne").is_dir() and len(list((out / "velodyne").iterdir())) > n:
            return
        time.sleep(0.05)
    raise AssertionError(f"no {n} scans written: {proc.stderr.read() if proc.poll() is not None else ''}")


def _children(pid: int) -> set[int]:
    try:
        return {int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()}
    except OSError:
        return set()


def _check_prefix(out: Path) -> int:
    seq = load_sequence(out)
    n = len(seq)
    assert n > 0
    assert seq.poses is not None and len(seq.poses) == n and np.isfinite(seq.poses).all()
    assert seq.odometry is not None and len(seq.odometry) == n
    assert seq.times is not None and len(seq.times) == n
    for i in (0, n - 1):
        assert len(seq.scan(i)) > 1000
    return n


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
def test_a_stopped_recording_is_a_readable_prefix_and_leaves_no_process(tmp_path, sig):
    out = tmp_path / "rec"
    proc = _start(out)
    _wait_for_scans(proc, out, 12)
    kids = _children(proc.pid)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    if sig == signal.SIGTERM:
        assert proc.returncode == 130
        last = proc.stderr.read().strip().splitlines()[-1]
        assert "complete frames" in last and str(out) in last
    else:
        assert proc.returncode == -signal.SIGKILL
    time.sleep(2.0)
    assert not [p for p in kids if os.path.exists(f"/proc/{p}")]
    n = _check_prefix(out)
    assert n >= 12
    # the folder is refused as the output of a new recording unless --overwrite says so
    r = subprocess.run(
        [sys.executable, "-m", "simbed.cli", "record", "--scene", "town_small", "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "--overwrite" in r.stderr
