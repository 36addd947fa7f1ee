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


def _write_map_v1(m, map_dir) -> None:
    """A map folder of format 1, as rangemcl once wrote them (the whole mesh in a binary PLY
    with ground labels as vertex colours, the tiling in tiles.npz): the fixture for "maps written by
    today's builder keep loading". A copy of that writer, kept here since the library writes format 2."""
    from pathlib import Path

    import numpy as np
    import yaml

    from rangemcl.common.atomic import savez_stable
    from rangemcl.maps.meshmap import GROUND_RGB, NON_GROUND_RGB, _plain

    d = Path(map_dir)
    d.mkdir(parents=True, exist_ok=True)
    colours = np.where(m.is_ground[:, None], GROUND_RGB, NON_GROUND_RGB).astype(np.uint8)
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(m.vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(m.faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vrec = np.empty(len(m.vertices), [("p", "<f8", 3), ("c", "u1", 3)])
    vrec["p"], vrec["c"] = m.vertices, colours
    frec = np.empty(len(m.faces), [("n", "u1"), ("i", "<i4", 3)])
    frec["n"], frec["i"] = 3, m.faces
    (d / "mesh.ply").write_bytes(head.encode() + vrec.tobytes() + frec.tobytes())
    with (d / "tiles.npz").open("wb") as fh:
        savez_stable(
            fh,
            tile_size_m=np.float64(m.tile_size_m),
            tile_origin_xy=m.tile_origin_xy,
            tiles=m.tiles,
            face_tile=m.face_tile,
        )
    with (d / "ground.npz").open("wb") as fh:
        savez_stable(
            fh, origin_xy=m.ground.origin_xy, cell_m=np.float64(m.ground.cell_m), heights=m.ground.heights
        )
    files = {"mesh": "mesh.ply", "tiles": "tiles.npz", "ground": "ground.npz"}
    if m.drive_xy is not None:
        with (d / "drive.npz").open("wb") as fh:
            savez_stable(fh, xy=m.drive_xy)
        files["drive"] = "drive.npz"
    doc = {
        "format": "rangemcl-mesh-map",
        "format_version": 1,
        "files": files,
        "counts": {
            "vertices": len(m.vertices),
            "triangles": len(m.faces),
            "ground_vertices": int(m.is_ground.sum()),
            "tiles": len(m.tiles),
        },
        "tile_size_m": float(m.tile_size_m),
        "ground_cell_m": float(m.ground.cell_m),
        "extent_m": [float(x) for x in m.extent],
        "meta": _plain(m.meta),
    }
    (d / "map.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.fixture
def save_v1():
    """``save_v1(mesh_map, folder)``: write a map folder of format 1 (see :func:`_write_map_v1`)."""
    return _write_map_v1


# The test files that take minutes (end to end runs, kill-and-resume, suites), handed out first: the tests
# run on both cores a file per worker (pytest-xdist, --dist loadfile, in pyproject.toml), and a long file
# started last would leave the other core idle at the end
_LONG_FILES = (
    "tests/simbed/trials/test_generalization.py",
    "tests/test_mapping_end_to_end.py",
    "tests/test_localization_end_to_end.py",
    "tests/rangemcl/localization/test_hypotheses.py",
    "tests/simbed/trials/test_suites.py",
    "tests/rangemcl/datasets/test_lidar_odometry.py",
)


def pytest_collection_modifyitems(config, items):
    root = config.rootpath

    def rank(item):
        try:
            rel = item.path.relative_to(root).as_posix()
        except ValueError:
            return len(_LONG_FILES)
        return _LONG_FILES.index(rel) if rel in _LONG_FILES else len(_LONG_FILES)

    items.sort(key=rank)  # stable: the order within a file and among the other files is kept
