"""``rangemcl import-mesh`` for meshes larger than memory: a binary PLY read in place.

:func:`rangemcl.maps.meshmap.import_mesh` reads the whole mesh (trimesh), then labels, tiles and writes
it: its peak memory grows with the mesh (3.7 GB for 8.6 M triangles). This module writes the same map
folder, file for file, from a binary PLY of triangles without holding it: the file's vertex and face
blocks are memory-mapped (fixed-size records), every pass reads them a block at a time, and what the
passes accumulate per vertex or per ground cell lives in memory-mapped scratch files. Memory then follows
the block size and the largest tile, not the mesh:

1. vertices, a block at a time: finite, bounds (the tile grid's origin, the ground grid's layout), and
   their colours when they carry the map's ground / non-ground colours (:meth:`MeshMap.save`'s labels);
2. faces, a block at a time: triangles with indices in range, at least one with an area; the up-turned
   face normals summed per vertex, one accumulator per corner, in face order (the sums of
   :func:`label_ground_vertices`, bit for bit), which vertices are used, and the faces spooled by the
   tile holding their centroid;
3. vertices again: the lowest used vertex of each ground-rule cell, then the ground labels (the rule of
   :func:`label_ground_vertices`) and the ground vertices spooled by the tile owning their ground-grid cell;
4. per tile: its faces from the spool, the vertices they use read from the file, the tile file and its
   coarse level; the ground grid one owner tile at a time; the index and ``map.yaml`` last.

Other mesh files (ASCII PLY, OBJ, STL, polygons that are not triangles) go through the in-memory import.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError

BLOCK = 1 << 20  # vertices or faces per block of a pass

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class PlyLayout:
    """Where a binary PLY keeps its vertices and triangles, as fixed-size records."""

    vertex_offset: int
    vertex_dtype: np.dtype
    n_vertices: int
    face_offset: int
    face_dtype: np.dtype  # fields "n" (the list's count) and "i" (3 indices), and any scalar properties
    n_faces: int


def ply_layout(path: Path) -> PlyLayout | None:
    """The layout of a binary PLY whose elements are ``vertex`` (scalar properties, x y z among them) then
    ``face`` (one list of indices, assumed of 3, and scalar properties); None for anything else (ASCII,
    other elements, lists in the vertices), which the in-memory import reads."""
    try:
        with open(path, "rb") as fh:
            if fh.readline().strip() != b"ply":
                return None
            fmt = None
            elements: list[list] = []
            while True:
                line = fh.readline()
                if not line:
                    return None
                words = line.decode("ascii", errors="replace").split()
                if not words or words[0] in ("comment", "obj_info"):
                    continue
                if words[0] == "format":
                    fmt = words[1] if len(words) > 1 else None
                elif words[0] == "element" and len(words) == 3:
                    elements.append([words[1], int(words[2]), []])
                elif words[0] == "property" and elements:
                    elements[-1][2].append(words[1:])
                elif words[0] == "end_header":
                    header = fh.tell()
                    break
                else:
                    return None
    except (OSError, ValueError):
        return None
    binary = fmt in ("binary_little_endian", "binary_big_endian")
    if not binary or [e[0] for e in elements] != ["vertex", "face"]:
        return None
    end = "<" if fmt == "binary_little_endian" else ">"
    (_, nv, vprops), (_, nf, fprops) = elements
    vfields = []
    for prop in vprops:
        if len(prop) != 2 or prop[0] not in _PLY_TYPES:
            return None
        vfields.append((prop[1], end + _PLY_TYPES[prop[0]]))
    names = [n for n, _ in vfields]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        return None
    ffields = []
    lists = 0
    for prop in fprops:
        if prop[0] == "list" and len(prop) == 4 and prop[1] in _PLY_TYPES and prop[2] in _PLY_TYPES:
            lists += 1
            ffields += [("n", end + _PLY_TYPES[prop[1]]), ("i", end + _PLY_TYPES[prop[2]], (3,))]
        elif len(prop) == 2 and prop[0] in _PLY_TYPES and prop[1] not in ("n", "i"):
            ffields.append((prop[1], end + _PLY_TYPES[prop[0]]))
        else:
            return None
    if lists != 1:
        return None
    vdtype, fdtype = np.dtype(vfields), np.dtype(ffields)
    face_offset = header + nv * vdtype.itemsize
    if path.stat().st_size != face_offset + nf * fdtype.itemsize:
        return None  # truncated, polygons that are not all triangles, trailing data: the in-memory reader
    return PlyLayout(header, vdtype, nv, face_offset, fdtype, nf)


def _xyz(block) -> np.ndarray:
    return np.stack([block["x"], block["y"], block["z"]], axis=1).astype(np.float64)


def import_mesh_streaming(
    path,
    out_dir,
    *,
    work_dir,
    tile_size_m: float = 100.0,
    coarse_ratio: float | None = None,
    meta: dict | None = None,
    max_angle_deg: float = 30.0,
    label_cell_m: float = 1.0,
    layer_m: float = 0.3,
    ground_cell_m: float = 1.0,
    block: int = BLOCK,
    drive_xy: np.ndarray | None = None,
) -> dict | None:
    """Write the map folder ``out_dir`` from the binary PLY ``path`` (module docstring); the same files as
    ``import_mesh(path).save(out_dir)``. Returns the counts of ``map.yaml``, or None when the file is not a
    binary triangle PLY this reads (the caller falls back to the in-memory import). Scratch files go to
    ``work_dir`` (removed at the end)."""
    from rangemcl.maps.coarse import write_with_coarse
    from rangemcl.maps.meshmap import (
        GROUND_RGB,
        GROUND_RULE_LABEL,
        NON_GROUND_RGB,
        GroundGrid,
        fill_cell_medians,
        ground_grid_layout,
        tile_ij,
        tile_keys,
        write_map_files,
    )
    from rangemcl.maps.store import write_index

    path, out_dir, work = Path(path), Path(out_dir), Path(work_dir)
    layout = ply_layout(path)
    if layout is None:
        return None
    nv, nf = layout.n_vertices, layout.n_faces
    if nv == 0 or nf == 0:
        raise InputError(f"{path}: holds no triangles (a point cloud or an empty mesh?)")
    vfile = np.memmap(path, layout.vertex_dtype, "r", layout.vertex_offset, (nv,))
    ffile = np.memmap(path, layout.face_dtype, "r", layout.face_offset, (nf,))
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    try:
        tile_size_m = float(tile_size_m)
        # 1. vertices: finite, bounds, colours
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        names = layout.vertex_dtype.names
        by_colour = all(c in names for c in ("red", "green", "blue"))  # until a vertex is otherwise
        for a in range(0, nv, block):
            b = vfile[a : a + block]
            v = _xyz(b)
            bad = ~np.isfinite(v).all(axis=1)
            if bad.any():
                raise InputError(f"{path}: vertex {a + int(np.argmax(bad))} is NaN or infinite")
            lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
            if by_colour:
                rgb = np.stack([b["red"], b["green"], b["blue"]], axis=1)
                by_colour = bool(np.all(np.all(rgb == GROUND_RGB, 1) | np.all(rgb == NON_GROUND_RGB, 1)))
        origin = np.floor(lo[:2] / tile_size_m) * tile_size_m

        # 2. faces: checks, normal sums per corner (in face order), used vertices, faces spooled by tile
        acc = [np.memmap(work / f"normals_{k}.f8", np.float64, "w+", shape=(nv, 3)) for k in range(3)]
        used = np.memmap(work / "used.u1", np.uint8, "w+", shape=(nv,))
        parts: dict[int, list[Path]] = {}
        area = False
        for n_block, a in enumerate(range(0, nf, block)):
            rec = ffile[a : a + block]
            if (rec["n"] != 3).any():
                k = a + int(np.argmax(rec["n"] != 3))
                raise InputError(f"{path}: face {k} has {int(rec['n'][k - a])} corners, not a triangle mesh")
            f = rec["i"].astype(np.int64)
            if f.min() < 0 or f.max() >= nv:
                raise InputError(
                    f"{path}: face indices out of range 0..{nv - 1} (found {f.min()}..{f.max()})"
                )
            tri = _xyz(vfile[f.reshape(-1)]).reshape(-1, 3, 3)
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            area = area or bool((np.linalg.norm(n, axis=1) > 0).any())
            n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
            for k in range(3):
                for d in range(3):  # a vertex's sum grows in face order, as np.bincount's does
                    np.add.at(acc[k][:, d], f[:, k], n[:, d])
            used[f.reshape(-1)] = 1
            centroid = (tri[:, 0, :2] + tri[:, 1, :2] + tri[:, 2, :2]) / 3.0
            ij = np.floor((centroid - origin) / tile_size_m)
            keys = tile_keys(ij[:, 0], ij[:, 1])
            for key in np.unique(keys):
                part = work / f"faces_{key}_{n_block:06d}.npy"
                np.save(part, f[keys == key].astype(np.int64))
                parts.setdefault(int(key), []).append(part)
        if not area:
            raise InputError(f"{path}: all {nf} triangles are degenerate (zero area)")

        # 3. ground labels (colours, or the rule: lowest used vertex per cell), ground vertices by owner
        is_ground = np.memmap(work / "ground.u1", np.uint8, "w+", shape=(nv,))
        c_origin = np.floor(lo[:2] / label_cell_m)
        c_n = (np.floor(hi[:2] / label_cell_m) - c_origin).astype(np.int64) + 1
        lowest = np.memmap(work / "lowest.f8", np.float64, "w+", shape=(int(c_n[1]), int(c_n[0])))
        if not by_colour:
            lowest[:] = np.inf
            for a in range(0, nv, block):
                v = _xyz(vfile[a : a + block])
                u = used[a : a + block].astype(bool)
                c = (np.floor(v[u, :2] / label_cell_m) - c_origin).astype(np.int64)
                np.minimum.at(lowest, (c[:, 1], c[:, 0]), v[u, 2])
        cos_max = math.cos(math.radians(max_angle_deg))
        g_origin, g_cell, (gnx, gny) = ground_grid_layout(lo[:2], hi[:2], ground_cell_m)
        ground_parts: dict[int, list[Path]] = {}
        for n_block, a in enumerate(range(0, nv, block)):
            b = vfile[a : a + block]
            v = _xyz(b)
            u = used[a : a + block].astype(bool)
            if by_colour:
                g = np.all(np.stack([b["red"], b["green"], b["blue"]], axis=1) == GROUND_RGB, axis=1)
            else:
                vn = (np.array(acc[0][a : a + block]) + np.array(acc[1][a : a + block])) + np.array(
                    acc[2][a : a + block]
                )
                norm = np.linalg.norm(vn, axis=1)
                flat = (norm > 0) & (vn[:, 2] >= cos_max * norm)
                c = (np.floor(v[:, :2] / label_cell_m) - c_origin).astype(np.int64)
                g = flat & u & (v[:, 2] <= lowest[c[:, 1], c[:, 0]] + layer_m)
            is_ground[a : a + block] = g
            pg = v[g]  # (colour labels may mark unused vertices: the whole-mesh import counts them too)
            if len(pg):
                cell = np.clip(
                    np.floor((pg[:, :2] - g_origin) / g_cell).astype(np.int64), 0, [gnx - 1, gny - 1]
                )
                owner = tile_keys(*np.floor((g_origin + cell * g_cell - origin) / tile_size_m).T)
                for key in np.unique(owner):
                    part = work / f"gv_{key}_{n_block:06d}.npy"
                    np.save(part, pg[owner == key])
                    ground_parts.setdefault(int(key), []).append(part)
        del acc, lowest

        # 4. the tiles, the ground grid, the index and map.yaml
        out_dir.mkdir(parents=True, exist_ok=True)
        entries = []
        for key in sorted(parts):
            f = np.concatenate([np.load(p) for p in parts[key]])
            verts, inverse = np.unique(f, return_inverse=True)
            entries.append(
                write_with_coarse(
                    out_dir,
                    tile_ij(np.array([key]))[0],
                    _xyz(vfile[verts]),
                    inverse.reshape(-1, 3).astype(np.int32),
                    np.asarray(is_ground[verts]).astype(bool),
                    coarse_ratio,
                )
            )
            for p in parts[key]:
                p.unlink()
        heights = np.full((gny, gnx), np.nan, np.float32)
        for owned in ground_parts.values():
            fill_cell_medians(heights, np.concatenate([np.load(p) for p in owned]), g_origin, g_cell)
        write_index(out_dir, tile_size_m, origin, entries)
        base = {"source_mesh": str(path), "created_by": "rangemcl import-mesh"}
        base["ground_labels"] = "vertex colours" if by_colour else GROUND_RULE_LABEL
        return write_map_files(
            out_dir,
            entries,
            ground=GroundGrid(g_origin, g_cell, heights),
            drive_xy=drive_xy,
            tile_size_m=tile_size_m,
            meta={**base, **(meta or {})},
        )
    finally:
        del vfile, ffile
        shutil.rmtree(work, ignore_errors=True)
