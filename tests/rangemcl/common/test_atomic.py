"""Atomic writes: whole or absent, and with the mode a plain ``open()`` would give (``mkstemp``'s
0600 would make copied maps and recordings partly unreadable)."""

from __future__ import annotations

import os
import stat

import pytest

from rangemcl.common.atomic import atomic_write
from rangemcl.errors import InputError


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_files_get_the_umask_mode_like_their_neighbours(tmp_path, mask):
    old = os.umask(mask)
    try:
        atomic_write(tmp_path / "a.json", "{}")
        with open(tmp_path / "b.json", "w") as fh:
            fh.write("{}")
    finally:
        os.umask(old)
    mode_a = stat.S_IMODE((tmp_path / "a.json").stat().st_mode)
    mode_b = stat.S_IMODE((tmp_path / "b.json").stat().st_mode)
    assert mode_a == mode_b == 0o666 & ~mask


def test_whole_or_absent(tmp_path):
    atomic_write(tmp_path / "x.bin", b"old")

    def fail(fh):
        fh.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.bin", fail)
    assert (tmp_path / "x.bin").read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.bin"]  # no temporary left behind
    with pytest.raises(InputError, match="cannot write"):
        atomic_write(tmp_path / "missing" / "y.txt", "y")


def test_npz_bytes_depend_only_on_the_arrays(monkeypatch):
    import io
    import time

    import numpy as np

    from rangemcl.common.atomic import savez_stable

    arrays = {"a": np.arange(10.0), "b": np.array("meta"), "c": np.zeros((3, 2), np.int32)}

    def write(fn, when, **kw):
        monkeypatch.setattr(time, "time", lambda: when)
        buf = io.BytesIO()
        fn(buf, **arrays, **kw)
        return buf.getvalue()

    assert write(savez_stable, 1.0e9) == write(savez_stable, 1.5e9)
    assert write(savez_stable, 1.0e9, compressed=True) == write(savez_stable, 1.5e9, compressed=True)
    back = np.load(io.BytesIO(write(savez_stable, 1.0e9, compressed=True)))
    assert all(np.array_equal(back[k], v) for k, v in arrays.items())
