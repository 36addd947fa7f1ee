"""The reader of format-1 map folders' ``mesh.ply`` (binary little-endian PLY, float64 positions, uchar
colours as ground labels, int32 triangle lists), kept only so that maps of the older format 1 still load
(``rangemcl map-upgrade`` rewrites them as format 2, a numpy ``.npz`` mesh per tile:
:mod:`rangemcl.maps.store`). Nothing in rangemcl writes this format any more; ``simbed export-mesh``
writes its PLY through Open3D.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangemcl.errors import InputError

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply_binary(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(vertices (V, 3) float64, faces (F, 3) int64, colours (V, 3) uint8 or None)`` of a binary
    triangle PLY; any problem is an InputError naming the file."""
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror or err}") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (it does not start with 'ply')")
    if end < 0:
        raise InputError(f"{path}: truncated in the header (no 'end_header')")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise InputError(f"{path}: truncated in the header")
    body = memoryview(data)[nl + 1 :]
    try:
        lines = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(f"{path}: PLY header is not ASCII text") from None
    order = None
    # (name, count, [(property, dtype) or (property, (count dtype, item dtype))])
    elements: list[tuple[str, int, list]] = []
    for raw in lines[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(words[1], "?")
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append((words[4], (_PLY_TYPES[words[2]], _PLY_TYPES[words[3]])))
            elif words[0] == "property":
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise InputError(f"{path}: bad PLY header line {raw.strip()!r}") from None
    if order is None:
        raise InputError(f"{path}: PLY header has no 'format' line")
    if order == "?":
        raise InputError(f"{path}: only binary PLY is supported here (import other meshes with import-mesh)")
    vertices = faces = colours = None
    offset = 0
    for name, count, props in elements:
        if count < 0:
            raise InputError(f"{path}: element {name} has a negative count")
        fields = []
        for prop, t in props:
            if isinstance(t, tuple):
                if name != "face":
                    raise InputError(f"{path}: list property in element '{name}' is not supported")
                fields += [(prop + "_n", order + t[0]), (prop, order + t[1], (3,))]
            else:
                fields.append((prop, order + t))
        dt = np.dtype(fields)
        nbytes = dt.itemsize * count
        if offset + nbytes > len(body):
            raise InputError(
                f"{path}: truncated: element '{name}' needs {nbytes} bytes at offset {offset}, "
                f"only {max(len(body) - offset, 0)} left"
            )
        rec = np.frombuffer(body, dt, count, offset)
        offset += nbytes
        names = dt.names or ()
        if name == "vertex":
            if not {"x", "y", "z"} <= set(names):
                raise InputError(f"{path}: vertex element lacks x, y, z")
            vertices = np.stack([rec[c].astype(np.float64) for c in "xyz"], axis=1)
            if {"red", "green", "blue"} <= set(names):
                colours = np.stack([rec[c].astype(np.uint8) for c in ("red", "green", "blue")], axis=1)
        elif name == "face":
            lists = [p for p, t in props if isinstance(t, tuple)]
            if len(lists) != 1:
                raise InputError(f"{path}: face element must have exactly one list property")
            if count and np.any(rec[lists[0] + "_n"] != 3):
                raise InputError(f"{path}: faces are not all triangles")
            faces = rec[lists[0]].astype(np.int64).reshape(-1, 3)
    if offset != len(body):
        raise InputError(f"{path}: {len(body) - offset} bytes after the last element (counts disagree?)")
    if vertices is None or faces is None:
        raise InputError(f"{path}: PLY needs a 'vertex' and a 'face' element")
    return vertices, faces, colours
