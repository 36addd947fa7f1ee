"""PointCloud2 decoding field by field against clouds packed independently here with numpy structured
arrays: any field order, padding inside points and at row ends, float64 and integer coordinates, big-endian,
``count > 1``, no time field; NaN and all-zero points dropped with their other fields; bad layouts are one
``InputError``. And the per-point time conventions of the common drivers."""

from __future__ import annotations

import re

import numpy as np
import pytest

from rangemcl.datasets import pointcloud2 as pc2
from rangemcl.errors import InputError

CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def pack(columns: dict[str, np.ndarray], offsets: dict[str, int], point_step: int, big: bool = False):
    """A payload and its fields, written by numpy's own structured dtype."""
    order = ">" if big else "<"
    names = list(columns)
    dt = np.dtype(
        {
            "names": names,
            "formats": [order + columns[n].dtype.str[1:] for n in names],
            "offsets": [offsets[n] for n in names],
            "itemsize": point_step,
        }
    )
    n = len(next(iter(columns.values())))
    rec = np.zeros(n, dt)
    for k in names:
        rec[k] = columns[k]
    fields = [pc2.PointField(k, offsets[k], CODES[columns[k].dtype.str[1:]]) for k in names]
    return fields, rec.tobytes()


def cloud(rng, n=50):
    xyz = rng.normal(0, 10, (n, 3))
    return {
        "x": xyz[:, 0],
        "y": xyz[:, 1],
        "z": xyz[:, 2],
        "intensity": rng.uniform(0, 255, n).astype(np.float32),
        "ring": rng.integers(0, 128, n).astype(np.uint16),
        "t": rng.integers(0, 100_000_000, n).astype(np.uint32),
    }


@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("coords", ["f4", "f8", "i2"])
def test_any_order_padding_and_byte_order(big, coords):
    rng = np.random.default_rng(3)
    c = cloud(rng)
    for k in "xyz":
        c[k] = (c[k] * (100 if coords == "i2" else 1)).astype(coords)
    # fields in another order, a gap of 3 bytes after the ring, 5 bytes of padding at the end
    names = ["ring", "t", "intensity", "z", "y", "x"]
    offsets, off = {}, 0
    for name in names:
        offsets[name] = off
        off += c[name].dtype.itemsize + (3 if name == "ring" else 0)
    step = off + 5
    fields, data = pack({k: c[k] for k in names}, offsets, step, big)
    out = pc2.decode(fields, data, width=50, height=1, point_step=step, row_step=50 * step, is_bigendian=big)
    want = np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float32)
    assert out.points.dtype == np.float32 and np.array_equal(out.points, want)
    assert np.array_equal(out.intensity, c["intensity"])
    assert out.fields["ring"].dtype == np.uint16 and np.array_equal(out.fields["ring"], c["ring"])
    assert out.fields["t"].dtype.byteorder in ("=", "|") and np.array_equal(out.fields["t"], c["t"])


def test_row_padding_and_organized_clouds():
    rng = np.random.default_rng(4)
    c = cloud(rng, 40)
    names = ["x", "y", "z", "intensity"]
    f32 = {k: c[k].astype(np.float32) for k in names}
    fields, data = pack(f32, {"x": 0, "y": 4, "z": 8, "intensity": 12}, 16)
    rows = np.frombuffer(data, np.uint8).reshape(4, 10 * 16)  # 4 rows of 10 points, 8 padding bytes each
    padded = np.concatenate([rows, np.full((4, 8), 0xAB, np.uint8)], axis=1).tobytes()
    out = pc2.decode(fields, padded, width=10, height=4, point_step=16, row_step=168, is_bigendian=False)
    assert np.array_equal(out.points, np.stack([f32["x"], f32["y"], f32["z"]], 1))


def test_nan_and_zero_points_are_dropped_with_their_fields():
    xyz = np.array([[1, 2, 3], [np.nan, 0, 0], [0, 0, 0], [4, np.inf, 1], [5, 6, 7]], np.float32)
    ring = np.arange(5, dtype=np.uint16)
    t = np.linspace(-0.1, 0, 5).astype(np.float32)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "ring": ring, "time": t}
    fields, data = pack(cols, {"x": 0, "y": 4, "z": 8, "ring": 12, "time": 14}, 18)
    out = pc2.decode(fields, data, width=5, height=1, point_step=18, row_step=90, is_bigendian=False)
    assert np.array_equal(out.points, xyz[[0, 4]]) and out.dropped == 3
    assert np.array_equal(out.fields["ring"], [0, 4]) and np.array_equal(out.fields["time"], t[[0, 4]])
    assert np.array_equal(out.intensity, np.zeros(2, np.float32))  # no intensity field: zeros


def test_count_and_unnamed_and_repeated_fields():
    dt = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", ("<u1", (3,))],
                   "offsets": [0, 4, 8, 12], "itemsize": 16})  # fmt: skip
    rec = np.zeros(3, dt)
    rec["x"] = [1, 2, 3]
    rec["rgb"] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    fields = [pc2.PointField("x", 0, 7), pc2.PointField("y", 4, 7), pc2.PointField("z", 8, 7),
              pc2.PointField("rgb", 12, 2, 3), pc2.PointField("x", 4, 7)]  # fmt: skip
    out = pc2.decode(fields, rec.tobytes(), width=3, height=1, point_step=16, row_step=48, is_bigendian=False)
    assert out.fields["rgb"].shape == (3, 3) and out.fields["rgb"][2].tolist() == [7, 8, 9]
    assert out.points[:, 0].tolist() == [1, 2, 3]  # the first "x" counts


def test_encode_then_decode_keeps_dtypes():
    rng = np.random.default_rng(5)
    pts = rng.normal(0, 5, (30, 3)).astype(np.float32)
    extra = {
        "intensity": rng.uniform(0, 1, 30).astype(np.float32),
        "ring": np.arange(30, dtype=np.uint16),
        "label": (np.arange(30) % 2).astype(np.uint8),
        "time": np.linspace(-0.1, 0, 30).astype(np.float32),
    }
    fields, data, step = pc2.encode(pts, extra)
    assert step == 12 + 4 + 2 + 1 + 4
    out = pc2.decode(
        fields, data, width=30, height=1, point_step=step, row_step=step * 30, is_bigendian=False
    )
    assert np.array_equal(out.points, pts) and np.array_equal(out.intensity, extra["intensity"])
    for k in ("ring", "label", "time"):
        assert out.fields[k].dtype == extra[k].dtype and np.array_equal(out.fields[k], extra[k])


@pytest.mark.parametrize(
    "change, message",
    [
        ({"datatype": 9}, "unknown datatype 9"),
        ({"offset": 14}, "does not fit a point of 16 bytes"),
        ({"name": "w"}, "no x field (fields: w, y, z)"),
    ],
)
def test_bad_fields_are_one_line(change, message):
    fields = [pc2.PointField("x", 0, 7), pc2.PointField("y", 4, 7), pc2.PointField("z", 8, 7)]
    fields[0] = pc2.PointField(**{**fields[0].__dict__, **change})
    with pytest.raises(InputError, match=re.escape(message)) as err:
        pc2.decode(fields, bytes(48), width=3, height=1, point_step=16, row_step=48, is_bigendian=False,
                   where="bag: /points scan 7")  # fmt: skip
    assert str(err.value).startswith("bag: /points scan 7: ") and "\n" not in str(err.value)


def test_short_data_and_short_rows():
    fields = [pc2.PointField("x", 0, 7), pc2.PointField("y", 4, 7), pc2.PointField("z", 8, 7)]
    with pytest.raises(InputError, match=r"40 bytes of data for 1 x 4 points \(48 needed\)"):
        pc2.decode(fields, bytes(40), width=4, height=1, point_step=12, row_step=48, is_bigendian=False)
    with pytest.raises(InputError, match="row_step 40 is shorter"):
        pc2.decode(fields, bytes(48), width=4, height=1, point_step=12, row_step=40, is_bigendian=False)


def test_point_time_conventions():
    stamp = 1_700_000_000.25
    # Ouster: uint32 ns after the stamp (the sweep's start)
    assert np.allclose(pc2.point_times(np.array([0, 50_000_000], np.uint32), stamp), [0, 0.05])
    # Velodyne: float seconds relative to the stamp (its end by default)
    assert np.allclose(pc2.point_times(np.array([-0.1, 0.0], np.float32), stamp), [-0.1, 0], atol=1e-7)
    # Hesai: absolute float64 seconds
    assert np.allclose(pc2.point_times(np.array([stamp - 0.1, stamp]), stamp), [-0.1, 0], atol=1e-6)
    # Livox: absolute float64 nanoseconds
    assert np.allclose(
        pc2.point_times(np.array([stamp * 1e9 - 1e8, stamp * 1e9]), stamp), [-0.1, 0], atol=1e-6
    )
    with pytest.raises(InputError, match="point time unit 'ms'"):
        pc2.point_times(np.zeros(3), stamp, unit="ms")
    assert pc2.find_time_field({"ring": np.zeros(2), "timestamp": np.zeros(2)}) == "timestamp"
    assert pc2.find_time_field({"ring": np.zeros(2)}) is None
