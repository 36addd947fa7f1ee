"""Bad input across the CLIs: a table of cases, each one line on stderr naming the problem, exit
status 2, and nothing created or changed.

Every case runs in a copy of one small folder of good inputs (``BASE``: a three-frame sequence in the
KITTI layout written by hand, a map from ``rangemcl import-mesh`` of a ground plane with a box, a
localization results folder, a sensor spec, an MJCF scene, a waypoint file), changed by the case's own
``files`` (the bad input: a path relative to the folder and its new text, bytes, ``None`` to delete it,
``DIR`` for an empty folder, or a function of the path). ``test_the_good_inputs_are_good`` checks that the
base inputs themselves are accepted, so each case fails because of its own input.

The commands run in this process (``main()`` of ``simbed.cli`` or ``rangemcl.cli`` with ``sys.argv`` set,
stderr, warnings and log records captured; the exit status from ``SystemExit``): a case costs what its
command does before it refuses, not a Python start-up. ``test_in_process_equals_a_process`` checks on a
few cases that a real process prints the same line with the same status.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import logging
import shutil
import signal
import subprocess
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

# --- the good inputs -----------------------------------------------------------------------------------

N_FRAMES = 3
ROWS, COLUMNS = 12, 2048  # the scans: a LiDAR's rays that hit the ground, 1.73 m below it
N_POINTS = ROWS * COLUMNS


def pose_line(x: float, y: float = 0.0, z: float = 1.73) -> str:
    return f"1 0 0 {x:g} 0 1 0 {y:g} 0 0 1 {z:g}\n"


POSES = "".join(pose_line(k) for k in range(N_FRAMES))
IDENTITY_12 = "1 0 0 0 0 1 0 0 0 0 1 0"
SENSOR_YAML = Path(__file__).resolve().parents[1] / "rangemcl" / "presets" / "os1-64.yaml"
RESULTS_SUMMARY = (
    '{"first_frame": 0, "frames": 3, "converged_frame": 0, "convergence_frames": [0], '
    '"recovery_frames": [], "calib_Tr": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}\n'
)
FRAMES_CSV = "frame,x,y,yaw,converged,recovered\n" + "".join(f"{k},{k},0,0,1,0\n" for k in range(3))
OWN_SCENE = (
    "<mujoco>\n<worldbody>\n"
    '<geom name="floor" type="plane" size="60 60 0.1"/>\n'
    '<geom name="block" type="box" size="2 2 2" pos="15 0 2"/>\n'
    "</worldbody>\n</mujoco>\n"
)


def ground_scan() -> np.ndarray:
    """``(N, 4)`` float32 x, y, z, intensity: rays from -24.5 to -8 degrees all round, on flat ground."""
    elevation, azimuth = np.meshgrid(
        np.radians(np.linspace(-24.5, -8.0, ROWS)),
        np.linspace(-np.pi, np.pi, COLUMNS, endpoint=False),
        indexing="ij",
    )
    r = 1.73 / np.sin(-elevation)
    xyz = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )
    return np.column_stack([(r * xyz).reshape(3, -1).T, np.ones(N_POINTS)]).astype(np.float32)


def _write_base(d: Path) -> None:
    """The good inputs (see the module docstring)."""
    import trimesh

    seq = d / "seq"
    (seq / "velodyne").mkdir(parents=True)
    for k in range(N_FRAMES):
        (seq / "velodyne" / f"{k:06d}.bin").write_bytes(ground_scan().tobytes())
    (seq / "poses.txt").write_text(POSES)
    (seq / "odometry.txt").write_text(POSES)
    (seq / "times.txt").write_text("".join(f"{0.1 * k:.9f}\n" for k in range(N_FRAMES)))
    (seq / "calib.txt").write_text(f"Tr: {IDENTITY_12}\n")
    (seq / "meta.yaml").write_text("scene: hand-written\ncomplete: true\n")

    ground = trimesh.creation.box(extents=(80.0, 80.0, 1.0))
    ground.apply_translation((0.0, 0.0, -0.5))
    block = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
    block.apply_translation((15.0, 0.0, 2.0))
    trimesh.util.concatenate([ground, block]).export(d / "ground.ply")
    code, err = run_cli("rangemcl", ["import-mesh", str(d / "ground.ply"), "--out", str(d / "map")])
    assert code in (0, None), err

    res = d / "results"
    res.mkdir()
    (res / "summary.json").write_text(RESULTS_SUMMARY)
    (res / "estimate_kitti.txt").write_text(POSES)
    (res / "frames.csv").write_text(FRAMES_CSV)
    (res / "config.yaml").write_text("{}\n")

    (d / "sensor.yaml").write_text(SENSOR_YAML.read_text())
    (d / "scene.xml").write_text(OWN_SCENE)
    (d / "route.txt").write_text("-20 -10\n20 -10\n")  # beside the block
    (d / "a_file").write_text("not a folder\n")


# --- how the bad inputs are made -----------------------------------------------------------------------

DIR = object()  # an empty folder


def cut(n_bytes: int):
    """The file without its last ``n_bytes`` bytes."""

    def apply(p: Path) -> None:
        p.write_bytes(p.read_bytes()[:-n_bytes])

    return apply


def flip(at: int):
    """The file with its byte ``at`` inverted (same size: a damaged, not a truncated, file)."""

    def apply(p: Path) -> None:
        b = bytearray(p.read_bytes())
        b[at] ^= 0xFF
        p.write_bytes(bytes(b))

    return apply


def flip_attributes(p: Path) -> None:
    """A zip file (an ``.npz``) with a byte of its first member's attributes in the central directory
    inverted: every array still reads (zip's CRC covers the data only), the file is not the one written."""
    b = bytearray(p.read_bytes())
    b[b.index(b"PK\x01\x02") + 38] ^= 0xFF  # external file attributes
    p.write_bytes(bytes(b))


def halve(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def append(text: str):
    def apply(p: Path) -> None:
        p.write_text(p.read_text() + text)

    return apply


def replace(old: str, new: str):
    def apply(p: Path) -> None:
        text = p.read_text()
        assert old in text, (p, old)
        p.write_text(text.replace(old, new, 1))

    return apply


def _apply(d: Path, files: dict) -> None:
    for rel, what in files.items():
        p = d / rel
        if what is None:
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink()
        elif what is DIR:
            if p.is_dir():
                shutil.rmtree(p)
            p.mkdir(parents=True)
        elif callable(what):
            what(p)
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(what, bytes):
                p.write_bytes(what)
            else:
                p.write_text(what)


# --- the cases -----------------------------------------------------------------------------------------

# Each case: (program and arguments, {d} is the case's folder; words the one stderr line must hold;
# the bad input, as files changed in the folder). Every case exits with status 2 and changes nothing.
LOC = "rangemcl localize {d}/seq --map {d}/map --out {d}/o"
BUILD = "rangemcl build-map {d}/seq --out {d}/o"
EVAL = "rangemcl evaluate {d}/results --gt {d}/seq/poses.txt"
QUALITY = "rangemcl map-quality {d}/map --truth {d}/ground.ply"
RECORD = "simbed record --scene town_small --route test --out {d}/o --frames 5"
TRIALS = "simbed trials runtime --out {d}/t --map {d}/map --quick"
CFG = "{d}/c.yaml"

PRIOR_DAMAGED = ["place_prior.npz", "damaged", "rangemcl place-prior {d}/map"]
ELEVEN = pose_line(0) + pose_line(1).rsplit(" ", 1)[0] + "\n" + pose_line(2)
NAN_POSE = pose_line(0) + pose_line(1).replace("1.73", "nan") + pose_line(2)

CASES: list[tuple[str, list[str], dict]] = [
    # --- command lines that do not parse
    ("rangemcl locate {d}/seq", ["No such command", "locate", "'rangemcl --help'"], {}),
    ("simbed recrod --out {d}/o", ["No such command", "recrod", "'simbed --help'"], {}),
    (LOC + " --frames abc", ["--frames", "integer", "'rangemcl localize --help'"], {}),
    ("rangemcl build-map {d}/seq", ["Missing option", "--out", "'rangemcl build-map --help'"], {}),
    ("rangemcl import-mesh --out {d}/o", ["Missing argument", "'rangemcl import-mesh --help'"], {}),
    ("rangemcl map-info {d}/map --bogus", ["No such option", "--bogus"], {}),
    ("simbed record --out {d}/o --actors many", ["--actors", "integer", "'simbed record --help'"], {}),
    ("simbed make-town --out {d}/t.xml --size big", ["--size", "'simbed make-town --help'"], {}),
    ("simbed trials runtime --out {d}/t", ["--map: suite 'runtime' needs the scene's map folder"], {}),
    # --- rangemcl sensors
    ("rangemcl sensors os1-65", ["unknown LiDAR preset", "os1-65"], {}),
    ("rangemcl sensors {d}/s.yaml", ["s.yaml", "malformed YAML", "line 2"], {"s.yaml": "name: x\n  a: [\n"}),
    ("rangemcl sensors {d}/sensor.yaml", ["unknown key", "colour"], {"sensor.yaml": append("colour: red\n")}),
    ("rangemcl sensors {d}/s.yaml", ["s.yaml", "mapping"], {"s.yaml": "- 1\n- 2\n"}),
    (
        "rangemcl sensors {d}/sensor.yaml",
        ["columns must be >= 1", "0"],
        {"sensor.yaml": replace("columns: 1024", "columns: 0")},
    ),
    (
        "rangemcl sensors {d}/sensor.yaml",
        ["columns must be an integer"],
        {"sensor.yaml": replace("columns: 1024", "columns: many")},
    ),
    (
        "rangemcl sensors {d}/sensor.yaml",
        ["dropout_prob", "[0, 1)"],
        {"sensor.yaml": replace("dropout_prob: 0.0", "dropout_prob: 1.5")},
    ),
    (
        "rangemcl sensors {d}/sensor.yaml",
        ["max_range_m", "min_range_m"],
        {"sensor.yaml": replace("max_range_m: 120.0", "max_range_m: 0.1")},
    ),
    (
        "rangemcl sensors {d}/sensor.yaml",
        ["rotation_hz must be > 0"],
        {"sensor.yaml": replace("rotation_hz: 10.0", "rotation_hz: -10")},
    ),
    ("rangemcl sensors {d}/missing.yaml", ["missing.yaml"], {}),
    # --- rangemcl sweep
    ("rangemcl sweep --sensor nonsense --out {d}/o", ["unknown LiDAR preset", "nonsense"], {}),
    ("rangemcl sweep --sensor {d}/s.yaml --out {d}/o", ["s.yaml", "malformed YAML"], {"s.yaml": "a: [\n"}),
    ("rangemcl sweep --out {d}/o --threads -1", ["--threads", "-1"], {}),
    ("rangemcl sweep --out {d}/o --device nonsense", ["device", "nonsense"], {}),
    ("rangemcl sweep --out {d}/o --seed -1", ["--seed", "-1"], {}),
    ("rangemcl sweep --out {d}/a_file", ["a_file", "not a folder"], {}),
    (
        "rangemcl sweep --out {d}/o",
        ["range_os1-64.png", "exists", "--overwrite"],
        {"o/range_os1-64.png": b"x"},
    ),
    (
        "rangemcl sweep --sensor vlp-16 --out {d}/o",
        ["scan_vlp-16.bin", "exists", "--overwrite"],
        {"o/scan_vlp-16.bin": b"x"},
    ),
    # --- rangemcl build-map: the sequence
    ("rangemcl build-map {d}/nope --out {d}/o", ["nope", "no such sequence folder"], {}),
    ("rangemcl build-map {d}/a_file --out {d}/o", ["a_file", "not a folder"], {}),
    (BUILD, ["seq", "no velodyne/ folder"], {"seq/velodyne": None}),
    (BUILD, ["velodyne", "no .bin scans"], {"seq/velodyne": DIR}),
    (BUILD, ["000001.bin", "missing"], {"seq/velodyne/000001.bin": None}),
    (BUILD, ["000001.bin", "truncated", "16-byte"], {"seq/velodyne/000001.bin": cut(6)}),
    (BUILD, ["poses.txt", "required"], {"seq/poses.txt": None}),
    (BUILD, ["poses.txt", "0 lines for 3 scans"], {"seq/poses.txt": ""}),
    (BUILD, ["poses.txt", "line 2", "11 numbers"], {"seq/poses.txt": ELEVEN}),
    (BUILD, ["poses.txt", "line 2", "NaN"], {"seq/poses.txt": NAN_POSE}),
    (
        BUILD,
        ["poses.txt", "line 1", "'one'", "not a number"],
        {"seq/poses.txt": POSES.replace("1", "one", 1)},
    ),
    (
        BUILD,
        ["poses.txt", "line 1", "orthonormal"],
        {"seq/poses.txt": POSES.replace("1 0 0", "2 0 0", 1)},
    ),
    (BUILD, ["times.txt", "2 lines for 3 scans"], {"seq/times.txt": "0.0\n0.1\n"}),
    (BUILD, ["times.txt", "line 3", "before the previous"], {"seq/times.txt": "0.0\n0.2\n0.1\n"}),
    (BUILD, ["odometry.txt", "line 2", "NaN"], {"seq/odometry.txt": NAN_POSE}),
    (BUILD, ["calib.txt", "11 numbers"], {"seq/calib.txt": "Tr: 1 0 0 0 0 1 0 0 0 0 1\n"}),
    (BUILD, ["calib.txt", "no 'Tr:' line"], {"seq/calib.txt": f"P0: {IDENTITY_12}\n"}),
    (BUILD, ["meta.yaml", "malformed YAML"], {"seq/meta.yaml": "scene: [\n"}),
    (BUILD, ["meta.yaml", "mapping"], {"seq/meta.yaml": "- complete\n"}),
    # --- rangemcl build-map: the config and options
    (BUILD + " --config {d}/nope.yaml", ["nope.yaml", "no such config file"], {}),
    (BUILD + " --config {d}/seq", ["seq", "cannot read config file"], {}),
    (
        BUILD + " --config " + CFG,
        ["c.yaml", "malformed YAML", "line 2"],
        {"c.yaml": "tiles:\n  size_m: 5: 6\n"},
    ),
    (BUILD + " --config " + CFG, ["c.yaml", "tiles.sise_m", "size_m"], {"c.yaml": "tiles:\n  sise_m: 5\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "tiles.size_m", "number"], {"c.yaml": "tiles:\n  size_m: big\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "tiles", "mapping"], {"c.yaml": "tiles: [1, 2]\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "top level", "mapping"], {"c.yaml": "- tiles\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "tiles.size_m"], {"c.yaml": "tiles:\n  size_m: -5\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "tiles.size_m"], {"c.yaml": "tiles:\n  size_m: 0\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "poisson.depth"], {"c.yaml": "poisson:\n  depth: -1\n"}),
    (BUILD + " --config " + CFG, ["poisson.depth", "16"], {"c.yaml": "poisson:\n  depth: 17\n"}),
    (BUILD + " --config " + CFG, ["density_quantile"], {"c.yaml": "poisson:\n  density_quantile: 1.5\n"}),
    (BUILD + " --config " + CFG, ["scans.every_nth"], {"c.yaml": "scans:\n  every_nth: 0\n"}),
    (BUILD + " --config " + CFG, ["scans.max_range_m"], {"c.yaml": "scans:\n  max_range_m: -40\n"}),
    (BUILD + " --config " + CFG, ["scans.min_range_m"], {"c.yaml": "scans:\n  min_range_m: 50\n"}),
    (
        BUILD + " --config " + CFG,
        ["ground.max_angle_deg", "90"],
        {"c.yaml": "ground:\n  max_angle_deg: 95\n"},
    ),
    (BUILD + " --config " + CFG, ["ground.z_margin_m"], {"c.yaml": "ground:\n  z_margin_m: .nan\n"}),
    (BUILD + " --config " + CFG, ["projection.width"], {"c.yaml": "projection:\n  width: 0\n"}),
    (
        BUILD + " --config " + CFG,
        ["projection.fov_down_deg"],
        {"c.yaml": "projection:\n  fov_down_deg: 10\n"},
    ),
    (BUILD + " --config " + CFG, ["simplify.voxel_m"], {"c.yaml": "simplify:\n  voxel_m: 0\n"}),
    (
        BUILD + " --config " + CFG,
        ["simplify.smooth_iterations"],
        {"c.yaml": "simplify:\n  smooth_iterations: -1\n"},
    ),
    (BUILD + " --config " + CFG, ["tiles.margin_m"], {"c.yaml": "tiles:\n  margin_m: -1\n"}),
    (BUILD + " --config " + CFG, ["c.yaml", "workers"], {"c.yaml": "workers: -2\n"}),
    (
        BUILD + " --config " + CFG,
        ["projection.height x projection.width"],
        {"c.yaml": "projection:\n  height: 100000000\n"},
    ),
    (BUILD + " --workers -3", ["workers"], {}),
    (
        BUILD,
        ["seq", "no scan has a valid point"],
        {f"seq/velodyne/{k:06d}.bin": b"" for k in range(N_FRAMES)},
    ),
    ("rangemcl build-map {d}/seq --out {d}/a_file", ["a_file", "not a folder"], {}),
    (BUILD, ["o", "holds no map", "choose another --out"], {"o/notes.txt": "mine\n"}),
    ("rangemcl build-map {d}/seq --out {d}/map", ["map", "--overwrite"], {}),
    (BUILD + " --resume", ["nothing to resume"], {}),
    ("rangemcl build-map {d}/seq --out {d}/map --resume --overwrite", ["--resume", "--overwrite"], {}),
    ("rangemcl build-map {d}/seq --out {d}/o --backend dask", ["--backend", "dask", "process, ray"], {}),
    ("rangemcl build-map {d}/seq --out {d}/o --address auto", ["--address", "--backend ray"], {}),
    (BUILD + " --resume", ["state.json", "unreadable", "--overwrite"], {"o/.build/state.json": "{broken"}),
    (BUILD + " --resume", ["state.json", "not a build state"], {"o/.build/state.json": "[1]"}),
    (BUILD + " --resume", ["another sequence or other settings"], {"o/.build/state.json": '{"version": 0}'}),
    (BUILD, ["interrupted build", "--resume"], {"o/.build/state.json": "{}"}),
    # --- rangemcl convert
    ("rangemcl convert {d}/nope --out {d}/o.bag --format rosbag1", ["nope", "no such sequence folder"], {}),
    ("rangemcl convert {d}/seq --out {d}/o --format bag", ["--format 'bag'", "kitti, mcap"], {}),
    (
        "rangemcl convert {d}/seq --out {d}/o --format rosbag1",
        ["o", "a ROS 1 bag is a file ending in .bag"],
        {},
    ),
    ("rangemcl convert {d}/seq --out {d}/o.bag --format mcap", ["o.bag", "is a folder"], {}),
    ("rangemcl convert {d}/seq --out {d}/seq --format kitti", ["seq", "--overwrite"], {}),
    ("rangemcl convert {d}/seq --out {d}/o --lidar-topic /points", ["seq", "topic options are for bags"], {}),
    ("rangemcl convert {d}/x.bag --out {d}/o", ["x.bag", "cannot read the bag"], {"x.bag": "not a bag\n"}),
    # --- bags and odometry sources for localize and build-map
    (LOC + " --odometry wheel", ["--odometry 'wheel'", "kiss-icp or poses:FILE"], {}),
    (LOC + " --odometry poses:{d}/nope.txt", ["nope.txt", "cannot read poses"], {}),
    (LOC + " --sensor-to-base 1,2,3", ["--sensor-to-base", "x,y,z,roll,pitch,yaw"], {}),
    (LOC + " --scan-stamp middle", ["--scan-stamp 'middle'", "start or end"], {}),
    (LOC + " --poses {d}/nope.txt", ["nope.txt", "no such poses file"], {}),
    (
        "rangemcl localize {d}/x.mcap --map {d}/map --out {d}/o",
        ["x.mcap", "cannot read the bag"],
        {"x.mcap": "junk"},
    ),
    ("rangemcl build-map {d}/x.bag --out {d}/o", ["x.bag", "cannot read the bag"], {"x.bag": "junk"}),
    # --- rangemcl import-mesh
    ("rangemcl import-mesh {d}/nope.ply --out {d}/o", ["nope.ply", "does not exist"], {}),
    ("rangemcl import-mesh {d}/seq --out {d}/o", ["seq", "not a file"], {}),
    ("rangemcl import-mesh {d}/m.ply --out {d}/o", ["m.ply"], {"m.ply": "hello, not a mesh\n"}),
    (
        "rangemcl import-mesh {d}/m.obj --out {d}/o",
        ["m.obj", "no triangles"],
        {"m.obj": "hello, not a mesh\n"},
    ),
    ("rangemcl import-mesh {d}/m.ply --out {d}/o", ["m.ply"], {"m.ply": b""}),
    ("rangemcl import-mesh {d}/m.obj --out {d}/o", ["m.obj", "no triangles"], {"m.obj": b""}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/o", ["ground.ply"], {"ground.ply": halve}),
    (
        "rangemcl import-mesh {d}/m.obj --out {d}/o",
        ["m.obj", "NaN"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n"},
    ),
    (
        "rangemcl import-mesh {d}/m.obj --out {d}/o",
        ["m.obj", "no triangles"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\n"},
    ),
    (
        "rangemcl import-mesh {d}/m.obj --out {d}/o",
        ["m.obj", "degenerate"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"},
    ),
    (
        "rangemcl import-mesh {d}/m.obj --out {d}/o",
        ["m.obj", "cannot read as a triangle mesh", "out of bounds"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n"},
    ),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/o --drive {d}/nope.txt", ["nope.txt", "cannot read"], {}),
    (
        "rangemcl import-mesh {d}/ground.ply --out {d}/o --drive {d}/w.txt",
        ["w.txt:2", "4 numbers"],
        {"w.txt": "1 2\n1 2 3 4\n"},
    ),
    (
        "rangemcl import-mesh {d}/ground.ply --out {d}/o --drive {d}/w.txt",
        ["w.txt", "two points"],
        {"w.txt": "1 2\n"},
    ),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/o --tile-size 0", ["tile_size_m", "0"], {}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/o --tile-size -5", ["tile_size_m", "-5"], {}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/o --tile-size nan", ["tile_size_m", "nan"], {}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/a_file", ["a_file", "not a folder"], {}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/seq", ["seq", "holds no map"], {}),
    ("rangemcl import-mesh {d}/ground.ply --out {d}/map", ["map", "--overwrite"], {}),
    # --- rangemcl place-prior: bad map folders, settings, budget
    ("rangemcl place-prior {d}/nope", ["nope", "does not exist"], {}),
    ("rangemcl place-prior {d}/map", ["tiles/0_0.npz", "truncated"], {"map/tiles/0_0.npz": cut(10)}),
    (
        "rangemcl place-prior {d}/map --config " + CFG,
        ["c.yaml", "init.prior_cel_m"],
        {"c.yaml": "init:\n  prior_cel_m: 1\n"},
    ),
    ("rangemcl place-prior {d}/map --map-memory -5", ["--map-memory", "-5"], {}),
    # --- rangemcl map-info: bad map folders
    ("rangemcl map-info {d}/nope", ["nope", "does not exist"], {}),
    ("rangemcl map-info {d}/a_file", ["a_file", "not a folder"], {}),
    ("rangemcl map-info {d}/map", ["map.yaml", "missing"], {"map/map.yaml": None}),
    ("rangemcl map-info {d}/map", ["tiles/0_0.npz", "missing"], {"map/tiles/0_0.npz": None}),
    ("rangemcl map-info {d}/map", ["tiles/0_0.npz", "truncated"], {"map/tiles/0_0.npz": cut(10)}),
    ("rangemcl map-info {d}/map", ["tiles/0_0.npz", "checksum"], {"map/tiles/0_0.npz": flip(60)}),
    ("rangemcl map-info {d}/map", ["tiles.json", "missing"], {"map/tiles.json": None}),
    ("rangemcl map-coarse {d}/nope", ["nope", "does not exist"], {}),
    ("rangemcl map-coarse {d}/map --ratio 0", ["--ratio", "(0, 1]"], {}),
    ("rangemcl map-coarse {d}/map", ["tiles/0_0.npz", "truncated"], {"map/tiles/0_0.npz": cut(10)}),
    ("rangemcl map-coarse {d}/map", ["tiles.json", "missing"], {"map/tiles.json": None}),
    ("rangemcl map-upgrade {d}/nope", ["nope", "does not exist"], {}),
    ("rangemcl map-upgrade {d}/a_file", ["a_file", "not a folder"], {}),
    ("rangemcl map-upgrade {d}/map", ["map.yaml", "missing"], {"map/map.yaml": None}),
    ("rangemcl map-upgrade {d}/map", ["tiles/0_0.npz", "truncated"], {"map/tiles/0_0.npz": cut(10)}),
    ("rangemcl map-info {d}/map", ["tiles.json", "cannot read"], {"map/tiles.json": "{broken"}),
    # a damaged place prior (cut, a corrupt zip, arrays that are not the stored ones), ground grid (a byte
    # outside the arrays, which zip's CRC does not cover): the file and the way out
    ("rangemcl map-info {d}/map", PRIOR_DAMAGED, {"map/place_prior.npz": halve}),
    ("rangemcl map-info {d}/map", PRIOR_DAMAGED, {"map/place_prior.npz": flip(200)}),
    ("rangemcl map-info {d}/map", ["ground.npz", "its checksum"], {"map/ground.npz": flip_attributes}),
    ("rangemcl map-info {d}/map", ["ground.npz", "cannot read"], {"map/ground.npz": halve}),
    ("rangemcl map-info {d}/map", ["map.yaml", "malformed YAML"], {"map/map.yaml": append("counts: [\n")}),
    ("rangemcl map-info {d}/map", ["map.yaml", "mapping"], {"map/map.yaml": "- 1\n"}),
    (
        "rangemcl map-info {d}/map",
        ["tiles.json", "24 triangles", "25"],
        {"map/map.yaml": replace("triangles: 24", "triangles: 25")},
    ),
    ("rangemcl map-info {d}/map", ["drive.npz", "not an .npz file"], {"map/drive.npz": b"\x93NUMPY junk"}),
    (
        BUILD,
        ["points_meta/000001.npz", "not an .npz file"],
        {"seq/points_meta/000001.npz": b"\x80\x04junk"},  # a pickle
    ),
    (
        "rangemcl map-info {d}/map",
        ["map.yaml", "format_version"],
        {"map/map.yaml": replace("format_version: 2", "format_version: 99")},
    ),
    # --- rangemcl map-quality
    ("rangemcl map-quality {d}/nope --truth {d}/ground.ply", ["nope", "does not exist"], {}),
    (QUALITY, ["tiles.json", "cannot read"], {"map/tiles.json": b"garbage"}),
    (QUALITY, ["tiles/1_1.npz", "truncated"], {"map/tiles/1_1.npz": halve}),
    ("rangemcl map-quality {d}/map --truth {d}/nope.ply", ["nope.ply", "does not exist"], {}),
    ("rangemcl map-quality {d}/map --truth {d}/m.obj", ["m.obj", "no triangles"], {"m.obj": "not a mesh\n"}),
    (QUALITY + " --tolerance 0", ["--tolerance", "0"], {}),
    (QUALITY + " --tolerance -1", ["--tolerance", "-1"], {}),
    (QUALITY + " --reference {d}/nope", ["nope", "no such sequence folder"], {}),
    (QUALITY + " --reference {d}/seq", ["poses.txt", "required"], {"seq/poses.txt": None}),
    (QUALITY + " --reference {d}/seq", ["000000.bin", "truncated"], {"seq/velodyne/000000.bin": cut(3)}),
    (QUALITY + " --json {d}/nodir/q.json", ["--json", "nodir"], {}),
    (QUALITY + " --json {d}/seq", ["--json", "seq"], {}),
    # --- rangemcl localize: options
    (LOC + " --frames -5", ["frames", "-5"], {}),
    (LOC + " --frames 0", ["frames", "0"], {}),
    (LOC + " --first-frame -1", ["first frame", "-1"], {}),
    (LOC + " --first-frame 3", ["first frame 3", "out of range"], {}),
    (LOC + " --threads 0", ["threads"], {}),
    (LOC + " --particles 0", ["particles"], {}),
    (LOC + " --particles -100", ["particles", "-100"], {}),
    (LOC + " --seed -1", ["--seed", "-1"], {}),
    (LOC + " --device nonsense", ["device", "nonsense"], {}),
    (LOC + " --mode sideways", ["sideways"], {}),
    (LOC + " --init-pose 1,2,0", ["tracking"], {}),
    (LOC + " --mode tracking --init-pose 1,2", ["--init-pose", "three numbers"], {}),
    (LOC + " --mode tracking --init-pose a,b,c", ["--init-pose", "three numbers"], {}),
    (LOC + " --mode tracking --init-pose 1,2,nan", ["--init-pose", "finite"], {}),
    (LOC + " --mode tracking --init-pose 5000,0,0", ["5000", "map"], {}),
    # --- rangemcl localize: the sequence
    ("rangemcl localize {d}/nope --map {d}/map --out {d}/o", ["nope", "no such sequence folder"], {}),
    ("rangemcl localize {d}/a_file --map {d}/map --out {d}/o", ["a_file", "not a folder"], {}),
    (LOC, ["poses.txt", "0 lines for 3 scans"], {"seq/poses.txt": ""}),
    (LOC, ["poses.txt", "line 2", "11 numbers"], {"seq/poses.txt": ELEVEN}),
    (LOC, ["poses.txt", "NaN"], {"seq/poses.txt": NAN_POSE}),
    (LOC, ["odometry.txt", "NaN"], {"seq/odometry.txt": NAN_POSE}),
    (LOC, ["odometry.txt", "--odometry-from-poses"], {"seq/odometry.txt": None}),
    (LOC, ["times.txt", "2 lines for 3 scans"], {"seq/times.txt": "0.0\n0.1\n"}),
    (LOC, ["outside the map", "frame"], {"seq/poses.txt": POSES.replace(" 0 1 0 0 ", " 0 1 0 5000 ")}),
    # --- rangemcl localize: the map
    ("rangemcl localize {d}/seq --map {d}/nope --out {d}/o", ["nope", "does not exist"], {}),
    ("rangemcl localize {d}/seq --map {d}/a_file --out {d}/o", ["a_file", "not a folder"], {}),
    (LOC, ["map.yaml", "missing"], {"map/map.yaml": None}),
    (LOC, ["tiles/0_1.npz", "truncated"], {"map/tiles/0_1.npz": halve}),
    (LOC, ["tiles.json", "not a tile index"], {"map/tiles.json": "[]"}),
    (LOC, PRIOR_DAMAGED, {"map/place_prior.npz": halve}),
    (LOC, PRIOR_DAMAGED, {"map/place_prior.npz": flip(200)}),
    (LOC + " --mode tracking", ["ground.npz", "checksum"], {"map/ground.npz": flip_attributes}),
    # --- rangemcl localize: the config
    (LOC + " --config " + CFG, ["c.yaml", "malformed YAML"], {"c.yaml": "refine: {gate_m: \n"}),
    (LOC + " --config " + CFG, ["c.yaml", "refine.gate_mm", "gate_m"], {"c.yaml": "refine:\n  gate_mm: 1\n"}),
    (
        LOC + " --config " + CFG,
        ["c.yaml", "observation.rays", "integer"],
        {"c.yaml": "observation:\n  rays: 1.5\n"},
    ),
    (LOC + " --config " + CFG, ["c.yaml", "observation", "mapping"], {"c.yaml": "observation: [range]\n"}),
    (
        LOC + " --config {d}/bad_gate.yaml",
        ["bad_gate.yaml", "refine.gate_m"],
        {"bad_gate.yaml": "refine:\n  gate_m: -1\n"},
    ),
    (LOC + " --config " + CFG, ["calibration_window_m"], {"c.yaml": "motion:\n  calibration_window_m: 0\n"}),
    (
        LOC + " --config " + CFG,
        ["calibration_settle_updates"],
        {"c.yaml": "motion:\n  calibration_settle_updates: -2\n"},
    ),
    (LOC + " --config " + CFG, ["observation.rays"], {"c.yaml": "observation:\n  rays: 0\n"}),
    (LOC + " --config " + CFG, ["particles.global_count"], {"c.yaml": "particles:\n  global_count: -10\n"}),
    (LOC + " --config " + CFG, ["init.prior_share", "[0, 1]"], {"c.yaml": "init:\n  prior_share: 1.5\n"}),
    (
        LOC + " --config " + CFG,
        ["convergence.min_inliers"],
        {"c.yaml": "convergence:\n  min_inliers: -0.5\n"},
    ),
    (LOC + " --config " + CFG, ["resample_neff_ratio"], {"c.yaml": "particles:\n  resample_neff_ratio: 0\n"}),
    (
        LOC + " --config " + CFG,
        ["convergence.method", "fancy"],
        {"c.yaml": "convergence:\n  method: fancy\n"},
    ),
    (
        LOC + " --config " + CFG,
        ["observation.model", "nonsense"],
        {"c.yaml": "observation:\n  model: nonsense\n"},
    ),
    (LOC + " --config " + CFG, ["sensor_height_m"], {"c.yaml": "sensor_height_m: 0\n"}),
    (
        LOC + " --config " + CFG,
        ["observation.ground_share", "[0, 1]"],
        {"c.yaml": "observation:\n  ground_share: 2\n"},
    ),
    (
        LOC + " --config " + CFG,
        ["observation.tall_share", "[0, 1]"],
        {"c.yaml": "observation:\n  tall_share: -0.5\n"},
    ),
    (
        LOC + " --config " + CFG,
        ["observation.ray_sampling", "diagonal"],
        {"c.yaml": "observation:\n  ray_sampling: diagonal\n"},
    ),
    (LOC + " --config " + CFG, ["observation.min_range_m"], {"c.yaml": "observation:\n  min_range_m: 50\n"}),
    (
        LOC + " --config " + CFG,
        ["c.yaml", "duplicate key 'refine'"],
        {"c.yaml": "refine:\n  gate_m: 1\nrefine:\n  gate_m: 2\n"},
    ),
    (LOC + " --config " + CFG, ["c.yaml", "not UTF-8"], {"c.yaml": b"\xff\xfe binary"}),
    # --- rangemcl settings: the config it prints
    ("rangemcl settings --config {d}/nope.yaml", ["nope.yaml", "no such config file"], {}),
    ("rangemcl settings --config " + CFG, ["c.yaml", "malformed YAML"], {"c.yaml": "refine: {gate_m: \n"}),
    (
        "rangemcl settings --config " + CFG,
        ["c.yaml", "refine.gate_mm", "gate_m"],
        {"c.yaml": "refine:\n  gate_mm: 1\n"},
    ),
    (
        "rangemcl settings --config " + CFG,
        ["c.yaml", "observation.rays"],
        {"c.yaml": "observation:\n  rays: 0\n"},
    ),
    # --- rangemcl localize: the output folder
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/a_file", ["a_file", "not a folder"], {}),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/seq", ["seq", "holds no localization results"], {}),
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/results", ["results", "--overwrite"], {}),
    (LOC + " --resume", ["holds no interrupted localization"], {}),
    (
        "rangemcl localize {d}/seq --map {d}/map --out {d}/results --resume --overwrite",
        ["--resume", "--overwrite"],
        {},
    ),
    (
        "rangemcl localize {d}/seq --map {d}/map --out {d}/results",
        ["interrupted localization", "--resume"],
        {"results/.resume": DIR},
    ),
    # --- rangemcl evaluate
    ("rangemcl evaluate {d}/nope --gt {d}/seq/poses.txt", ["summary.json", "missing"], {}),
    ("rangemcl evaluate {d}/seq --gt {d}/seq/poses.txt", ["summary.json", "missing", "results folder"], {}),
    (EVAL, ["summary.json", "cannot read"], {"results/summary.json": "{not json\n"}),
    (EVAL, ["summary.json", "malformed", "JSON object"], {"results/summary.json": "[1, 2]\n"}),
    (EVAL, ["summary.json", "malformed"], {"results/summary.json": '{"first_frame": "x"}\n'}),
    (EVAL, ["summary.json", "malformed"], {"results/summary.json": '{"converged_frame": "soon"}\n'}),
    (EVAL, ["summary.json", "calib_Tr"], {"results/summary.json": '{"calib_Tr": [[1, 0], [0, 1]]}\n'}),
    # --resume on a folder without a checkpoint: refused before the filter starts (the map folder, where
    # the place prior is cached on first use, stays as it was)
    ("rangemcl localize {d}/seq --map {d}/map --out {d}/results --resume", ["results", "resume"], {}),
    (
        LOC,
        ["meta.yaml", "sensor.mount.xyz_m"],
        {"seq/meta.yaml": "complete: true\nsensor: {mount: {xyz_m: [0, 0, high]}}\n"},
    ),
    (EVAL, ["estimate_kitti.txt", "line 2", "11 numbers"], {"results/estimate_kitti.txt": ELEVEN}),
    (
        EVAL,
        ["frames.csv", "no frame was finished"],
        {"results/summary.json": None, "results/frames.csv": FRAMES_CSV.splitlines()[0] + "\n"},
    ),
    ("rangemcl evaluate {d}/results --gt {d}/nope.txt", ["nope.txt", "no such file"], {}),
    (EVAL, ["poses.txt", "line 2", "11 numbers"], {"seq/poses.txt": ELEVEN}),
    (EVAL, ["poses.txt", "NaN"], {"seq/poses.txt": NAN_POSE}),
    (EVAL, ["poses.txt", "has 2 poses"], {"seq/poses.txt": pose_line(0) + pose_line(1)}),
    (EVAL + " --check-every 0", ["--check-every", "0"], {}),
    (EVAL + " --check-every -5", ["--check-every", "-5"], {}),
    (EVAL + " --success-m 0", ["--success-m", "0"], {}),
    (EVAL + " --success-m nan", ["--success-m", "nan"], {}),
    # --- simbed make-town
    ("simbed make-town --out {d}/t.xml --size 50", ["size_m", "50"], {}),
    ("simbed make-town --out {d}/t.xml --size -400", ["size_m", "-400"], {}),
    ("simbed make-town --out {d}/t.xml --size nan", ["size_m", "nan"], {}),
    ("simbed make-town --out {d}/t.xml --seed -1", ["seed", "-1"], {}),
    ("simbed make-town --out {d}/t.xml --variants -1", ["variants", "-1"], {}),
    ("simbed make-town --out {d}/seq --size 120", ["seq", ".xml"], {}),
    ("simbed make-town --out {d}/t.xml --size 120", ["t.xml", "is a folder"], {"t.xml": DIR}),
    ("simbed make-town --out {d}/a_file/t.xml --size 120", ["a_file", "is a file"], {}),
    (
        "simbed make-town --out {d}/t.xml --size 120",
        ["t.xml", "exists", "--overwrite"],
        {"t.xml": "<mujoco/>\n"},
    ),
    (
        "simbed make-town --out {d}/t.xml --size 120",
        ["t.yaml", "exists", "--overwrite"],
        {"t.yaml": "name: t\n"},
    ),
    # --- simbed record
    ("simbed record --scene town_small --route test --out {d}/o --actors -1", ["actors", "-1"], {}),
    ("simbed record --scene town_small --route test --out {d}/o --frames 0", ["frames"], {}),
    (RECORD.replace("--frames 5", "--frames -5"), ["frames", "-5"], {}),
    (RECORD + " --variant -1", ["variant", "-1"], {}),
    (RECORD + " --variant 7", ["no variant 7"], {}),
    (RECORD + " --seed -1", ["seed", "-1"], {}),
    (RECORD + " --device nonsense", ["device", "nonsense"], {}),
    (RECORD + " --sensor nonsense", ["unknown LiDAR preset", "nonsense"], {}),
    (
        RECORD + " --sensor {d}/sensor.yaml",
        ["sensor.yaml", "columns"],
        {"sensor.yaml": replace("columns: 1024", "columns: -1")},
    ),
    ("simbed record --scene nonsense --out {d}/o", ["nonsense.xml", "no such scene file"], {}),
    (
        "simbed record --scene {d}/bad.xml --out {d}/o",
        ["bad.xml", "malformed MJCF"],
        {"bad.xml": "<mujoco><worldbody>\n"},
    ),
    (
        "simbed record --scene {d}/bad.xml --route {d}/route.txt --out {d}/o",
        ["bad.xml", "does not compile"],
        {
            "bad.xml": '<mujoco><worldbody><geom type="box" size="1 1 1" material="nope"/>'
            "</worldbody></mujoco>"
        },
    ),
    (
        "simbed record --scene {d}/bad.xml --route {d}/route.txt --out {d}/o",
        ["bad.xml", "missing.stl"],
        {
            "bad.xml": '<mujoco><asset><mesh name="m" file="missing.stl"/></asset>'
            '<worldbody><geom type="mesh" mesh="m"/></worldbody></mujoco>'
        },
    ),
    (RECORD.replace("--route test", "--route sideways"), ["unknown route", "sideways"], {}),
    (RECORD.replace("--route test", "--route test-x"), ["test-x", "integer"], {}),
    (RECORD.replace("--route test", "--route test--3"), ["test--3", "N >= 0"], {}),
    (
        RECORD.replace("--route test", "--route {d}/route.txt"),
        ["route.txt:2", "'x y'"],
        {"route.txt": "0 0\n10 north\n"},
    ),
    (
        RECORD.replace("--route test", "--route {d}/route.txt"),
        ["route.txt", "at least 2 waypoints"],
        {"route.txt": "0 0\n"},
    ),
    (RECORD.replace("--route test", "--route {d}/nope.txt"), ["nope.txt", "cannot read waypoints"], {}),
    (RECORD + " --loop", ["--loop", "waypoint"], {}),
    ("simbed record --scene {d}/scene.xml --route mapping --out {d}/o", ["scene.xml", "road network"], {}),
    (
        "simbed record --scene {d}/scene.xml --route {d}/route.txt --out {d}/o",
        ["route.txt:1", "the ground steps", "0.00 m to 4.00 m"],
        {"route.txt": "0 0\n30 0\n"},  # through the block
    ),
    (
        RECORD + " --actor-paths {d}/actors.yaml",
        ["actors.yaml", "kind 'horse'"],
        {"actors.yaml": "actors:\n  - kind: horse\n    waypoints: [[0, 0], [9, 0]]\n"},
    ),
    (
        RECORD + " --actor-paths {d}/actors.yaml",
        ["actors.yaml", "non-empty list 'actors'"],
        {"actors.yaml": "actors: []\n"},
    ),
    ("simbed record --scene town_small --route test --out {d}/a_file", ["a_file", "not a folder"], {}),
    ("simbed record --scene town_small --route test --out {d}/results", ["results", "--overwrite"], {}),
    # --- simbed import-scene
    ("simbed import-scene {d}/nope.obj --out {d}/s.xml", ["nope.obj", "no such file"], {}),
    ("simbed import-scene {d}/seq --out {d}/s.xml", ["seq", "not a file"], {}),
    ("simbed import-scene {d}/a_file --out {d}/s.xml", ["a_file", "not a mesh file"], {}),
    ("simbed import-scene {d}/m.obj --out {d}/s.xml", ["m.obj", "no triangles"], {"m.obj": "not a mesh\n"}),
    ("simbed import-scene {d}/m.ply --out {d}/s.xml", ["m.ply", "not a mesh"], {"m.ply": b""}),
    (
        "simbed import-scene {d}/m.obj --out {d}/s.xml",
        ["m.obj", "not finite"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n"},
    ),
    (
        "simbed import-scene {d}/m.obj --out {d}/s.xml",
        ["m.obj", "degenerate"],
        {"m.obj": "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"},
    ),
    (
        "simbed import-scene {d}/m.obj --out {d}/s.xml",
        ["no surface a car can stand on"],
        {"m.obj": "v 0 0 0\nv 10 0 0\nv 0 0 5\nf 1 2 3\n"},  # a wall, no ground
    ),
    ("simbed import-scene {d}/ground.ply --out {d}/s.xml --scale 0", ["--scale", "above 0"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/s.xml --scale nan", ["--scale", "above 0"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/s.xml --up x", ["--up", "auto, z or y"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/s.xml --ground-cell 0", ["--ground-cell"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/s.xml --max-piece-faces 10", ["--max-piece-faces"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/a_file", ["a_file", ".xml"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/scene.xml", ["scene.xml", "--overwrite"], {}),
    ("simbed import-scene {d}/ground.ply --out {d}/a_file/s.xml", ["a_file", "is a file"], {}),
    # --- simbed export-mesh
    ("simbed export-mesh --scene nonsense --out {d}/m.ply", ["nonsense.xml", "no such scene file"], {}),
    (
        "simbed export-mesh --scene {d}/bad.xml --out {d}/m.ply",
        ["bad.xml", "malformed MJCF"],
        {"bad.xml": "<mujoco>\n"},
    ),
    ("simbed export-mesh --scene town_small --variant 5 --out {d}/m.ply", ["no variant 5"], {}),
    (
        "simbed export-mesh --scene town_small --out {d}/m.ply --route-out {d}/r.txt --route nowhere",
        ["nowhere"],
        {},
    ),
    ("simbed export-mesh --scene town_small --variant -1 --out {d}/m.ply", ["variant", "-1"], {}),
    ("simbed export-mesh --scene {d}/scene.xml --out {d}/a_file/m.ply", ["a_file", "is a file"], {}),
    ("simbed export-mesh --scene {d}/scene.xml --out {d}/seq", ["seq", "is a folder"], {}),
    # a file of an earlier run is not replaced without --overwrite (every command's policy)
    (
        "simbed export-mesh --scene {d}/scene.xml --out {d}/m.ply",
        ["m.ply", "--overwrite"],
        {"m.ply": "ply\n"},
    ),
    (
        "simbed export-mesh --scene {d}/scene.xml --out {d}/m.ply --route-out {d}/route.txt",
        ["route.txt", "exists", "--overwrite"],
        {},
    ),
    # --- simbed demo
    ("simbed demo --out {d}/o --test-frames 0", ["--test-frames", "0"], {}),
    ("simbed demo --out {d}/o --particles 0", ["--particles", "0"], {}),
    ("simbed demo --out {d}/o --seed -1", ["--seed", "-1"], {}),
    ("simbed demo --out {d}/o --device nonsense", ["device", "nonsense"], {}),
    ("simbed demo --out {d}/a_file", ["a_file", "not a folder"], {}),
    # --- simbed trials
    ("simbed trials sideways --out {d}/t --map {d}/map", ["suite", "sideways"], {}),
    (TRIALS + " --map {d}/nope", ["nope", "does not exist"], {}),
    (TRIALS.replace("runtime", "particles") + " --models rang", ["observation model", "rang"], {}),
    (TRIALS.replace("runtime", "particles") + " --counts 100,x", ["--counts", "100,x"], {}),
    (TRIALS.replace("runtime", "particles") + " --counts 0,500", ["particle counts", "0"], {}),
    (
        TRIALS.replace("runtime", "sensors") + " --sensors os1-64,nonsense",
        ["unknown LiDAR preset", "nonsense"],
        {},
    ),
    (TRIALS + " --sensor nonsense", ["unknown LiDAR preset", "nonsense"], {}),
    (TRIALS + " --workers -1", ["--workers", "-1"], {}),
    (TRIALS + " --backend carrier-pigeon", ["backend", "carrier-pigeon"], {}),
    (TRIALS + " --frames 0", ["--frames", "0"], {}),
    (TRIALS + " --starts 0", ["--starts", "0"], {}),
    (TRIALS + " --drive-frames -1", ["--drive-frames", "-1"], {}),
    (TRIALS + " --actors -1", ["--actors", "-1"], {}),
    (TRIALS + " --variant -1", ["--variant", "-1"], {}),
    (TRIALS + " --device nonsense", ["device", "nonsense"], {}),
    (TRIALS + " --scene nonsense", ["nonsense", "no such scene file"], {}),
    (TRIALS + " --route sideways", ["unknown route", "sideways"], {}),
    (TRIALS + " --config " + CFG, ["c.yaml", "malformed YAML"], {"c.yaml": "a: [\n"}),
    (
        TRIALS + " --config " + CFG,
        ["c.yaml", "particles.globl_count"],
        {"c.yaml": "particles:\n  globl_count: 5\n"},
    ),
    (TRIALS + " --compare default", ["--compare", "--report-only"], {}),
    (TRIALS + " --realism snow", ["realism level", "snow"], {}),
    (TRIALS.replace("runtime", "robustness") + " --realism rain", ["--realism", "--levels"], {}),
    (TRIALS + " --report-only", ["results.csv", "no finished trial"], {}),
    ("simbed trials runtime --out {d}/a_file --map {d}/map --quick", ["a_file", "not a folder"], {}),
    # --- simbed render
    (
        "simbed render --scene {d}/bad.xml --out {d}/o.png",
        ["bad.xml", "Line number=3"],
        {"bad.xml": '<mujoco>\n<worldbody>\n<geom type="box" size="1 1"\n</worldbody></mujoco>\n'},
    ),
    ("simbed render --scene nonsense --out {d}/o.png", ["nonsense.xml", "no such scene file"], {}),
    ("simbed render --scene town_small --camera nope --out {d}/o.png", ["camera", "nope"], {}),
    (
        "simbed render --scene {d}/scene.xml --actors 2 --out {d}/o.png",
        ["scene.xml", "actors", "town with roads"],
        {},
    ),
    ("simbed render --scene town_small --variant 9 --out {d}/o.png", ["no variant 9"], {}),
    ("simbed render --scene town_small --actors -1 --out {d}/o.png", ["actors", "-1"], {}),
    ("simbed render --scene town_small --seed -1 --out {d}/o.png", ["--seed", "-1"], {}),
    ("simbed render --scan {d}/nope --out {d}/o.png", ["nope", "no such sequence folder"], {}),
    ("simbed render --scan {d}/seq --frame 3 --out {d}/o.png", ["frame 3", "out of range"], {}),
    ("simbed render --scan {d}/seq --frame -1 --out {d}/o.png", ["frame -1", "out of range"], {}),
    (
        "simbed render --scan {d}/seq --frame 1 --out {d}/o.png",
        ["000001.bin", "truncated"],
        {"seq/velodyne/000001.bin": cut(1)},
    ),
    ("simbed render --scan {d}/seq --out {d}/seq", ["seq", "is a folder"], {}),
    ("simbed render --scene town_small --out {d}/a_file/o.png", ["a_file", "is a file"], {}),
    ("simbed render --scene town_small --out {d}/o.png", ["o.png", "exists", "--overwrite"], {"o.png": b"x"}),
    ("simbed render --scan {d}/seq --out {d}/o.png", ["o.png", "exists", "--overwrite"], {"o.png": b"x"}),
]


# --- running a command in this process -------------------------------------------------------------------

# the warnings a plain ``python`` does not print (its default filters)
_SILENT = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def run_cli(prog: str, args: list[str]) -> tuple[int | None, str]:
    """``prog``'s ``main()`` with ``args``: (exit status, what a process would have printed on stderr:
    its own lines, printed warnings and log records). Any other exception propagates (a traceback)."""
    cli = importlib.import_module(f"{prog}.cli")
    err = io.StringIO()
    handler = logging.StreamHandler(err)
    handler.setLevel(logging.WARNING)
    root = logging.getLogger()
    argv, sigterm = sys.argv, signal.getsignal(signal.SIGTERM)
    sys.argv = [prog, *args]
    root.addHandler(handler)
    code: int | str | None = 0
    try:
        with (
            contextlib.redirect_stderr(err),
            contextlib.redirect_stdout(io.StringIO()),
            warnings.catch_warnings(record=True) as caught,
        ):
            warnings.simplefilter("always")
            try:
                cli.main()
            except SystemExit as exc:
                code = exc.code
    finally:
        sys.argv = argv
        signal.signal(signal.SIGTERM, sigterm)
        root.removeHandler(handler)
    shown = [f"{w.filename}:{w.lineno}: {w.category.__name__}: {w.message}" for w in caught]
    shown = [s for s, w in zip(shown, caught, strict=True) if not issubclass(w.category, _SILENT)]
    return code, err.getvalue() + "".join(f"{s}\n" for s in shown)


def _tree(root: Path):
    return sorted((str(p.relative_to(root)), p.stat().st_mtime_ns, p.stat().st_size) for p in root.rglob("*"))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("good_inputs")
    _write_base(d)
    return d


def _case_folder(base: Path, tmp_path: Path, files: dict) -> Path:
    d = tmp_path / "case"
    shutil.copytree(base, d)
    _apply(d, files)
    return d


def _check(d: Path, command: str, words: list[str]) -> None:
    args = command.format(d=d).split()
    before = _tree(d)
    code, stderr = run_cli(args[0], args[1:])
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    for w in words:
        assert w.format(d=d) in lines[0], (w, lines[0])
    assert _tree(d) == before  # nothing created or changed


def _case_id(i: int, command: str) -> str:
    words = command.split()
    return f"{i:03d}-{words[0]}-{words[1]}"


@pytest.mark.parametrize(
    ("command", "words", "files"), CASES, ids=[_case_id(i, c[0]) for i, c in enumerate(CASES)]
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(base, tmp_path, command, words, files):
    _check(_case_folder(base, tmp_path, files), command, words)


def test_the_table_covers_every_command():
    """At least 100 cases, and some for every command of both CLIs (as the apps list them)."""
    import typer.main

    counts = Counter(" ".join(c[0].split()[:2]) for c in CASES)
    for prog in ("rangemcl", "simbed"):
        group = typer.main.get_command(importlib.import_module(f"{prog}.cli").app)
        assert len(group.commands) >= 6
        for name in group.commands:
            assert counts[f"{prog} {name}"] >= 3, (prog, name)
    assert len(CASES) >= 100


def test_the_good_inputs_are_good(base, tmp_path):
    """The base folder's inputs are accepted, so that each case fails for its own bad input: the sequence
    and the map pass every check of ``localize`` before its filter starts, the map is built from the
    sequence, the results folder evaluates, the sensor spec prints, the scene drives its route."""
    from rangemcl.localization.pipeline import LocalizationPipeline, RunOptions
    from rangemcl.maps.meshmap import MeshMap

    assert MeshMap.load(base / "map").n_triangles == 24
    d = _case_folder(base, tmp_path, {})
    pipeline = LocalizationPipeline(d / "seq", d / "map", d / "o", options=RunOptions(mode="tracking"))
    pipeline.load()
    assert len(pipeline.seq) == N_FRAMES and pipeline.odo_source == "odometry.txt"
    for command in (
        "rangemcl map-info {d}/map",
        "rangemcl evaluate {d}/results --gt {d}/seq/poses.txt",
        "rangemcl sensors {d}/sensor.yaml",
        "rangemcl build-map {d}/seq --out {d}/built --workers 1",
        "simbed import-scene {d}/ground.ply --out {d}/imported.xml",
        "simbed record --scene {d}/scene.xml --route {d}/route.txt --sensor vlp-16 --frames 2 --out {d}/r",
    ):
        args = command.format(d=d).split()
        code, stderr = run_cli(args[0], args[1:])
        assert code == 0 and stderr == "", (command, stderr)
    assert not (d / "o").exists()


def test_place_prior_replaces_a_damaged_prior_with_the_same_bytes(base, tmp_path):
    """The remedy a damaged prior's message names works: ``rangemcl place-prior MAP`` renders it again
    (it does not stop at the damaged file), and the new file is the old one byte for byte."""
    d = _case_folder(base, tmp_path, {"map/place_prior.npz": halve})
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    run = subprocess.run(
        [sys.executable, "-c", code, "place-prior", str(d / "map")], capture_output=True, text=True
    )
    assert run.returncode == 0 and "place prior built (a damaged file replaced)" in run.stdout, run.stderr
    assert (d / "map/place_prior.npz").read_bytes() == (base / "map/place_prior.npz").read_bytes()
    assert run_cli("rangemcl", ["map-info", str(d / "map")])[0] in (0, None)


def test_a_damaged_drive_file_is_one_line(base, tmp_path):
    """The mapping drive's file is checked against map.yaml's sha256 as the ground grid is."""
    from rangemcl.maps.meshmap import MeshMap

    m = MeshMap.load(base / "map")
    m.drive_xy = np.array([[-20.0, -10.0], [0.0, -10.0], [20.0, -10.0]])
    m.save(tmp_path / "map")
    assert run_cli("rangemcl", ["map-info", str(tmp_path / "map")])[0] in (0, None)
    flip_attributes(tmp_path / "map/drive.npz")
    _check(tmp_path, "rangemcl map-info {d}/map", ["drive.npz", "checksum in map.yaml"])


def test_a_prior_rendered_during_localize_is_announced(base, tmp_path, monkeypatch):
    """A map without its place prior: global localization says on stderr that it renders it and where it
    goes (into the map folder; beside the results when the map folder is not writable), then runs."""
    import rangemcl.localization.place_prior as place_prior

    d = _case_folder(base, tmp_path, {"map/place_prior.npz": None, "map/report.json": None})
    args = ["localize", f"{d}/seq", "--map", f"{d}/map", "--particles", "200", "--no-plots", "--frames", "2"]
    code, err = run_cli("rangemcl", [*args, "--out", f"{d}/o"])
    assert code in (0, None), err
    notice = f"rangemcl: rendering the map's place prior (4 cells of 2 m, written to {d}/map/place_prior.npz)"
    assert notice in err, err
    assert f"`rangemcl place-prior {d}/map` renders it ahead" in err
    assert (d / "map/place_prior.npz").read_bytes() == (base / "map/place_prior.npz").read_bytes()
    # the next run finds it: nothing more is rendered
    code, err = run_cli("rangemcl", [*args, "--out", f"{d}/o2"])
    assert code in (0, None) and "rendering" not in err, err
    # a map folder that cannot be written (root ignores permissions, so the check is replaced)
    e = _case_folder(base, tmp_path / "ro", {"map/place_prior.npz": None})
    monkeypatch.setattr(place_prior, "_writable", lambda path: False)
    args[1], args[3] = f"{e}/seq", f"{e}/map"
    code, err = run_cli("rangemcl", [*args, "--out", f"{e}/o"])
    assert code in (0, None) and f"written to {e}/o/place_prior.npz" in err, err
    assert not (e / "map/place_prior.npz").exists() and (e / "o/place_prior.npz").is_file()


def test_the_same_scans_give_the_same_map_bytes(base, tmp_path):
    """``rangemcl build-map`` twice on the same scans: every file of the two maps is the same, byte for
    byte, the place prior included (timings live in report.json only)."""
    maps = []
    for name in ("a", "b"):
        args = ["build-map", str(base / "seq"), "--out", str(tmp_path / name), "--workers", "1"]
        code, err = run_cli("rangemcl", args)
        assert code in (0, None), err
        maps.append(tmp_path / name)
    files = sorted(str(p.relative_to(maps[0])) for p in maps[0].rglob("*") if p.is_file())
    assert "place_prior.npz" in files and "tiles.json" in files
    assert files == sorted(str(p.relative_to(maps[1])) for p in maps[1].rglob("*") if p.is_file())
    files.remove("report.json")
    for name in files:
        assert (maps[0] / name).read_bytes() == (maps[1] / name).read_bytes(), name
    report = json.loads((maps[0] / "report.json").read_text())
    assert report["place_prior"]["place_prior.npz"]["seconds"] > 0


def test_file_outputs_are_replaced_only_with_overwrite_and_their_folders_made(base, tmp_path):
    """The commands that write files follow the folders' policy: a second run with other options is
    refused and the first result stays; with --overwrite it is replaced; missing folders above the files
    are made (``import-scene --out new/folder/scene.xml`` too)."""
    d = _case_folder(base, tmp_path, {})

    def ok(command: str) -> None:
        args = command.format(d=d).split()
        code, err = run_cli(args[0], args[1:])
        assert code in (0, None) and err == "", (command, err)

    ok("simbed make-town --out {d}/new/town/t.xml --size 120 --seed 1")
    first = (d / "new/town/t.xml").read_bytes()
    _check(d, "simbed make-town --out {d}/new/town/t.xml --size 120 --seed 2", ["t.xml", "--overwrite"])
    assert (d / "new/town/t.xml").read_bytes() == first
    ok("simbed make-town --out {d}/new/town/t.xml --size 120 --seed 2 --overwrite")
    assert (d / "new/town/t.xml").read_bytes() != first

    ok("rangemcl sweep --sensor vlp-16 --out {d}/sweep --seed 1")
    scan = (d / "sweep/scan_vlp-16.bin").read_bytes()
    _check(d, "rangemcl sweep --sensor vlp-16 --out {d}/sweep --seed 2", ["range_vlp-16.png", "--overwrite"])
    ok("rangemcl sweep --sensor mq-8 --out {d}/sweep")  # another sensor's files beside it
    ok("rangemcl sweep --sensor vlp-16 --out {d}/sweep --seed 2 --overwrite")
    assert (d / "sweep/scan_vlp-16.bin").read_bytes() != scan and (d / "sweep/scan_mq-8.bin").is_file()

    ok("simbed export-mesh --scene {d}/scene.xml --out {d}/made/here/m.ply")
    _check(d, "simbed export-mesh --scene {d}/scene.xml --out {d}/made/here/m.ply", ["m.ply", "--overwrite"])
    ok("simbed export-mesh --scene {d}/scene.xml --out {d}/made/here/m.ply --overwrite")

    ok("simbed render --scan {d}/seq --out {d}/pictures/scan.png")
    _check(
        d, "simbed render --scan {d}/seq --frame 1 --out {d}/pictures/scan.png", ["scan.png", "--overwrite"]
    )
    ok("simbed render --scan {d}/seq --frame 1 --out {d}/pictures/scan.png --overwrite")

    ok("simbed import-scene {d}/ground.ply --out {d}/new_folder/deeper/scene.xml")
    assert (d / "new_folder/deeper/scene_ground.bin").is_file()


def test_a_checkpoint_of_another_version_is_refused_in_one_line(base, tmp_path):
    """The filter's checkpoint holds its objects as that version lays them out: a folder interrupted by
    another version of rangemcl is refused before any work, naming both versions and the way out."""
    from rangemcl import __version__
    from rangemcl.common.checkpoint import save_state

    d = _case_folder(base, tmp_path, {"results/.resume": DIR})
    save_state(d / "results/.resume/state.npz", {}, {"fingerprint": {"rangemcl_version": "0.16.0"}})
    words = ["results", "written by rangemcl 0.16.0", f"this is {__version__}", "--overwrite"]
    _check(d, LOC.replace("{d}/o", "{d}/results") + " --resume", words)


def test_in_process_equals_a_process(base, tmp_path):
    """A few cases as real processes: the same line, the same status."""
    d = _case_folder(base, tmp_path, {"seq/poses.txt": ELEVEN})
    for command in (LOC + " --frames -5", BUILD, "rangemcl map-info {d}/nope"):
        args = command.format(d=d).split()
        code = "import sys; from {m}.cli import main; sys.argv[0] = '{m}'; main()".format(m=args[0])
        out = subprocess.run(
            [sys.executable, "-c", code, *args[1:]], capture_output=True, text=True, timeout=120
        )
        assert (out.returncode, out.stderr) == run_cli(args[0], args[1:])


def test_a_map_memory_budget_too_small_is_refused_before_the_first_frame(base, tmp_path):
    """``--map-memory`` short of what the run needs (what is held besides the tiles: the ground grid, the
    drivable area, the place prior, the beam prior the first update loads for scans with nothing in the
    high band; and room for the largest tile) is refused before the first frame: one line with the total
    and its parts, exit status 2, nothing left in --out. Before, a budget that held all but the beam prior
    failed at the first update and left --out behind, and one that held no tile said "the smallest needs
    0.0 MB". The total it names runs."""
    import re

    d = _case_folder(base, tmp_path, {})
    run = [*LOC.format(d=d).split()[1:], "--no-plots"]
    code, err = run_cli("rangemcl", [*run, "--map-memory", "10"])  # room to spare: what the run holds
    assert code in (0, None), err
    derived = json.loads((d / "o" / "summary.json").read_text())["map_memory"]["derived_mb"]
    assert {"ground grid", "drivable area", "place prior", "beam place prior"} <= set(derived)
    shutil.rmtree(d / "o")
    held = sum(derived.values())
    beam = derived["beam place prior"]
    words = ["--map-memory", "is too small for this run", "ground grid", "place prior", "beam place prior"]
    totals = []
    for budget in (held - beam / 2, held - beam + 1e-4):  # frames later; no tile fits
        _check(d, LOC + f" --no-plots --map-memory {budget:.6f}", [*words, "the largest tile"])
        assert not (d / "o").exists()
        _code, err = run_cli("rangemcl", [*run, "--map-memory", f"{budget:.6f}"])
        totals.append(float(re.search(r"it needs ([0-9.]+) MB in all \(", err).group(1)))
    assert totals[0] == totals[1] >= held
    code, err = run_cli("rangemcl", [*run, "--map-memory", str(totals[0])])  # the total it names fits
    assert code in (0, None), err
    summary = json.loads((d / "o" / "summary.json").read_text())
    assert summary["frames"] == N_FRAMES and summary["map_memory"]["needed_mb"] <= totals[0]


def _nan_drive(d: Path, nan_frames: set[int], n: int = 20) -> None:
    """The base sequence made ``n`` frames long (0.5 m a frame along x), the scans of ``nan_frames`` all
    NaN (x, y, z and intensity)."""
    seq = d / "seq"
    shutil.rmtree(seq / "velodyne")
    (seq / "velodyne").mkdir()
    for k in range(n):
        scan = ground_scan()
        if k in nan_frames:
            scan[:] = np.nan
        (seq / "velodyne" / f"{k:06d}.bin").write_bytes(scan.tobytes())
    poses = "".join(pose_line(0.5 * k) for k in range(n))
    (seq / "poses.txt").write_text(poses)
    (seq / "odometry.txt").write_text(poses)
    (seq / "times.txt").write_text("".join(f"{0.1 * k:.9f}\n" for k in range(n)))


def test_a_drive_without_valid_points_is_odometry_alone_not_a_success(base, tmp_path):
    """Scans that are all NaN: the metrics and the summary say how many frames were localized from scans,
    the summary counts the NaN points dropped, and a run whose filter never had a scan to weigh is not a
    success (the reason in metrics.json and in the metrics line), also when evaluated again; a drive with
    some scans keeps the paper's success."""
    from rangemcl.cli import metrics_line

    runs = {}
    for name, nan_frames in (("some", set(range(3, 17))), ("none", set(range(20)))):
        d = _case_folder(base, tmp_path / name, {})
        _nan_drive(d, nan_frames)
        code, err = run_cli("rangemcl", [*LOC.format(d=d).split()[1:], "--mode", "tracking", "--no-plots"])
        assert code in (0, None), err
        metrics = json.loads((d / "o" / "metrics.json").read_text())
        summary = json.loads((d / "o" / "summary.json").read_text())
        assert summary["nan_points_dropped"] == len(nan_frames) * N_POINTS
        assert summary["scans_with_nan_points"] == len(nan_frames)
        scanned = 20 - len(nan_frames)
        assert metrics["frames_localized_from_scans"] == summary["frames_localized_from_scans"] == scanned
        assert metrics["frames_without_scan"] == len(nan_frames)
        assert metrics["success_requires_a_scan_update"] is True
        runs[name] = d, metrics, summary
    _d, metrics, summary = runs["some"]
    assert metrics["success"] and metrics["failure_reason"] is None and metrics["scan_updates"] > 0
    assert "success" in metrics_line(summary["metrics"]) and "6 of 20 frames localized from scans" in (
        metrics_line(summary["metrics"])
    )
    d, metrics, summary = runs["none"]
    assert metrics["location_rmse_m"] < 0.01  # odometry alone, from the true start ...
    assert not metrics["success"] and metrics["scan_updates"] == 0  # ... is not a success
    assert "no frame had a scan with a valid point" in metrics["failure_reason"]
    assert not summary["metrics"]["success"]
    line = metrics_line(summary["metrics"])
    assert "FAILURE (no frame had a scan with a valid point" in line and "0 of 20 frames" in line
    code, err = run_cli("rangemcl", ["evaluate", str(d / "o"), "--gt", str(d / "seq" / "poses.txt")])
    assert code in (0, None), err
    again = json.loads((d / "o" / "metrics.json").read_text())
    assert not again["success"] and again["failure_reason"] == metrics["failure_reason"]
