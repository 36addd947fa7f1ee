"""Fixtures shared by test modules."""

from __future__ import annotations

import os

# MuJoCo picks its offscreen GL backend when it is first imported: headless EGL, as simbed itself sets it,
# whichever test module happens to import mujoco first
os.environ.setdefault("MUJOCO_GL", "egl")

import pytest


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory):
    """rangemcl's cache files (surface voxels of maps) go to a folder of this test session."""
    mp = pytest.MonkeyPatch()
    mp.setenv("RANGEMCL_CACHE_DIR", str(tmp_path_factory.mktemp("rangemcl-cache")))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def small_town_map(tmp_path_factory):
    """A map of the first 60 frames (about 40 m) of town_small's mapping route: ``(root, map_dir)`` with the
    mapping drive in ``root / "map_run"``."""
    from rangemcl.mapping.pipeline import MapSettings, build_map
    from simbed.record import record

    root = tmp_path_factory.mktemp("small_town_map")
    record("town_small", "mapping", "os1-64", root / "map_run", frames=60, seed=3, progress=False)
    s = MapSettings()
    s.poisson.depth = 8
    s.workers = 2
    s.scans.every_nth = 2
    build_map(root / "map_run", root / "map", s)
    return root, root / "map"
