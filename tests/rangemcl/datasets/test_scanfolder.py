"""A folder of .pcd/.ply scans as a sequence: natural order, times from the names or times.txt, poses.txt,
extra fields kept (time -> time_s), NaN/zero points dropped, bad files one line."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from rangemcl.datasets.kitti import write_poses_txt
from rangemcl.datasets.sources import open_source
from rangemcl.errors import InputError


def write_cloud(path, points, **fields):
    pc = o3d.t.geometry.PointCloud()
    pc.point["positions"] = o3d.core.Tensor(np.asarray(points, np.float32))
    for k, v in fields.items():
        pc.point[k] = o3d.core.Tensor(np.asarray(v).reshape(-1, 1))
    o3d.t.io.write_point_cloud(str(path), pc)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_a_folder_of_scans(tmp_path, suffix):
    rng = np.random.default_rng(1)
    scans, poses = [], []
    for k in (2, 10, 1):  # natural order: 1, 2, 10
        pts = rng.normal(0, 10, (100, 3)).astype(np.float32)
        pts[5] = np.nan
        pts[6] = 0
        t = np.linspace(-0.1, 0, 100).astype(np.float32)
        write_cloud(tmp_path / f"{k}{suffix}", pts, intensity=np.full(100, k, np.float32), time=t)
        scans.append((k, pts, t))
    for k in (1, 2, 10):
        T = np.eye(4)
        T[0, 3] = k
        poses.append(T)
    write_poses_txt(tmp_path / "poses.txt", np.array(poses))
    seq = open_source(tmp_path)
    assert len(seq) == 3 and [p.stem for p in seq.scan_paths] == ["1", "2", "10"]
    assert np.array_equal(seq.times, [1.0, 2.0, 10.0]) and seq.meta["scan_times"] == "the file names"
    assert np.array_equal(seq.poses[:, 0, 3], [1, 2, 10])
    by_name = {k: (p, t) for k, p, t in scans}
    for i, k in enumerate((1, 2, 10)):
        p, t = by_name[k]
        keep = np.ones(100, bool)
        keep[[5, 6]] = False
        pts, inten = seq.scan_with_intensity(i)
        assert np.array_equal(pts, p[keep]) and np.all(inten == k)
        assert np.array_equal(seq.point_meta(i)["time_s"], t[keep])


def test_times_file_and_bad_scans(tmp_path):
    write_cloud(tmp_path / "a.pcd", np.ones((3, 3)))
    write_cloud(tmp_path / "b.pcd", np.ones((3, 3)))
    seq = open_source(tmp_path)
    assert seq.meta["scan_times"] == "none: 10 Hz assumed" and np.allclose(seq.times, [0, 0.1])
    (tmp_path / "times.txt").write_text("5.0\n4.0\n")
    with pytest.raises(InputError, match=r"b\.pcd's time is not after the previous one"):
        open_source(tmp_path)
    (tmp_path / "times.txt").write_text("5.0\n5.5\n")
    assert np.array_equal(open_source(tmp_path).times, [5.0, 5.5])
    (tmp_path / "b.pcd").write_text("not a point cloud")
    with pytest.raises(InputError, match=r"b.pcd: cannot read the scan") as err:
        open_source(tmp_path).scan(1)
    assert "\n" not in str(err.value)
    with pytest.raises(InputError, match="no poses"):
        open_source(tmp_path, require_poses=True)


def test_every_reader_is_a_frame_source(tmp_path):
    """The KITTI folder, a scan folder and a bag all give what :class:`rangemcl.datasets.sources.FrameSource`
    promises (attributes and methods), through the one way in, ``open_source``."""
    pytest.importorskip("rosbags")
    from rangemcl.datasets.convert import convert
    from rangemcl.datasets.kitti import SequenceWriter
    from rangemcl.datasets.sources import FrameSource, open_source

    kitti = tmp_path / "kitti"
    with SequenceWriter(kitti) as w:
        for k in range(3):
            w.add_frame(np.ones((10, 3), np.float32) * (k + 1), pose=np.eye(4), time_s=0.1 * k)
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        write_cloud(folder / f"{k:03d}.pcd", np.ones((10, 3)) * (k + 1))
    convert(kitti, tmp_path / "drive.bag", "rosbag1")
    for path in (kitti, folder, tmp_path / "drive.bag"):
        seq = open_source(path)
        assert isinstance(seq, FrameSource), path
        assert len(seq) == 3 and len(seq.scan_paths) == 3
        points, intensity = seq.scan_with_intensity(1)
        assert points.dtype == np.float32 and points.shape[1] == 3 and len(intensity) == len(points)
        assert np.array_equal(seq.scan(1), points) and isinstance(seq.point_meta(1), dict)
        assert seq.calib_Tr.shape == (4, 4) and isinstance(seq.calib_source, str)
        close = getattr(seq, "close", None)
        if close is not None:
            close()
