"""Bags in and out: a simulated drive recorded as MCAP, ROS 2 (SQLite) and ROS 1 bags reads back
as the KITTI folder of the same drive (points, per-point times and fields, times, poses, odometry, IMU); an
MCAP written by another library (mcap-ros2-support) reads the same; a localization on the bag gives the
folder's trajectory; bad bags are one line and exit status 2."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rangemcl.datasets.sources import open_source
from rangemcl.localization import LocalizerSettings
from rangemcl.localization.pipeline import RunOptions, localize_sequence
from simbed.record import record

FRAMES = 20


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """The same drive (town_small, seed 8, 4 actors) recorded in every format."""
    root = tmp_path_factory.mktemp("bags")
    out = {}
    for fmt, name in (("kitti", "kitti"), ("mcap", "mcap"), ("rosbag2", "ros2"), ("rosbag1", "ros1.bag")):
        record(
            "town_small", "mapping", "os1-64", root / name, frames=FRAMES, seed=8, variant=1, actors=4,
            progress=False, fmt=fmt,
        )  # fmt: skip
        out[fmt] = root / name
    return out


def assert_same_frames(bag, folder) -> None:
    assert len(bag) == len(folder) == FRAMES
    for i in range(len(folder)):
        p, inten = bag.scan_with_intensity(i)
        q, inten_q = folder.scan_with_intensity(i)
        assert p.dtype == np.float32 and np.array_equal(p, q) and np.array_equal(inten, inten_q)
        a, b = bag.point_meta(i), folder.point_meta(i)
        assert set(a) == set(b) == {"ring", "column", "time_s", "label"}
        for key in b:
            assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key
    assert np.array_equal(bag.times, folder.times)
    # KITTI text keeps 10 significant digits; the bag keeps float64
    assert np.allclose(bag.poses, folder.poses, atol=1e-8, rtol=0)
    if folder.odometry is not None:
        assert np.allclose(bag.odometry, folder.odometry, atol=1e-8, rtol=0)
    if folder.imu_roll_pitch is not None:
        assert np.allclose(bag.imu_roll_pitch, folder.imu_roll_pitch, atol=1e-9, rtol=0)


@pytest.mark.parametrize("fmt", ["mcap", "rosbag2", "rosbag1"])
def test_a_recorded_bag_reads_back_as_the_folder(drives, fmt):
    folder = open_source(drives["kitti"])
    with open_source(drives[fmt]) as bag:
        assert_same_frames(bag, folder)
        assert bag.meta["sensor"] == folder.meta["sensor"] and bag.meta["complete"] is True
        assert bag.meta["scan_stamp"] == "end"
        assert bag.odometry_source.startswith("/odom")
    if fmt == "mcap":  # the .mcap file alone (as Foxglove opens it) reads the same
        with open_source(next(drives[fmt].glob("*.mcap"))) as bag:
            assert len(bag) == FRAMES


def test_the_mcap_is_standard_ros2(drives):
    """Another library's reader (mcap-ros2-support) decodes our MCAP: schemas, CDR, the actors' markers."""
    pytest.importorskip("mcap_ros2")
    from mcap_ros2.reader import read_ros2_messages

    path = next(drives["mcap"].glob("*.mcap"))
    seen: dict[str, int] = {}
    for m in read_ros2_messages(str(path)):
        seen[m.channel.topic] = seen.get(m.channel.topic, 0) + 1
        if m.channel.topic == "/points" and seen["/points"] == 1:
            names = [f.name for f in m.ros_msg.fields]
            assert names[:4] == ["x", "y", "z", "intensity"] and "time" in names and "ring" in names
        if m.channel.topic == "/actors" and seen["/actors"] == 1:
            assert len(m.ros_msg.markers) == 4
    assert seen["/points"] == seen["/odom"] == seen["/imu"] == seen["/ground_truth"] == FRAMES
    assert seen["/tf_static"] == 1 and seen["/simbed/meta"] == 1


def _write_with_mcap_ros2(folder_path, out, *, odom_imu: bool = False) -> None:
    """The folder as an MCAP written by mcap-ros2-support: PointCloud2 (fields in another order, with
    padding), TF static mount, ground truth on ``/gt``; with ``odom_imu`` also the folder's odometry on
    ``/wheel/odom`` and its IMU roll and pitch on ``/imu/data`` (names no default picks)."""
    from mcap_ros2.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    from rangemcl.datasets.rosbag import stamp_ns
    from rangemcl.se2 import quat_from_matrix

    ts = get_typestore(Stores.ROS2_HUMBLE)

    def schema(w, name):
        text, _ = ts.generate_msgdef(name, ros_version=2)
        return w.register_msgdef(name, text)

    seq = open_source(folder_path)
    with open(out, "wb") as fh:
        w = Writer(fh)
        s_pc, s_tf, s_odo, s_imu = (
            schema(w, n)
            for n in (
                "sensor_msgs/msg/PointCloud2",
                "tf2_msgs/msg/TFMessage",
                "nav_msgs/msg/Odometry",
                "sensor_msgs/msg/Imu",
            )
        )
        for i in range(len(seq)):
            ns = stamp_ns(seq.times[i])
            stamp = {"sec": ns // 10**9, "nanosec": ns % 10**9}
            pts, inten = seq.scan_with_intensity(i)
            meta = seq.point_meta(i)
            # ring first, then a float64 time, x y z later, 3 bytes of padding per point
            dt = np.dtype(
                {
                    "names": ["ring", "time", "x", "y", "z", "intensity", "column", "label"],
                    "formats": ["<u2", "<f8", "<f4", "<f4", "<f4", "<f4", "<u2", "u1"],
                    "offsets": [0, 2, 10, 14, 18, 22, 26, 28],
                    "itemsize": 32,
                }
            )
            rec = np.zeros(len(pts), dt)
            rec["x"], rec["y"], rec["z"] = pts.T
            rec["intensity"], rec["ring"], rec["column"], rec["label"] = (
                inten, meta["ring"], meta["column"], meta["label"],
            )  # fmt: skip
            rec["time"] = meta["time_s"]
            codes = {"<u2": 4, "<f8": 8, "<f4": 7, "|u1": 2}
            fields = [
                {"name": n, "offset": dt.fields[n][1], "datatype": codes[dt.fields[n][0].str], "count": 1}
                for n in dt.names
            ]
            msg = {
                "header": {"stamp": stamp, "frame_id": "velodyne"},
                "height": 1, "width": len(pts), "fields": fields, "is_bigendian": False, "point_step": 32,
                "row_step": 32 * len(pts), "data": rec.tobytes(), "is_dense": True,
            }  # fmt: skip
            w.write_message("/velodyne_points", s_pc, msg, log_time=ns, publish_time=ns)

            def odometry(T, frame, stamp=stamp):
                q = quat_from_matrix(T[:3, :3])
                pose = {
                    "position": dict(zip("xyz", T[:3, 3].tolist(), strict=True)),
                    "orientation": dict(zip("xyzw", q.tolist(), strict=True)),
                }
                zero = {"x": 0, "y": 0, "z": 0}
                return {
                    "header": {"stamp": stamp, "frame_id": frame},
                    "child_frame_id": "base_link",
                    "pose": {"pose": pose, "covariance": [0.0] * 36},
                    "twist": {"twist": {"linear": zero, "angular": zero}, "covariance": [0.0] * 36},
                }

            w.write_message("/gt", s_odo, odometry(seq.poses[i], "map"), log_time=ns, publish_time=ns)
            if odom_imu:
                odo = odometry(seq.odometry[i], "odom")
                w.write_message("/wheel/odom", s_odo, odo, log_time=ns, publish_time=ns)
                roll, pitch = seq.imu_roll_pitch[i]
                cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
                R = np.array([[cp, sp * sr, sp * cr], [0, cr, -sr], [-sp, cp * sr, cp * cr]])  # Ry @ Rx
                q = quat_from_matrix(R)
                vec = {"x": 0.0, "y": 0.0, "z": 0.0}
                imu = {
                    "header": {"stamp": stamp, "frame_id": "base_link"},
                    "orientation": dict(zip("xyzw", q.tolist(), strict=True)),
                    "orientation_covariance": [1e-6, 0, 0, 0, 1e-6, 0, 0, 0, 1e3],
                    "angular_velocity": vec,
                    "angular_velocity_covariance": [-1.0] + [0.0] * 8,
                    "linear_acceleration": vec,
                    "linear_acceleration_covariance": [0.0] * 9,
                }
                w.write_message("/imu/data", s_imu, imu, log_time=ns, publish_time=ns)
            if i == 0:
                identity = {
                    "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                }
                tf = {"header": {"stamp": stamp, "frame_id": "base_link"}, "child_frame_id": "velodyne"}
                w.write_message(
                    "/tf_static", s_tf, {"transforms": [tf | {"transform": identity}]}, log_time=ns
                )
        w.finish()


def test_an_mcap_from_another_writer_reads_as_the_folder(drives, tmp_path):
    pytest.importorskip("mcap_ros2")
    from rangemcl.datasets.rosbag import BagOptions

    path = tmp_path / "other.mcap"
    _write_with_mcap_ros2(drives["kitti"], path)
    folder = open_source(drives["kitti"])
    with open_source(path, bag_options=BagOptions(truth_topic="/gt")) as bag:
        assert bag.topic == "/velodyne_points" and bag.odometry is None
        assert len(bag) == FRAMES
        for i in range(FRAMES):
            assert np.array_equal(bag.scan(i), folder.scan(i))
            a, b = bag.point_meta(i), folder.point_meta(i)
            assert np.array_equal(a["time_s"], b["time_s"]) and np.array_equal(a["ring"], b["ring"])
        assert np.array_equal(bag.times, folder.times)
        assert np.allclose(bag.poses, folder.poses, atol=1e-8, rtol=0)


def test_localizing_the_bag_gives_the_folders_trajectory(drives, small_town_map, tmp_path):
    _, map_dir = small_town_map
    s = LocalizerSettings()
    s.observation.rays = 200
    runs = {}
    for fmt in ("kitti", "mcap"):
        out = tmp_path / fmt
        localize_sequence(
            drives[fmt], map_dir, out, s, RunOptions(mode="tracking", seed=4, threads=2, plots=False)
        )
        runs[fmt] = np.loadtxt(out / "estimate_kitti.txt")
        summary = json.loads((out / "summary.json").read_text())
    assert runs["kitti"].shape == (FRAMES, 12)
    assert np.allclose(runs["mcap"], runs["kitti"], atol=1e-6, rtol=0)
    assert summary["odometry_source"].startswith("/odom")


def test_localize_with_every_topic_option(drives, small_town_map, tmp_path):
    """``rangemcl localize`` with every bag option that names a topic, on a bag written by rosbags (our
    recorder) and on one written by mcap-ros2-support whose topics no default would pick: both finish with
    their summary and metrics, the options recorded in the summary, and the trajectory of the KITTI folder
    of the same drive (the named topics are read, not the defaults)."""
    pytest.importorskip("mcap_ros2")
    _, map_dir = small_town_map
    other = tmp_path / "other.mcap"
    _write_with_mcap_ros2(drives["kitti"], other, odom_imu=True)
    cfg = tmp_path / "rays.yaml"
    cfg.write_text("observation:\n  rays: 200\n")
    start = open_source(drives["kitti"]).poses[0]
    pose = f"{start[0, 3]},{start[1, 3]},{np.arctan2(start[1, 0], start[0, 0])}"
    common = ["--map", map_dir, "--mode", "tracking", "--seed", "4", "--threads", "2", "--no-plots"]
    common += ["--config", cfg, "--init-pose", pose]
    topics = {
        drives["rosbag2"]: ("/points", "/odom", "/imu", "/ground_truth"),
        other: ("/velodyne_points", "/wheel/odom", "/imu/data", "/gt"),
    }
    estimates = []
    for bag, (lidar, odom, imu, truth) in topics.items():
        out = tmp_path / f"run_{bag.stem}"
        named = ["--lidar-topic", lidar, "--odom-topic", odom, "--imu-topic", imu, "--truth-topic", truth]
        r = _cli("localize", bag, "--out", out, *common, *named)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
        summary = json.loads((out / "summary.json").read_text())
        assert summary["frames"] == FRAMES and summary["odometry_source"].startswith(odom)
        assert summary["options"]["bag"]["lidar_topic"] == lidar
        assert summary["options"]["bag"]["imu_topic"] == imu
        assert summary["options"]["bag"]["truth_topic"] == truth
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["success"] and metrics["location_rmse_m"] < 0.1
        estimates.append(np.loadtxt(out / "estimate_kitti.txt"))
    # the same scans, odometry, roll and pitch through two writers: the same estimates
    assert np.allclose(estimates[0], estimates[1], atol=1e-4, rtol=0)


def _cli(*args):
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True)


def test_bad_bags_are_one_line(drives, small_town_map, tmp_path):
    _, map_dir = small_town_map
    bag = drives["rosbag1"]
    cases = {
        "no topic /scan (LiDAR scans); the bag has: /actors (MarkerArray, 20), /ground_truth": (
            bag,
            "--lidar-topic",
            "/scan",
        ),
        "topic /imu holds sensor_msgs/msg/Imu, not sensor_msgs/msg/PointCloud2": (
            bag,
            "--lidar-topic",
            "/imu",
        ),
    }
    # a bag without any PointCloud2
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    empty = tmp_path / "strings.bag"
    with Writer(empty) as w:
        con = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        msg = ts.types["std_msgs/msg/String"](data="hi")
        w.write(con, 10**9, ts.serialize_ros1(msg, "std_msgs/msg/String"))
    cases["no sensor_msgs/PointCloud2 topic; the bag has: /chatter (String, 1)"] = (empty,)
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    cases["cannot read the bag"] = (truncated,)
    mc = next(drives["mcap"].glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mc.read_bytes()[: mc.stat().st_size // 3])
    cases["cannot read the bag "] = (cut,)
    for expected, (path, *extra) in cases.items():
        out = tmp_path / f"out{len(extra)}{path.stem}"
        r = _cli("localize", path, "--map", map_dir, "--out", out, "--mode", "tracking", *extra)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert expected.strip() in lines[0] and str(path) in lines[0], lines[0]
        assert not out.exists()


def _ouster_like_bag(path, frames=4):
    """A ROS 2 bag of start-stamped scans with Ouster's ``t`` (uint32 ns after the stamp), no TF."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(0)
    with Writer(path, version=9) as w:
        con = w.add_connection("/os_cloud_node/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for k in range(frames):
            ns = 5 * 10**9 + k * 100_000_000
            n = 1000
            dt = np.dtype(
                {
                    "names": ["x", "y", "z", "t", "ring"],
                    "formats": ["<f4", "<f4", "<f4", "<u4", "<u2"],
                    "offsets": [0, 4, 8, 16, 20],
                    "itemsize": 24,
                }
            )
            rec = np.zeros(n, dt)
            rec["x"], rec["y"], rec["z"] = rng.normal(0, 10, (3, n)).astype(np.float32)
            rec["t"] = np.linspace(0, 99_000_000, n).astype(np.uint32)
            fields = [T["sensor_msgs/msg/PointField"](name=nm, offset=dt.fields[nm][1], datatype=d, count=1)
                      for nm, d in (("x", 7), ("y", 7), ("z", 7), ("t", 6), ("ring", 4))]  # fmt: skip
            stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="os_sensor"),
                height=1, width=n, fields=fields, is_bigendian=False, point_step=24, row_step=24 * n,
                data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True,
            )  # fmt: skip
            w.write(con, ns, ts.serialize_cdr(msg, msg.__msgtype__))


def test_start_stamped_scans_and_the_mount(tmp_path):
    from rangemcl.datasets.rosbag import BagOptions
    from rangemcl.errors import InputError

    path = tmp_path / "ouster"
    _ouster_like_bag(path)
    with pytest.raises(
        InputError, match=r"no static transform from base_link to the scans' frame 'os_sensor'"
    ):
        open_source(path)
    opts = BagOptions(sensor_to_base=(0.1, 0, 1.8, 0, 0, 90))
    with open_source(path, bag_options=opts) as bag:
        assert bag.meta["scan_stamp"] == "start"
        assert np.allclose(bag.times, 5.099 + 0.1 * np.arange(4))  # moved to the sweep's end
        t = bag.point_meta(2)["time_s"]
        assert t.dtype == np.float32 and np.isclose(t.min(), -0.099) and t.max() == 0
        assert bag.meta["sensor_to_base"]["xyz_m"] == [0.1, 0.0, 1.8]
        assert bag.poses is None and bag.odometry is None
    with open_source(
        path, bag_options=BagOptions(sensor_to_base=(0, 0, 0, 0, 0, 0), scan_stamp="end")
    ) as bag:
        assert np.allclose(bag.times, 5.0 + 0.1 * np.arange(4))
        assert bag.point_meta(0)["time_s"].max() > 0.09


def test_convert_round_trip_and_a_folder_without_metadata(drives, tmp_path):
    import shutil

    from rangemcl.datasets.convert import convert

    folder = open_source(drives["kitti"])
    assert convert(drives["kitti"], tmp_path / "a.bag", "rosbag1") == FRAMES
    assert convert(tmp_path / "a.bag", tmp_path / "back", "kitti") == FRAMES
    with open_source(tmp_path / "a.bag") as bag:
        assert_same_frames(bag, folder)
    back = open_source(tmp_path / "back")
    assert_same_frames(back, folder)
    assert back.meta["sensor"] == folder.meta["sensor"] and back.meta["converted_from"].endswith("a.bag")
    # a ROS 2 bag folder whose metadata.yaml is missing (it is written last) opens by its storage file
    shutil.copytree(drives["mcap"], tmp_path / "nometa")
    (tmp_path / "nometa" / "metadata.yaml").unlink()
    with open_source(tmp_path / "nometa") as bag:
        assert len(bag) == FRAMES
    r = _cli("convert", drives["kitti"], "--out", tmp_path / "a.bag", "--format", "rosbag1")
    assert r.returncode == 2 and "exists (give --overwrite to replace the bag)" in r.stderr


def test_kiss_icp_odometry_for_a_bag_without_wheel_odometry(drives, small_town_map, tmp_path):
    pytest.importorskip("kiss_icp")
    _, map_dir = small_town_map
    s = LocalizerSettings()
    s.observation.rays = 200
    out = tmp_path / "kiss"
    summary = localize_sequence(
        drives["mcap"], map_dir, out, s,
        RunOptions(mode="tracking", seed=4, threads=2, plots=False, odometry="kiss-icp"),
    )  # fmt: skip
    assert summary["odometry_source"].startswith("kiss-icp")
    kiss = np.loadtxt(out / "odometry_kiss_icp.txt")
    assert kiss.shape == (FRAMES, 12) and np.all(np.isfinite(kiss))
    # kiss-icp's first metres on this street slide along it (up to 1 m in 20 frames, straight facades; its
    # drift over 300 frames is measured in tests/rangemcl/datasets/test_lidar_odometry.py): the filter
    # holds on
    m = json.loads((out / "metrics.json").read_text())
    assert m["success"] and m["location_rmse_m"] < 0.25


def test_viz_out_writes_a_run_that_rerun_reads_back(drives, small_town_map, tmp_path):
    """``rangemcl localize --viz-out`` (in process: the options it sets) writes an .rrd whose frames
    rerun's own reader gives back: the map once, one error value per frame, equal to frames.csv's."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    _, map_dir = small_town_map
    s = LocalizerSettings()
    s.observation.rays = 200
    out, rrd = tmp_path / "run", tmp_path / "run.rrd"
    localize_sequence(
        drives["mcap"], map_dir, out, s,
        RunOptions(mode="tracking", seed=4, threads=2, plots=False, viz_out=str(rrd)),
    )  # fmt: skip
    frames, errors, static = [], [], set()
    for chunk in RrdReader(rrd).stream().to_chunks():
        if chunk.is_static:
            static.add(chunk.entity_path)
        rb = chunk.to_record_batch()
        if chunk.entity_path == "/metrics/error_m" and not chunk.is_static and "frame" in rb.schema.names:
            col = next(n for n in rb.schema.names if n.endswith("Scalars:scalars"))
            frames += rb.column("frame").to_pylist()
            errors += [v[0] for v in rb.column(col).to_pylist()]
    assert "/world/map" in static
    assert sorted(frames) == list(range(FRAMES))
    truth = open_source(drives["kitti"]).poses[:, :2, 3]
    est = np.loadtxt(out / "estimate_kitti.txt").reshape(-1, 3, 4)[:, :2, 3]
    want = np.linalg.norm(est - truth, axis=1)
    got = np.array(errors)[np.argsort(frames)]
    assert np.allclose(got, want, atol=1e-3)


def test_a_map_built_from_the_bag_is_the_folders(drives, tmp_path):
    """build-map reads the bag through the same loader: the mesh is the folder's (the poses differ by the
    folder's text rounding, 1e-10 m: vertices agree within 0.1 mm, a few of 9,000 faces flip in the
    ground simplification)."""
    from rangemcl.mapping.pipeline import MapSettings, build_map
    from rangemcl.maps.meshmap import MeshMap

    s = MapSettings()
    s.poisson.depth = 7
    s.workers = 1
    s.scans.every_nth = 4
    meshes = {}
    for fmt in ("kitti", "rosbag2"):
        build_map(drives[fmt], tmp_path / fmt, s)
        meshes[fmt] = MeshMap.load(tmp_path / fmt)
    a, b = meshes["kitti"], meshes["rosbag2"]
    assert a.n_triangles > 1000 and a.faces.shape == b.faces.shape
    assert np.allclose(a.vertices, b.vertices, atol=1e-4, rtol=0)
    assert np.any(a.faces != b.faces, axis=1).mean() < 0.005
