"""Sequences in the KITTI layout (``rangemcl.datasets.kitti``): round trips, KITTI files, interrupted
recordings,
validation.

Expected values come from this file: rotations are built from random unit quaternions with the textbook
formula (so the TUM quaternions can be checked against the quaternion that made the pose), KITTI files are
typed in as KITTI writes them, and ``poses @ Tr`` is computed here.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rangemcl.datasets.kitti import (
    Sequence,
    SequenceWriter,
    load_sequence,
    poses_to_tum,
    read_poses_txt,
    write_poses_txt,
)
from rangemcl.datasets.scanio import write_scan_bin
from rangemcl.errors import InputError

# --- independent helpers ---------------------------------------------------------------------------------


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (textbook formula)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_poses(rng: np.random.Generator, n: int, scale: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random rigid transforms ``(n, 4, 4)`` and the unit quaternions of their rotations."""
    q = random_quats(rng, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = quat_to_matrix(q[k])
        T[k, :3, 3] = rng.normal(scale=scale, size=3)
    return T, q


def make_sequence(root: Path, n: int = 4, *, seed: int = 0, extras: bool = True, **writer_kw) -> dict:
    """Record ``n`` random frames with the writer; returns what was written."""
    rng = np.random.default_rng(seed)
    poses, _ = random_poses(rng, n)
    odom, _ = random_poses(rng, n)
    times = np.cumsum(rng.uniform(0.0, 0.2, n))
    scans = [rng.normal(scale=20, size=(int(m), 3)).astype(np.float32) for m in rng.integers(0, 50, n)]
    inten = [rng.uniform(0, 1, len(s)).astype(np.float32) for s in scans]
    imu = rng.uniform(-0.2, 0.2, size=(n, 2))
    pmeta = [
        {
            "ring": rng.integers(0, 64, len(s)).astype(np.uint16),
            "column": rng.integers(0, 2048, len(s)).astype(np.uint16),
            "time_s": rng.uniform(0, 0.1, len(s)).astype(np.float32),
            "label": rng.integers(0, 2, len(s)).astype(np.uint8),
        }
        for s in scans
    ]
    meta = {"scene": "town_small", "seed": seed, "sensor": {"name": "vlp16", "beams": 16}, "route": "loop"}
    with SequenceWriter(root, meta=meta, **writer_kw) as w:
        for k in range(n):
            got = w.add_frame(
                scans[k],
                pose=poses[k],
                time_s=times[k],
                intensity=inten[k],
                odometry=odom[k] if extras else None,
                imu_roll_pitch=imu[k] if extras else None,
                point_meta=pmeta[k] if extras else None,
            )
            assert got == k
    return dict(
        poses=poses, odom=odom, times=times, scans=scans, inten=inten, imu=imu, pmeta=pmeta, meta=meta
    )


@pytest.fixture
def seq_dir(tmp_path: Path) -> Path:
    root = tmp_path / "seq"
    make_sequence(root)
    return root


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


# --- round trips -----------------------------------------------------------------------------------------


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), extras=st.booleans())
def test_round_trip(seed: int, n: int, extras: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "seq"
        w = make_sequence(root, n, seed=seed, extras=extras)
        seq = load_sequence(root, require_poses=True)
        assert isinstance(seq, Sequence)
        assert len(seq) == n
        assert [p.name for p in seq.scan_paths] == [f"{k:06d}.bin" for k in range(n)]
        assert seq.poses.shape == (n, 4, 4) and seq.poses.dtype == np.float64
        np.testing.assert_allclose(seq.poses, w["poses"], rtol=1e-9, atol=0)
        np.testing.assert_allclose(seq.times, w["times"], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(seq.calib_Tr, np.eye(4))
        assert seq.meta == {**w["meta"], "complete": True}
        for k in range(n):
            pts, inten = seq.scan_with_intensity(k)
            assert pts.dtype == np.float32 and pts.shape == w["scans"][k].shape
            assert pts.tobytes() == w["scans"][k].tobytes()
            assert inten.tobytes() == w["inten"][k].tobytes()
            assert seq.scan(k).tobytes() == w["scans"][k].tobytes()
            pm = seq.point_meta(k)
            if extras:
                assert pm.keys() == w["pmeta"][k].keys()
                for key, a in w["pmeta"][k].items():
                    assert pm[key].dtype == a.dtype
                    np.testing.assert_array_equal(pm[key], a)
            else:
                assert pm == {}
        if extras:
            np.testing.assert_allclose(seq.odometry, w["odom"], rtol=1e-9, atol=0)
            np.testing.assert_allclose(seq.imu_roll_pitch, w["imu"], rtol=1e-9, atol=0)
        else:
            assert seq.odometry is None and seq.imu_roll_pitch is None
            assert not (root / "odometry.txt").exists() and not (root / "imu.txt").exists()
        assert not [p for p in root.rglob("*") if p.name.startswith(".")]  # no temporary files left


def test_negative_index_and_range(seq_dir: Path) -> None:
    seq = load_sequence(seq_dir)
    assert seq.scan(-1).tobytes() == seq.scan(len(seq) - 1).tobytes()
    with pytest.raises(InputError, match="out of range"):
        seq.scan(len(seq))


def test_text_formats(seq_dir: Path) -> None:
    pose_line = (seq_dir / "poses.txt").read_text().splitlines()[0].split()
    assert len(pose_line) == 12 and all(
        "e" in v and len(v.split("e")[0].lstrip("-")) == 11 for v in pose_line
    )
    t = (seq_dir / "times.txt").read_text().splitlines()[0]
    assert len(t.split(".")[1]) == 9
    assert (seq_dir / "calib.txt").read_text().startswith("Tr: 1.000000000e+00 0.000000000e+00")


def test_sequence_without_optional_files(tmp_path: Path) -> None:
    """Scans only (like KITTI test sequences 11-21): loads, with Nones and identity calib."""
    for k in range(3):
        write_scan_bin(tmp_path / "velodyne" / f"{k:06d}.bin", np.ones((5, 3)))
    seq = load_sequence(tmp_path)
    assert len(seq) == 3
    assert seq.poses is None and seq.times is None and seq.odometry is None and seq.imu_roll_pitch is None
    assert seq.meta == {}
    np.testing.assert_array_equal(seq.calib_Tr, np.eye(4))
    with pytest.raises(InputError, match=r"poses\.txt"):
        load_sequence(tmp_path, require_poses=True)


def test_update_meta_and_numpy_values(tmp_path: Path) -> None:
    with SequenceWriter(tmp_path / "s", meta={"seed": np.int64(3), "spec": {"elev": np.arange(3.0)}}) as w:
        w.add_frame(np.zeros((2, 3)), pose=np.eye(4), time_s=0.0)
        w.update_meta(frames=1, route_done=True, complete=True, small=1e-5)
        assert load_sequence(tmp_path / "s").meta["complete"] is False  # still recording
    meta = load_sequence(tmp_path / "s").meta
    assert meta == {
        "seed": 3,
        "spec": {"elev": [0.0, 1.0, 2.0]},
        "frames": 1,
        "route_done": True,
        "small": 1e-5,
        "complete": True,
    }


def test_meta_yaml_exponent_floats(seq_dir: Path) -> None:
    (seq_dir / "meta.yaml").write_text("noise: 1e-3\ncomplete: true\n")
    assert load_sequence(seq_dir).meta["noise"] == pytest.approx(1e-3)


# --- KITTI -----------------------------------------------------------------------------------------------

# KITTI odometry sequence 00's calib.txt, as distributed.
KITTI_CALIB = """\
P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 4.915215000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
"""  # noqa: E501

# The first three lines of KITTI's poses/00.txt.
KITTI_POSES = """\
1.000000e+00 9.043680e-12 2.326809e-11 5.551115e-17 9.043683e-12 1.000000e+00 2.392370e-10 3.330669e-16 2.326810e-11 2.392370e-10 9.999999e-01 -4.440892e-16
9.999978e-01 5.272628e-04 -2.066935e-03 -4.690294e-02 -5.296506e-04 9.999992e-01 -1.154865e-03 -2.839928e-02 2.066324e-03 1.155958e-03 9.999971e-01 8.586941e-01
9.999910e-01 1.048972e-03 -4.131348e-03 -9.374345e-02 -1.058514e-03 9.999968e-01 -2.308104e-03 -5.676064e-02 4.128913e-03 2.312456e-03 9.999887e-01 1.716275e+00
"""  # noqa: E501

KITTI_TIMES = "0.000000e+00\n1.037359e-01\n2.073381e-01\n"


def kitti_matrix(line: str) -> np.ndarray:
    T = np.eye(4)
    T[:3] = np.array(line.split(), dtype=np.float64).reshape(3, 4)
    return T


def write_kitti_scans(folder: Path, n: int) -> None:
    rng = np.random.default_rng(1)
    for k in range(n):
        write_scan_bin(folder / "velodyne" / f"{k:06d}.bin", rng.normal(size=(10, 3)), rng.uniform(size=10))


def test_kitti_calib_gives_lidar_poses(tmp_path: Path) -> None:
    (tmp_path / "calib.txt").write_text(KITTI_CALIB)
    (tmp_path / "poses.txt").write_text(KITTI_POSES)
    (tmp_path / "times.txt").write_text(KITTI_TIMES)
    write_kitti_scans(tmp_path, 3)
    seq = load_sequence(tmp_path, require_poses=True)
    Tr = kitti_matrix(KITTI_CALIB.splitlines()[4].partition(":")[2])
    assert not np.allclose(Tr, np.eye(4))
    np.testing.assert_array_equal(seq.calib_Tr, Tr)
    for k, line in enumerate(KITTI_POSES.splitlines()):
        np.testing.assert_allclose(seq.poses[k], kitti_matrix(line) @ Tr, rtol=0, atol=1e-15)
    np.testing.assert_allclose(seq.times, [0.0, 0.1037359, 0.2073381])
    assert seq.meta == {}


def test_kitti_poses_folder_fallback(tmp_path: Path) -> None:
    """Real KITTI: dataset/sequences/00/ with dataset/poses/00.txt."""
    root = tmp_path / "dataset" / "sequences" / "00"
    root.mkdir(parents=True)
    (root / "calib.txt").write_text(KITTI_CALIB)
    (root / "times.txt").write_text(KITTI_TIMES)
    write_kitti_scans(root, 3)
    assert load_sequence(root).poses is None
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "00.txt").write_text(KITTI_POSES)
    seq = load_sequence(root, require_poses=True)
    np.testing.assert_allclose(seq.poses[2], kitti_matrix(KITTI_POSES.splitlines()[2]) @ seq.calib_Tr)


def test_writer_with_calib_round_trips_lidar_poses(tmp_path: Path) -> None:
    Tr = kitti_matrix(KITTI_CALIB.splitlines()[4].partition(":")[2])
    Tr[:3, :3] = np.linalg.svd(Tr[:3, :3])[0] @ np.linalg.svd(Tr[:3, :3])[2]  # exactly orthonormal
    w = make_sequence(tmp_path / "s", 3, calib_Tr=Tr)
    seq = load_sequence(tmp_path / "s")
    np.testing.assert_allclose(seq.calib_Tr, Tr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(seq.poses, w["poses"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(seq.odometry, w["odom"], rtol=0, atol=1e-6)
    raw = read_poses_txt(tmp_path / "s" / "poses.txt")
    np.testing.assert_allclose(raw @ Tr, w["poses"], rtol=0, atol=1e-6)


# --- interrupted recordings ------------------------------------------------------------------------------


def test_interrupted_write_loads_prefix(tmp_path: Path) -> None:
    root = tmp_path / "s"
    w = SequenceWriter(root, meta={"scene": "x"})
    for k in range(3):
        w.add_frame(np.full((4, 3), k), pose=np.eye(4), time_s=k * 0.1, odometry=np.eye(4))
    # a crash after the fourth scan was renamed into place, and after its poses.txt line, before times.txt
    write_scan_bin(root / "velodyne" / "000003.bin", np.zeros((4, 3)))
    assert load_sequence(root).meta["complete"] is False
    assert len(load_sequence(root)) == 3
    with open(root / "poses.txt", "a") as f:
        f.write(" ".join(["1.0", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"]) + "\n")
    with open(root / "times.txt", "a") as f:
        f.write("0.3")  # half a line, no newline
    seq = load_sequence(root)
    assert len(seq) == 3 and len(seq.poses) == 3 and len(seq.times) == 3 and len(seq.odometry) == 3
    assert seq.scan(2)[0, 0] == 2
    w.close(complete=False)
    # the same folder claiming to be complete is inconsistent
    meta = (root / "meta.yaml").read_text().replace("complete: false", "complete: true")
    (root / "meta.yaml").write_text(meta)
    with pytest.raises(InputError, match=r"odometry\.txt: 3 lines for 4 scans") as exc:
        load_sequence(root)
    one_line(exc)


def test_incomplete_with_two_surplus_scans_is_an_error(tmp_path: Path) -> None:
    root = tmp_path / "s"
    w = SequenceWriter(root)
    w.add_frame(np.zeros((1, 3)), pose=np.eye(4), time_s=0.0)
    write_scan_bin(root / "velodyne" / "000001.bin", np.zeros((1, 3)))
    write_scan_bin(root / "velodyne" / "000002.bin", np.zeros((1, 3)))
    with pytest.raises(InputError, match=r"poses\.txt: 1 lines for 3 scans"):
        load_sequence(root)
    w.close(complete=False)


def test_exception_in_with_block_leaves_complete_false(tmp_path: Path) -> None:
    root = tmp_path / "s"
    with pytest.raises(KeyboardInterrupt), SequenceWriter(root) as w:
        w.add_frame(np.zeros((1, 3)), pose=np.eye(4), time_s=0.0)
        write_scan_bin(root / "velodyne" / "000001.bin", np.zeros((1, 3)))  # half a frame
        raise KeyboardInterrupt
    seq = load_sequence(root)
    assert len(seq) == 1 and seq.meta["complete"] is False


def test_killed_recording_leaves_a_readable_prefix(tmp_path: Path) -> None:
    """SIGKILL a process that records as fast as it can: whatever the moment, the folder loads."""
    root = tmp_path / "s"
    script = textwrap.dedent(
        f"""
        import numpy as np
        from rangemcl.datasets.kitti import SequenceWriter
        rng = np.random.default_rng(0)
        with SequenceWriter({str(root)!r}, meta={{"scene": "x"}}) as w:
            for k in range(100000):
                w.add_frame(rng.normal(size=(200, 3)), pose=np.eye(4), time_s=k * 0.1, odometry=np.eye(4),
                            imu_roll_pitch=[0.0, 0.0], point_meta={{"ring": np.zeros(200, np.uint16)}})
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            poses = root / "poses.txt"
            if poses.exists() and poses.read_text().count("\n") >= 20:
                break
            assert proc.poll() is None, "the recorder died"
            time.sleep(0.01)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    seq = load_sequence(root, require_poses=True)
    # poses.txt had 20 lines; the kill may land before that frame's other lines, which cuts it
    assert len(seq) >= 19 and seq.meta["complete"] is False
    assert len(seq.times) == len(seq.odometry) == len(seq.imu_roll_pitch) == len(seq)
    assert seq.scan(len(seq) - 1).shape == (200, 3)
    assert seq.point_meta(len(seq) - 1)["ring"].shape == (200,)


# --- validation ------------------------------------------------------------------------------------------


def _replace_line(path: Path, k: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[k] = text
    path.write_text("\n".join(lines) + "\n")


def _drop_last_line(path: Path) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:-1]) + "\n")


ROW = "1 0 0 0 0 1 0 0 0 0 1 0"
CORRUPTIONS = {
    "no velodyne": (lambda r: shutil.rmtree(r / "velodyne"), r"seq: no velodyne/"),
    "no bin": (lambda r: [p.unlink() for p in (r / "velodyne").iterdir()], r"velodyne: no \.bin"),
    "scan gap": (lambda r: (r / "velodyne" / "000001.bin").unlink(), r"000001\.bin: missing"),
    "poses 11 numbers": (
        lambda r: _replace_line(r / "poses.txt", 1, "1 0 0 0 0 1 0 0 0 0 1"),
        r"poses\.txt: line 2 has 11 numbers, expected 12",
    ),
    "poses 13 numbers": (
        lambda r: _replace_line(r / "poses.txt", 0, ROW + " 5"),
        r"poses\.txt: line 1 has 13 numbers",
    ),
    "poses non-numeric": (
        lambda r: _replace_line(r / "poses.txt", 2, ROW.replace("0 1 0 0", "0 abc 0 0", 1)),
        r"poses\.txt: line 3: 'abc' is not a number",
    ),
    "poses nan": (
        lambda r: _replace_line(r / "poses.txt", 0, ROW.replace("1 0 0 0", "1 0 nan 0", 1)),
        r"poses\.txt: line 1 has NaN or inf",
    ),
    "poses inf": (
        lambda r: _replace_line(r / "poses.txt", 0, ROW.replace(" 0 1 0", " 0 1 inf", 1)),
        r"poses\.txt: line 1 has NaN or inf",
    ),
    "poses not orthonormal": (
        lambda r: _replace_line(r / "poses.txt", 3, "1.01 0 0 0 0 1 0 0 0 0 1 0"),
        r"poses\.txt: line 4: rotation is not orthonormal",
    ),
    "poses reflection": (
        lambda r: _replace_line(r / "poses.txt", 0, "-1 0 0 0 0 1 0 0 0 0 1 0"),
        r"poses\.txt: line 1: rotation has determinant -1",
    ),
    "poses count": (lambda r: _drop_last_line(r / "poses.txt"), r"poses\.txt: 3 lines for 4 scans"),
    "poses blank line": (
        lambda r: _replace_line(r / "poses.txt", 1, ""),
        r"poses\.txt: line 2 is empty",
    ),
    "odometry count": (lambda r: _drop_last_line(r / "odometry.txt"), r"odometry\.txt: 3 lines for 4 scans"),
    "odometry numbers": (
        lambda r: _replace_line(r / "odometry.txt", 0, "1 0 0"),
        r"odometry\.txt: line 1 has 3 numbers",
    ),
    "odometry not orthonormal": (
        lambda r: _replace_line(r / "odometry.txt", 1, "1 0.1 0 0 0 1 0 0 0 0 1 0"),
        r"odometry\.txt: line 2: rotation is not orthonormal",
    ),
    "times count": (lambda r: _drop_last_line(r / "times.txt"), r"times\.txt: 3 lines for 4 scans"),
    "times extra": (
        lambda r: (r / "times.txt").write_text((r / "times.txt").read_text() + "9.0\n"),
        r"times\.txt: 5 lines for 4 scans",
    ),
    "times decreasing": (
        lambda r: _replace_line(r / "times.txt", 2, "-1.0"),
        r"times\.txt: line 3: time -1 is before",
    ),
    "times non-numeric": (lambda r: _replace_line(r / "times.txt", 0, "zero"), r"times\.txt: line 1: 'zero'"),
    "times nan": (lambda r: _replace_line(r / "times.txt", 0, "nan"), r"times\.txt: line 1 is not finite"),
    "imu count": (lambda r: _drop_last_line(r / "imu.txt"), r"imu\.txt: 3 lines for 4 scans"),
    "imu numbers": (
        lambda r: _replace_line(r / "imu.txt", 1, "0.1 0.2 0.3"),
        r"imu\.txt: line 2 has 3 numbers",
    ),
    "calib without Tr": (
        lambda r: (r / "calib.txt").write_text(KITTI_CALIB.split("Tr:")[0]),
        r"calib\.txt: no 'Tr:' line",
    ),
    "calib Tr 11 numbers": (
        lambda r: (r / "calib.txt").write_text("P0: 1 2 3\nTr: 1 0 0 0 0 1 0 0 0 0 1\n"),
        r"calib\.txt: 'Tr:' on line 2 has 11 numbers, expected 12",
    ),
    "calib Tr not rigid": (
        lambda r: (r / "calib.txt").write_text("Tr: 2 0 0 0 0 1 0 0 0 0 1 0\n"),
        r"calib\.txt: 'Tr:' on line 1: rotation is not orthonormal",
    ),
    "meta malformed": (
        lambda r: (r / "meta.yaml").write_text("scene: [unclosed\n"),
        r"meta\.yaml: malformed YAML",
    ),
    "meta duplicate key": (
        lambda r: (r / "meta.yaml").write_text("a: 1\na: 2\n"),
        r"meta\.yaml: malformed YAML.*duplicate key 'a'",
    ),
    "meta not a mapping": (
        lambda r: (r / "meta.yaml").write_text("- 1\n- 2\n"),
        r"meta\.yaml: expected a mapping",
    ),
}


@pytest.mark.parametrize("case", CORRUPTIONS)
def test_validation_errors_name_the_file(seq_dir: Path, case: str) -> None:
    corrupt, pattern = CORRUPTIONS[case]
    load_sequence(seq_dir)  # valid before
    corrupt(seq_dir)
    with pytest.raises(InputError, match=pattern) as exc:
        load_sequence(seq_dir)
    one_line(exc)


def test_missing_folder_and_file_instead_of_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nowhere: no such sequence folder") as exc:
        load_sequence(tmp_path / "nowhere")
    one_line(exc)
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match=r"f: not a folder"):
        load_sequence(tmp_path / "f")


def test_require_poses(seq_dir: Path) -> None:
    (seq_dir / "poses.txt").unlink()
    assert load_sequence(seq_dir).poses is None
    with pytest.raises(InputError, match=r"poses\.txt: no such file") as exc:
        load_sequence(seq_dir, require_poses=True)
    one_line(exc)


def test_truncated_scan_errors_when_read(seq_dir: Path) -> None:
    path = seq_dir / "velodyne" / "000002.bin"
    path.write_bytes(path.read_bytes() + b"\x00" * 5)
    seq = load_sequence(seq_dir)  # lazily: loading works
    seq.scan(1)
    with pytest.raises(InputError, match=r"000002\.bin: truncated scan"):
        seq.scan(2)


def test_point_meta_length_mismatch(seq_dir: Path) -> None:
    np.savez(seq_dir / "points_meta" / "000001.npz", ring=np.zeros(10**4, np.uint16))
    with pytest.raises(InputError, match=r"000001\.npz: array 'ring' has 10000 values"):
        load_sequence(seq_dir).point_meta(1)
    (seq_dir / "points_meta" / "000000.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"000000\.npz: cannot read"):
        load_sequence(seq_dir).point_meta(0)


def test_read_write_poses_txt(tmp_path: Path) -> None:
    poses, _ = random_poses(np.random.default_rng(5), 7, scale=1e4)
    path = write_poses_txt(tmp_path / "sub" / "traj.txt", poses)
    np.testing.assert_allclose(read_poses_txt(path), poses, rtol=1e-9, atol=0)
    np.testing.assert_allclose(read_poses_txt(write_poses_txt(path, poses[:, :3])), poses, rtol=1e-9, atol=0)
    assert sorted(p.name for p in path.parent.iterdir()) == ["traj.txt"]
    bad = poses.copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"traj\.txt: pose 3"):
        write_poses_txt(path, bad)
    with pytest.raises(InputError, match=r"missing\.txt: no such file"):
        read_poses_txt(tmp_path / "missing.txt")
    assert read_poses_txt(write_poses_txt(tmp_path / "empty.txt", np.zeros((0, 4, 4)))).shape == (0, 4, 4)


# --- writer errors ---------------------------------------------------------------------------------------


def test_writer_refuses_non_empty_folder_and_overwrites(seq_dir: Path) -> None:
    with pytest.raises(InputError, match=r"seq: folder is not empty") as exc:
        SequenceWriter(seq_dir)
    one_line(exc)
    assert len(load_sequence(seq_dir)) == 4  # untouched
    (seq_dir / "notes.md").write_text("mine")
    with SequenceWriter(seq_dir, overwrite=True, meta={"scene": "new"}) as w:
        w.add_frame(np.zeros((3, 3)), pose=np.eye(4), time_s=1.0)
    seq = load_sequence(seq_dir)
    assert len(seq) == 1 and seq.odometry is None and seq.imu_roll_pitch is None
    assert seq.meta == {"scene": "new", "complete": True}
    assert seq.point_meta(0) == {} and not (seq_dir / "points_meta").exists()
    assert (seq_dir / "notes.md").read_text() == "mine"


def test_writer_refuses_to_overwrite_a_non_sequence_folder(tmp_path: Path) -> None:
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"x")
    with pytest.raises(InputError, match=r"photos: folder is not empty and holds no sequence"):
        SequenceWriter(tmp_path / "photos", overwrite=True)
    assert (tmp_path / "photos" / "a.jpg").exists()


def test_writer_into_empty_existing_folder(tmp_path: Path) -> None:
    with SequenceWriter(tmp_path) as w:
        w.add_frame(np.zeros((3, 3)), pose=np.eye(4), time_s=0.0)
    assert len(load_sequence(tmp_path)) == 1


def test_unwritable_output_folder(tmp_path: Path) -> None:
    (tmp_path / "plain_file").write_text("x")
    with pytest.raises(InputError, match=r"plain_file/seq: cannot create the output folder") as exc:
        SequenceWriter(tmp_path / "plain_file" / "seq")
    one_line(exc)
    with pytest.raises(InputError, match=r"plain_file: exists and is not a folder"):
        SequenceWriter(tmp_path / "plain_file")


def test_writer_rejects_bad_frames_without_writing(tmp_path: Path) -> None:
    root = tmp_path / "s"
    with SequenceWriter(root) as w:
        w.add_frame(np.zeros((3, 3)), pose=np.eye(4), time_s=1.0, odometry=np.eye(4))
        bad_frames = {
            r"frame 1: odometry was given with earlier frames": dict(pose=np.eye(4), time_s=2.0),
            r"frame 1: imu was not given with earlier frames": dict(
                pose=np.eye(4), time_s=2.0, odometry=np.eye(4), imu_roll_pitch=[0, 0]
            ),
            r"frame 1: time_s 0\.5 is before": dict(pose=np.eye(4), time_s=0.5, odometry=np.eye(4)),
            r"frame 1: pose: rotation is not orthonormal": dict(
                pose=np.diag([1, 2, 1, 1.0]), time_s=2.0, odometry=np.eye(4)
            ),
            r"frame 1: pose: must have shape": dict(pose=np.eye(3), time_s=2.0, odometry=np.eye(4)),
            r"frame 1: odometry: has NaN": dict(pose=np.eye(4), time_s=2.0, odometry=np.full((4, 4), np.nan)),
            r"frame 1: point_meta 'ring' has 2 values for 3 points": dict(
                pose=np.eye(4), time_s=2.0, odometry=np.eye(4), point_meta={"ring": np.zeros(2)}
            ),
        }
        for pattern, kw in bad_frames.items():
            with pytest.raises(InputError, match=pattern) as exc:
                w.add_frame(np.zeros((3, 3)), **kw)
            one_line(exc)
        with pytest.raises(InputError, match=r"points must have shape \(N, 3\)"):
            w.add_frame(np.zeros((3, 4)), pose=np.eye(4), time_s=2.0, odometry=np.eye(4))
        assert w.add_frame(np.zeros((3, 3)), pose=np.eye(4), time_s=2.0, odometry=np.eye(4)) == 1
    seq = load_sequence(root)
    assert len(seq) == 2 and seq.meta == {"complete": True}
    with pytest.raises(RuntimeError, match="closed"):
        w.add_frame(np.zeros((3, 3)), pose=np.eye(4), time_s=3.0, odometry=np.eye(4))


# --- TUM -------------------------------------------------------------------------------------------------


def test_tum_lines_match_an_independent_conversion() -> None:
    rng = np.random.default_rng(11)
    poses, quats = random_poses(rng, 50)
    times = np.cumsum(rng.uniform(0, 1, 50))
    lines = poses_to_tum(poses, times)
    assert len(lines) == 50
    for line, T, q, t in zip(lines, poses, quats, times, strict=True):
        values = np.array(line.split(), dtype=np.float64)
        assert len(values) == 8 and "\n" not in line
        assert values[0] == pytest.approx(t, abs=1e-9)
        np.testing.assert_allclose(values[1:4], T[:3, 3], rtol=1e-9)
        q_got = values[4:]
        assert q_got[3] >= 0
        sign = 1.0 if np.dot(q_got, q) >= 0 else -1.0
        np.testing.assert_allclose(q_got, sign * q, atol=1e-9)
    assert poses_to_tum(np.zeros((0, 4, 4)), []) == []
    with pytest.raises(InputError, match="2 times for 50 poses"):
        poses_to_tum(poses, times[:2])
