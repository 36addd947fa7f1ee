"""The simbed console script as a user runs it: results on disk, and one-line errors with exit status 2."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from rangemcl.datasets.kitti import load_sequence


def simbed(*args: str) -> subprocess.CompletedProcess:
    code = "import sys; from simbed.cli import main; sys.argv[0] = 'simbed'; main()"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600, env=env
    )


def one_line_error(out: subprocess.CompletedProcess, *needles: str) -> None:
    assert out.returncode == 2, (out.stdout, out.stderr)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_record_writes_a_loadable_sequence(tmp_path):
    out = tmp_path / "seq"
    r = simbed(
        "record", "--scene", "town_small", "--route", "test", "--sensor", "vlp-16", "--frames", "3",
        "--actors", "2", "--seed", "7", "--out", str(out),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    seq = load_sequence(out, require_poses=True)
    assert len(seq) == 3 and seq.meta["route"] == "test" and seq.meta["actors"] == 2
    assert "wrote 3 frames" in r.stdout
    # an existing sequence is not overwritten by accident
    again = simbed("record", "--frames", "1", "--out", str(out))
    one_line_error(again, str(out))
    assert len(load_sequence(out)) == 3
    # nor by resuming a recording that is complete
    resumed = simbed(
        "record", "--scene", "town_small", "--route", "test", "--sensor", "vlp-16", "--frames", "5",
        "--actors", "2", "--seed", "7", "--out", str(out), "--resume",
    )  # fmt: skip
    one_line_error(resumed, str(out), "complete; nothing to resume")
    assert len(load_sequence(out)) == 3


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--scene", "no_such_town"], ["no_such_town", "no such scene"]),
        (["--sensor", "lidar-9000"], ["lidar-9000"]),
        (["--route", "scenic"], ["unknown route 'scenic'"]),
        (["--frames", "0"], ["frames"]),
        (["--variant", "7"], ["variant 7"]),
    ],
)
def test_record_bad_input(tmp_path, args, needles):
    out = tmp_path / "seq"
    r = simbed("record", "--frames", "2", "--out", str(out), *args)
    one_line_error(r, *needles)
    assert not out.exists()  # nothing half-written


def test_malformed_and_missing_scene_files(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><geom type='box' size='1 1'</worldbody>")
    r = simbed("record", "--scene", str(bad), "--out", str(tmp_path / "o"))
    one_line_error(r, str(bad), "malformed")
    r = simbed("export-mesh", "--scene", str(tmp_path / "missing.xml"), "--out", str(tmp_path / "m.ply"))
    one_line_error(r, "missing.xml")
    assert not (tmp_path / "o").exists() and not (tmp_path / "m.ply").exists()


def test_route_off_the_road_network(tmp_path):
    wp = tmp_path / "route.txt"
    wp.write_text("0 0\n500 500\n")
    r = simbed("record", "--route", str(wp), "--out", str(tmp_path / "o"))
    one_line_error(r, "route.txt", "off the road network")
    assert not (tmp_path / "o").exists()


def test_unwritable_output(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = simbed("record", "--frames", "1", "--out", str(blocker / "seq"))
    one_line_error(r, str(blocker / "seq"))


def test_export_mesh_is_the_static_scene(tmp_path):
    """The static mesh, and the mapping route as waypoints: imported with it as the map's drive, global
    localization searches near the roads only (the place prior over the roads, not the whole ground)."""
    out = tmp_path / "gt.ply"
    route = tmp_path / "route.txt"
    r = simbed("export-mesh", "--scene", "town_small", "--out", str(out), "--route-out", str(route))
    assert r.returncode == 0, r.stderr
    mesh = trimesh.load(out, force="mesh")
    lo, hi = mesh.bounds
    assert hi[0] - lo[0] >= 190 and hi[1] - lo[1] >= 190  # the 200 m town
    assert len(mesh.faces) > 10_000
    from simbed.record import scene_route
    from simbed.sim.world import World

    world = World("town_small")
    xy = np.loadtxt(route)
    np.testing.assert_allclose(xy, scene_route(world, "mapping").points, atol=1e-3)
    from simbed.scenes.routes import distance_to_roads

    off = distance_to_roads(xy, world.graph)  # from the roads' centre lines: a lane, corners cut at junctions
    assert np.median(off) < world.town.road_width_m / 2 and off.max() < world.town.road_width_m
    from rangemcl.localization import InitSettings, drivable_cells
    from rangemcl.maps.meshmap import MeshMap

    maps = {}
    for name, extra in (("with_drive", ["--drive", str(route)]), ("without", [])):
        cmd = [sys.executable, "-m", "rangemcl.cli", "import-mesh", str(out), "--out", str(tmp_path / name)]
        done = subprocess.run([*cmd, "--no-prior", *extra], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        maps[name] = MeshMap.load(tmp_path / name)
    drive = maps["with_drive"].drive_xy
    assert maps["without"].drive_xy is None and len(drive) > 100
    steps = np.linalg.norm(np.diff(drive[:-1], axis=0), axis=1)
    assert steps.min() >= 1.0 - 1e-9  # thinned to a point a metre (the last point kept as it is)
    near = len(drivable_cells(maps["with_drive"], InitSettings().drive_radius_m).corners)
    assert (
        0.2 * len(drivable_cells(maps["without"], InitSettings().drive_radius_m).corners)
        < near
        < 0.8 * len(drivable_cells(maps["without"], InitSettings().drive_radius_m).corners)
    )


def test_render_scene_and_scan(tmp_path):
    png = tmp_path / "scene.png"
    r = simbed("render", "--scene", "town_small", "--actors", "3", "--out", str(png))
    assert r.returncode == 0, r.stderr
    from PIL import Image

    image = np.asarray(Image.open(png))
    assert image.shape[:2] == (960, 1280) and image.std() > 10  # a picture, not a blank
    seq = tmp_path / "seq"
    assert simbed("record", "--frames", "1", "--sensor", "vlp-16", "--out", str(seq)).returncode == 0
    scan_png = tmp_path / "scan.png"
    r = simbed("render", "--scan", str(seq), "--out", str(scan_png))
    assert r.returncode == 0, r.stderr
    assert np.asarray(Image.open(scan_png)).shape[:2] == (16 * 4, 1808)
    again = simbed("render", "--scan", str(seq), "--frame", "1", "--out", str(scan_png))
    one_line_error(again, "exists", "--overwrite")
    other = tmp_path / "other.png"
    one_line_error(simbed("render", "--scan", str(seq), "--frame", "5", "--out", str(other)), "frame 5")


def test_make_town_writes_a_loadable_town(tmp_path):
    out = tmp_path / "town_t.xml"
    r = simbed("make-town", "--seed", "4", "--size", "150", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert out.is_file() and out.with_suffix(".yaml").is_file()
    from simbed.sim.world import World

    world = World(out)
    assert world.town is not None and len(world.town.edges) >= len(world.town.nodes)
    one_line_error(simbed("make-town", "--size", "-5", "--out", str(tmp_path / "t.xml")), "size")


def test_trials_bad_localizer_settings(tmp_path):
    cfg = tmp_path / "loc.yaml"
    cfg.write_text("observation:\n  ray_sampling: beams\n")
    r = simbed(
        "trials", "runtime", "--out", str(tmp_path / "s"), "--map", str(tmp_path), "--config", str(cfg)
    )
    one_line_error(r, "loc.yaml", "ray_sampling", "beams")
    r = simbed(
        "trials", "runtime", "--out", str(tmp_path / "s"), "--map", str(tmp_path), "--config", "nope.yaml"
    )
    one_line_error(r, "nope.yaml")
    assert not (tmp_path / "s").exists()
