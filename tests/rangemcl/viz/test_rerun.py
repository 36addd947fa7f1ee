"""rangemcl.viz.rerun: a synthetic run written to an .rrd and read back with rerun's own reader (no
viewer)."""

from __future__ import annotations

import math
import sys
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.viz.rerun import INSTALL, DriveViewer, RunViewer, colormap, pose_matrix, thin_indices

pytest.importorskip("rerun")
from rerun.chunk import RrdReader

N_FRAMES = 20


def box_scene() -> tuple[np.ndarray, np.ndarray]:
    """A 40 m ground square and a 4 m cube on it: (V, 3) and (F, 3)."""
    ground = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]], np.float64)
    cube = np.array([[x, y, z] for z in (0, 4) for y in (5, 9) for x in (5, 9)], np.float64)
    faces = [[0, 1, 2], [0, 2, 3]]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    for a, b, c, d in quads:
        faces += [[4 + a, 4 + b, 4 + c], [4 + a, 4 + c, 4 + d]]
    return np.vstack([ground, cube]), np.array(faces, np.int32)


def read_rrd(path) -> dict[str, list]:
    """Entity path -> the record batches of its chunks (static and temporal)."""
    out = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        out[chunk.entity_path].append((chunk.is_static, chunk.to_record_batch()))
    return out


def temporal_column(batches, column: str) -> tuple[list[int], list]:
    """Rows of ``column`` over all temporal chunks, ordered by the ``frame`` timeline."""
    rows = []
    for static, rb in batches:
        if static or column not in rb.schema.names:  # e.g. a Clear's chunk
            continue
        rows += zip(rb.column("frame").to_pylist(), rb.column(column).to_pylist(), strict=True)
    rows.sort(key=lambda r: r[0])
    return [r[0] for r in rows], [r[1] for r in rows]


def synthetic_run(viewer, n_frames: int = N_FRAMES, scan_points: int = 500, n_particles: int = 400):
    rng = np.random.default_rng(0)
    errors = []
    for i in range(n_frames):
        truth = np.eye(4)
        truth[:3, 3] = (0.5 * i, 0.0, 1.7)
        est = np.array([0.5 * i + 0.1, 0.05 * i, 0.01])
        particles = est + rng.normal(scale=[1.0, 1.0, 0.1], size=(n_particles, 3))
        w = rng.random(n_particles)
        scan = rng.normal(scale=10.0, size=(scan_points, 3))
        errors.append(0.1 * i)
        viewer.frame(
            i,
            0.1 * i,
            scan_sensor=scan,
            estimate=est,
            truth=truth,
            particles=particles,
            weights=w / w.sum(),
            sensor_height_m=1.7,
            error_m=errors[-1],
        )
    return errors


def test_run_written_and_read_back(tmp_path):
    out = tmp_path / "run.rrd"
    v, f = box_scene()
    with RunViewer.open("test run", out_rrd=out, max_scan_points=100, max_arrows=50) as viewer:
        assert viewer.enabled and viewer.out_rrd == out
        viewer.log_map(v, f)
        errors = synthetic_run(viewer)
    assert not viewer.enabled  # closed: further frames are ignored
    viewer.frame(99, 9.9, error_m=1.0)

    data = read_rrd(out)
    for entity in (
        "/world",
        "/world/map",
        "/world/estimate",
        "/world/estimate/scan",
        "/world/truth",
        "/world/particles",
        "/world/particles/yaw",
        "/world/path/estimate",
        "/world/path/truth",
        "/metrics/error_m",
        "/metrics/particles",
    ):
        assert entity in data, f"{entity} missing from {sorted(data)}"

    (static, mesh), *_ = data["/world/map"]
    assert static
    assert len(mesh.column("Mesh3D:triangle_indices").to_pylist()[0]) == len(f)

    frames, values = temporal_column(data["/metrics/error_m"], "Scalars:scalars")
    assert frames == list(range(N_FRAMES))
    np.testing.assert_allclose([x[0] for x in values], errors)
    times = []
    for _static, rb in data["/metrics/error_m"]:
        times += rb.column("time").cast("int64").to_pylist()
    np.testing.assert_allclose(sorted(times), [round(0.1 * i * 1e9) for i in range(N_FRAMES)], atol=1)

    frames, scans = temporal_column(data["/world/estimate/scan"], "Points3D:positions")
    assert frames == list(range(N_FRAMES)) and all(len(s) == 100 for s in scans)  # max_scan_points
    frames, arrows = temporal_column(data["/world/particles/yaw"], "Arrows3D:vectors")
    assert frames == list(range(N_FRAMES)) and all(len(a) == 50 for a in arrows)
    _, clouds = temporal_column(data["/world/particles"], "Points3D:positions")
    assert all(len(c) == 400 for c in clouds)
    assert clouds[0][0][2] == pytest.approx(1.7)  # particles at the sensor height
    frames, paths = temporal_column(data["/world/path/estimate"], "LineStrips3D:strips")
    assert frames == list(range(1, N_FRAMES))  # a strip from the second pose on
    assert len(paths[-1][0]) == N_FRAMES
    _, translations = temporal_column(data["/world/truth"], "Transform3D:translation")
    np.testing.assert_allclose(translations[-1][0], [0.5 * (N_FRAMES - 1), 0.0, 1.7])


def test_size_stays_small(tmp_path):
    """Full scans and big clouds are thinned when a file is written: a few MB per 100 frames."""
    out = tmp_path / "big.rrd"
    with RunViewer.open("big", out_rrd=out) as viewer:
        synthetic_run(viewer, n_frames=10, scan_points=60_000, n_particles=10_000)
    per_frame = out.stat().st_size / 10
    assert per_frame < 100_000, f"{per_frame:.0f} bytes a frame"  # 56 kB with FILE_LIMITS


def test_estimated_path_skips_frames_before_convergence(tmp_path):
    out = tmp_path / "conv.rrd"
    converged = [False, False, False, True, True, True, False, True, True, True]
    with RunViewer.open("conv", out_rrd=out) as viewer:
        for i, c in enumerate(converged):
            viewer.frame(i, 0.1 * i, estimate=(float(i), 0.0, 0.0), truth=(float(i), 0.5, 0.0), converged=c)
    data = read_rrd(out)
    _, strips = temporal_column(data["/world/path/estimate"], "LineStrips3D:strips")
    assert [len(s) for s in strips[-1]] == [3, 3]  # frames 3-5 and 7-9
    assert strips[-1][1][0] == pytest.approx([7.0, 0.0, 0.0])
    _, truth = temporal_column(data["/world/path/truth"], "LineStrips3D:strips")
    assert [len(s) for s in truth[-1]] == [10]
    _, errors = temporal_column(data["/metrics/error_m"], "Scalars:scalars")
    np.testing.assert_allclose([e[0] for e in errors], 0.5)  # estimate vs truth, when not given


def test_large_map_is_thinned_with_a_note(tmp_path):
    out = tmp_path / "map.rrd"
    v, f = box_scene()
    with RunViewer.open("map", out_rrd=out) as viewer:
        viewer.log_map(v, f, max_triangles=4)
    data = read_rrd(out)
    (_, mesh), *_ = data["/world/map"]
    assert len(mesh.column("Mesh3D:triangle_indices").to_pylist()[0]) == 4
    assert len(mesh.column("Mesh3D:vertex_positions").to_pylist()[0]) <= 12  # unused vertices dropped
    (_, note), *_ = data["/notes"]
    assert "14 triangles" in note.column("TextLog:text").to_pylist()[0][0]


def test_mesh_map(tmp_path):
    from rangemcl.maps.meshmap import MeshMap

    v, f = box_scene()
    mesh_map = MeshMap.from_mesh(v, f, is_ground=v[:, 2] < 0.1)
    out = tmp_path / "m.rrd"
    with RunViewer.open("m", out_rrd=out) as viewer:
        viewer.log_mesh_map(mesh_map)
    (_, mesh), *_ = read_rrd(out)["/world/map"]
    assert len(mesh.column("Mesh3D:vertex_colors").to_pylist()[0]) == len(v)


def test_disabled_viewer_does_nothing(tmp_path):
    for viewer in (RunViewer.disabled(), RunViewer.open("off")):
        assert not viewer.enabled
        with viewer:
            viewer.log_map(*box_scene())
            viewer.frame(0, 0.0, estimate=(0, 0, 0), particles=np.zeros((3, 3)), error_m=1.0)
    drive = DriveViewer.open("off")
    assert not drive.enabled
    drive.record_frame(SimpleNamespace(index=0), actors=[])  # returns before reading the frame
    drive.close()
    assert list(tmp_path.iterdir()) == []


def test_drive_viewer(tmp_path):
    out = tmp_path / "drive.rrd"
    rng = np.random.default_rng(1)
    actor = {"name": "actor_0_car", "xyz": np.array([5.0, 1.0, 0.75]), "quat_wxyz": np.array([1.0, 0, 0, 0])}
    actor |= {"half": (2.25, 0.9, 0.75), "rgba": (0.8, 0.2, 0.2, 1)}
    with DriveViewer.open("drive", out_rrd=out) as viewer:
        viewer.log_map(*box_scene())
        for i in range(5):
            T = pose_matrix((i, 0.0, 0.0), 1.7)
            sweep = SimpleNamespace(
                points=rng.normal(size=(800, 3)), label=(np.arange(800) % 7 == 0).astype(np.uint8)
            )
            frame = SimpleNamespace(index=i, time_s=0.1 * (i + 1), T_world_sensor=T, sweep=sweep)
            viewer.record_frame(frame, actors=[actor] if i < 3 else [])
    data = read_rrd(out)
    frames, sweeps = temporal_column(data["/world/car/sweep"], "Points3D:positions")
    assert frames == list(range(5)) and all(len(s) == 800 for s in sweeps)
    _, colors = temporal_column(data["/world/car/sweep"], "Points3D:colors")
    assert len(set(colors[0])) > 1
    frames, boxes = temporal_column(data["/world/actors"], "Boxes3D:centers")
    assert frames == [0, 1, 2] and boxes[0] == [pytest.approx([5.0, 1.0, 0.75])]
    _, cleared = temporal_column(data["/world/actors"], "Clear:is_recursive")
    assert len(cleared) == 2  # frames without actors clear the boxes
    assert "/world/path/car" in data and "/world/map" in data


@pytest.mark.parametrize("where", ["missing", "folder"])
def test_bad_out_path(tmp_path, where):
    out = tmp_path / "nope" / "run.rrd" if where == "missing" else tmp_path
    with pytest.raises(InputError) as err:
        RunViewer.open("x", out_rrd=out)
    msg = str(err.value)
    assert "\n" not in msg and str(tmp_path) in msg
    assert ("does not exist" if where == "missing" else "is a folder") in msg


def test_missing_rerun_names_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    with pytest.raises(InputError) as err:
        RunViewer.open("x", out_rrd=tmp_path / "run.rrd")
    assert "\n" not in str(err.value) and INSTALL in str(err.value)
    with pytest.raises(InputError, match="simbed-rangemcl\\[viz\\]"):
        DriveViewer.open("x", spawn=True)
    assert not RunViewer.open("x").enabled  # nothing asked: no import at all


def test_helpers():
    assert thin_indices(5, 10).tolist() == [0, 1, 2, 3, 4]
    idx = thin_indices(1000, 10)
    assert len(idx) == 10 and idx[0] == 0 and idx[-1] == 999
    c = colormap([0.0, 0.5, 1.0, math.nan])
    assert c.shape == (4, 3) and c.dtype == np.uint8 and not np.array_equal(c[0], c[2])
    T = pose_matrix((1.0, 2.0, math.pi / 2), 3.0)
    np.testing.assert_allclose(T @ [1, 0, 0, 1], [1.0, 3.0, 3.0, 1.0], atol=1e-12)
    with pytest.raises(ValueError):
        pose_matrix(np.zeros(4))
