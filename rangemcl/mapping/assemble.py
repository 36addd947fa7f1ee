"""Write a map folder from per-tile meshes without ever holding the whole map in memory.

``rangemcl build-map`` meshes each tile in its own job and leaves one ``.npz`` per tile (vertices, faces,
is_ground) in its work folder. :func:`assemble_map` turns those into the map folder that
:meth:`MeshMap.load` reads, with exactly the content :meth:`MeshMap.from_mesh` followed by
:meth:`MeshMap.save` gives for the tiles' meshes concatenated in order, while holding one tile's mesh
at a time:

1. a pass over the tiles for counts and bounds (the tile grid's origin, the ground grid's layout);
2. a pass that assigns each face to the tile holding its centroid (a face near a border can land in the
   neighbouring tile after ground simplification moved a vertex), and spools each ground vertex to the
   file of the tile that owns its ground-grid cell;
3. the ground grid, one owner tile at a time (per-cell medians of the ground vertices, as
   :meth:`GroundGrid.from_vertices` computes them);
4. ``mesh.ply`` streamed: the header with the totals, vertex records tile by tile, then face records
   (indices offset by the vertices before) from a spool file; ``tiles.npz`` with ``face_tile`` streamed
   from a memory-mapped file; ``ground.npz``, ``drive.npz``, ``map.yaml`` last.

So the builder's peak memory follows the largest tile, not the map's area. What does grow with the area:
the ground grid (4 bytes per cell, capped at ``MAX_GROUND_CELLS``) and ``face_tile`` on disk.
"""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np

from rangemcl.atomic import atomic_write, savez_stable
from rangemcl.errors import InputError
from rangemcl.mapping.meshmap import (
    GROUND_RGB,
    NON_GROUND_RGB,
    _tile_ij,
    _tile_keys,
    face_tile_ij,
    fill_cell_medians,
    ground_grid_layout,
    map_yaml_text,
    ply_face_bytes,
    ply_vertex_bytes,
    write_ply_header,
)
from rangemcl.pool import kill_point


def _load_tile(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        with np.load(path) as z:
            v = np.asarray(z["vertices"], np.float64).reshape(-1, 3)
            f = np.asarray(z["faces"], np.int64).reshape(-1, 3)
            g = np.asarray(z["is_ground"], bool).reshape(-1)
    except (OSError, KeyError, ValueError) as err:
        raise InputError(f"{path}: unreadable tile mesh: {err}") from None
    if len(g) != len(v):
        raise InputError(f"{path}: {len(g)} ground labels for {len(v)} vertices")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"{path}: face indices out of range 0..{len(v) - 1}")
    if not np.isfinite(v).all():
        raise InputError(f"{path}: tile mesh has NaN or infinite vertices")
    return v, f, g


def _member(name: str):
    """A zip member with a fixed timestamp (``zipfile`` stamps members with the current time)."""
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.external_attr = 0o644 << 16
    return info


def assemble_map(
    tile_meshes: list[Path],
    out_dir: Path,
    *,
    tile_size_m: float,
    work_dir: Path,
    ground_cell_m: float = 1.0,
    meta: dict | None = None,
    drive_xy: np.ndarray | None = None,
) -> dict:
    """Write the map folder ``out_dir`` from per-tile mesh files (see the module docstring).

    Returns the counts written to ``map.yaml`` (vertices, triangles, ground_vertices, tiles). Raises an
    InputError when the tiles hold no triangle.
    """
    out_dir = Path(out_dir)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    tile_size_m = float(tile_size_m)

    # 1. counts and bounds
    n_v = n_f = n_g = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    used = []
    for path in tile_meshes:
        v, f, g = _load_tile(path)
        if len(f) == 0:
            continue
        used.append(path)
        n_v, n_f, n_g = n_v + len(v), n_f + len(f), n_g + int(g.sum())
        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
    if n_f == 0:
        raise InputError("the reconstruction is empty (no tile has a triangle)")
    origin = np.floor(lo[:2] / tile_size_m) * tile_size_m
    g_origin, g_cell, (gnx, gny) = ground_grid_layout(lo[:2], hi[:2], ground_cell_m)

    # 2. face tiles (as keys, memory-mapped) and ground vertices spooled by the tile owning their cell
    spool = work / "assemble"
    shutil.rmtree(spool, ignore_errors=True)
    spool.mkdir()
    face_keys = np.lib.format.open_memmap(spool / "face_keys.npy", mode="w+", dtype=np.int64, shape=(n_f,))
    tile_keys: set[int] = set()
    ground_parts: dict[int, list[Path]] = {}
    pos = 0
    for n, path in enumerate(used):
        v, f, g = _load_tile(path)
        ij = face_tile_ij(v, f, origin, tile_size_m)
        keys = _tile_keys(ij[:, 0], ij[:, 1])
        face_keys[pos : pos + len(f)] = keys
        pos += len(f)
        tile_keys.update(np.unique(keys).tolist())
        pg = v[g]
        if len(pg):
            cell = np.clip(np.floor((pg[:, :2] - g_origin) / g_cell).astype(np.int64), 0, [gnx - 1, gny - 1])
            owner = _tile_keys(*np.floor((g_origin + cell * g_cell - origin) / tile_size_m).T)
            for key in np.unique(owner):
                part = spool / f"ground_{n}_{key}.npy"  # tile n's ground vertices in key's cells
                np.save(part, pg[owner == key])
                ground_parts.setdefault(int(key), []).append(part)
    face_keys.flush()
    keys_sorted = np.array(sorted(tile_keys), np.int64)

    # 3. ground grid, one owner tile at a time (a cell's vertices all go to one owner)
    heights = np.full((gny, gnx), np.nan, np.float32)
    for parts in ground_parts.values():
        fill_cell_medians(heights, np.concatenate([np.load(p) for p in parts]), g_origin, g_cell)

    # 4. mesh.ply and tiles.npz, streamed
    face_tile = np.lib.format.open_memmap(spool / "face_tile.npy", mode="w+", dtype=np.int32, shape=(n_f,))
    chunk = 1 << 22
    for start in range(0, n_f, chunk):
        face_tile[start : start + chunk] = np.searchsorted(keys_sorted, face_keys[start : start + chunk])
    face_tile.flush()
    del face_tile, face_keys

    faces_spool = spool / "faces.bin"

    def write_mesh(fh) -> None:
        write_ply_header(fh, n_v, n_f, colours=True)
        offset = 0
        with faces_spool.open("wb") as ff:
            for path in used:
                v, f, g = _load_tile(path)
                colours = np.where(g[:, None], GROUND_RGB, NON_GROUND_RGB).astype(np.uint8)
                fh.write(ply_vertex_bytes(v, colours))
                ff.write(ply_face_bytes(f + offset))
                offset += len(v)
        with faces_spool.open("rb") as ff:
            shutil.copyfileobj(ff, fh, 1 << 24)

    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(out_dir / "mesh.ply", write_mesh)
    kill_point("assemble")  # tests: killed with the map folder half written
    faces_spool.unlink()

    def write_tiles(fh) -> None:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, value in (
                ("tile_size_m", np.float64(tile_size_m)),
                ("tile_origin_xy", origin),
                ("tiles", _tile_ij(keys_sorted).astype(np.int32)),
            ):
                with zf.open(_member(f"{name}.npy"), "w", force_zip64=True) as entry:
                    np.lib.format.write_array(entry, np.asanyarray(value))
            # fixed timestamps: the same map gives the same bytes
            with (
                (spool / "face_tile.npy").open("rb") as src,
                zf.open(_member("face_tile.npy"), "w", force_zip64=True) as entry,
            ):
                shutil.copyfileobj(src, entry, 1 << 20)

    atomic_write(out_dir / "tiles.npz", write_tiles)
    atomic_write(
        out_dir / "ground.npz",
        lambda fh: savez_stable(fh, origin_xy=g_origin, cell_m=np.float64(g_cell), heights=heights),
    )
    files = {"mesh": "mesh.ply", "tiles": "tiles.npz", "ground": "ground.npz"}
    if drive_xy is not None:
        atomic_write(out_dir / "drive.npz", lambda fh: savez_stable(fh, xy=np.asarray(drive_xy, np.float64)))
        files["drive"] = "drive.npz"
    counts = {"vertices": n_v, "triangles": n_f, "ground_vertices": n_g, "tiles": len(keys_sorted)}
    extent = (*lo.tolist(), *hi.tolist())
    text = map_yaml_text(files, counts, tile_size_m, g_cell, extent, meta or {})
    atomic_write(out_dir / "map.yaml", lambda fh: fh.write(text.encode()))
    shutil.rmtree(spool, ignore_errors=True)
    return counts
