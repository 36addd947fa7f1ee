"""``sensor_msgs/PointCloud2`` to arrays and back, field by field, in plain numpy (no ROS install).

Decoding builds one structured dtype from the message's fields (any point step, any field order, padding,
either byte order, ``count > 1``), views the payload through it (row padding removed first), and returns
x, y, z as float32 with the points that have a non-finite or an all-zero position dropped, and the same
points of every other field. Encoding writes the arrays given, in their own dtypes, packed in order.

Per-point time fields follow each driver's convention; :func:`point_times` turns them into seconds relative
to the message's stamp (see its docstring), which is what the readers need to de-skew.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rangemcl.errors import InputError

# sensor_msgs/PointField datatypes
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_CODES = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "i2",
    UINT16: "u2",
    INT32: "i4",
    UINT32: "u4",
    FLOAT32: "f4",
    FLOAT64: "f8",
}
_DATATYPE_OF = {np.dtype(code).str[1:]: dt for dt, code in _CODES.items()}

INTENSITY_FIELDS = ("intensity", "signal", "reflectivity")
TIME_FIELDS = ("t", "time", "timestamp", "time_stamp", "offset_time")


@dataclass(frozen=True)
class PointField:
    """One ``sensor_msgs/PointField``: ``datatype`` is 1..8 (INT8 .. FLOAT64)."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class Cloud:
    """A decoded cloud: ``points`` ``(M, 3)`` float32, ``intensity`` ``(M,)`` float32 (zeros when the
    cloud has none of ``intensity``/``signal``/``reflectivity``), and every other field in ``fields`` (native
    byte order, the message's own dtype, ``(M,)`` or ``(M, count)``)."""

    points: np.ndarray
    intensity: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    dropped: int = 0  # points without a finite, non-zero position


def decode(
    fields: list[PointField] | list,
    data,
    *,
    width: int,
    height: int,
    point_step: int,
    row_step: int,
    is_bigendian: bool,
    where: str = "PointCloud2",
) -> Cloud:
    """Decode a PointCloud2 payload. ``fields`` are :class:`PointField` or any objects with ``name``,
    ``offset``, ``datatype`` and ``count`` (a deserialized message's). Any problem is an
    :class:`InputError` starting with ``where``."""
    order = ">" if is_bigendian else "<"
    names, formats, offsets = [], [], []
    for k, f in enumerate(fields):
        code = _CODES.get(int(f.datatype))
        if code is None:
            raise InputError(f"{where}: field {f.name!r} has an unknown datatype {f.datatype}")
        count = int(f.count) if int(f.count) > 0 else 1
        name = str(f.name) or f"_unnamed_{k}"
        if name in names:
            continue  # a repeated name: the first one counts
        size = np.dtype(code).itemsize * count
        if int(f.offset) < 0 or int(f.offset) + size > point_step:
            raise InputError(
                f"{where}: field {name!r} (offset {f.offset}, {size} bytes) does not fit a point of "
                f"{point_step} bytes"
            )
        names.append(name)
        formats.append(order + code if count == 1 else (order + code, (count,)))
        offsets.append(int(f.offset))
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise InputError(f"{where}: no {'/'.join(missing)} field (fields: {', '.join(names) or 'none'})")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    width, height, row_step = int(width), int(height), int(row_step)
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
    n = width * height
    if n == 0:
        return Cloud(np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    if row_step < width * point_step:
        raise InputError(f"{where}: row_step {row_step} is shorter than width x point_step")
    need = (height - 1) * row_step + width * point_step
    if len(buf) < need:
        raise InputError(f"{where}: {len(buf)} bytes of data for {height} x {width} points ({need} needed)")
    if row_step == width * point_step:
        rows = buf[: n * point_step]
    else:  # padding at the end of each row
        rows = np.ascontiguousarray(
            buf[: height * row_step].reshape(height, row_step)[:, : width * point_step]
        )
    rec = rows.view(dtype).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    if xyz.ndim != 2:  # x with count > 1
        raise InputError(f"{where}: x, y and z must be single values per point")
    xyz = xyz.astype(np.float32)
    keep = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0, axis=1)
    out = {}
    for name in names:
        if name in ("x", "y", "z"):
            continue
        a = rec[name][keep]
        out[name] = a.astype(a.dtype.newbyteorder("=")) if a.dtype.byteorder not in ("=", "|") else a.copy()
    intensity = np.zeros(int(keep.sum()), np.float32)
    for name in INTENSITY_FIELDS:
        if name in out and out[name].ndim == 1:
            intensity = out.pop(name).astype(np.float32)
            break
    return Cloud(np.ascontiguousarray(xyz[keep]), intensity, out, dropped=int(n - keep.sum()))


def encode(
    points: np.ndarray, extra: dict[str, np.ndarray] | None = None
) -> tuple[list[PointField], bytes, int]:
    """Pack ``points`` ``(N, 3)`` (as float32 x, y, z) and the ``(N,)`` arrays of ``extra``, each in its
    own dtype, little-endian and in the given order: the fields, the payload and the point step."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    columns = [("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])]
    for name, a in (extra or {}).items():
        a = np.asarray(a)
        if a.shape != (len(pts),):
            raise InputError(f"PointCloud2 field {name!r}: {a.shape} values for {len(pts)} points")
        columns.append((name, a))
    fields, names, formats, offsets, offset = [], [], [], [], 0
    for name, a in columns:
        code = a.dtype.str[1:]
        if code not in _DATATYPE_OF:
            raise InputError(f"PointCloud2 field {name!r}: dtype {a.dtype} has no PointField datatype")
        fields.append(PointField(name, offset, _DATATYPE_OF[code]))
        names.append(name)
        formats.append("<" + code)
        offsets.append(offset)
        offset += a.dtype.itemsize
    rec = np.zeros(
        len(pts), np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": offset})
    )
    for name, a in columns:
        rec[name] = a
    return fields, rec.tobytes(), offset


def point_times(
    values: np.ndarray, stamp_s: float, *, unit: str | None = None, where: str = "PointCloud2"
) -> np.ndarray:
    """Per-point times in seconds relative to the stamp (float64), from a time field's values.

    Units: integer fields count nanoseconds (Ouster ``t``); float fields are seconds relative to the stamp
    (Velodyne ``time``, simbed), or absolute when they are that large: above 1e15 absolute nanoseconds
    (Livox), above 1e8 absolute seconds (Hesai, Robosense). ``unit`` (``s``, ``ns``, ``abs_s``, ``abs_ns``)
    overrides the guess."""
    v = np.asarray(values)
    if v.ndim != 1:
        raise InputError(f"{where}: the time field must hold one value per point")
    if unit is None:
        if np.issubdtype(v.dtype, np.integer):
            unit = "ns"
        else:
            big = float(np.nanmax(np.abs(v))) if len(v) else 0.0
            unit = "abs_ns" if big > 1e15 else "abs_s" if big > 1e8 else "s"
    if unit == "ns":
        return v.astype(np.float64) * 1e-9
    if unit == "s":
        return v.astype(np.float64)
    if unit == "abs_s":
        return v.astype(np.float64) - stamp_s
    if unit == "abs_ns":
        return (v.astype(np.float64) - stamp_s * 1e9) * 1e-9
    raise InputError(f"{where}: point time unit {unit!r}: expected s, ns, abs_s or abs_ns")


def find_time_field(fields: dict[str, np.ndarray], name: str | None = None) -> str | None:
    """The cloud's per-point time field: ``name`` if given (it must exist), else the first of ``t``,
    ``time``, ``timestamp``, ``time_stamp``, ``offset_time`` that is present."""
    if name is not None:
        return name if name in fields else None
    return next((f for f in TIME_FIELDS if f in fields and fields[f].ndim == 1), None)
