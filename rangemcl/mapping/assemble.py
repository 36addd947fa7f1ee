"""Write a map folder from per-tile meshes without ever holding the whole map in memory.

``rangemcl build-map`` meshes each tile in its own job and leaves one ``.npz`` per tile (vertices, faces,
is_ground) in its work folder. :func:`assemble_map` turns those into the map folder (format 2) that
:meth:`MeshMap.load` reads, with exactly the content :meth:`MeshMap.from_mesh` followed by
:meth:`MeshMap.save` gives for the tiles' meshes concatenated in order, while holding one tile's mesh
at a time:

1. a pass over the tiles for counts and bounds (the tile grid's origin, the ground grid's layout);
2. a pass that assigns each face to the tile holding its centroid (a face near a border can land in the
   neighbouring tile after ground simplification moved a vertex), and spools each ground vertex to the
   file of the tile that owns its ground-grid cell;
3. the ground grid, one owner tile at a time (per-cell medians of the ground vertices, as
   :meth:`GroundGrid.from_vertices` computes them);
4. the map's tile files (:mod:`rangemcl.maps.store`), one map tile at a time from its spooled parts,
   then ``tiles.json``, ``ground.npz``, ``drive.npz`` and ``map.yaml`` last.

So the builder's peak memory follows the largest tile, not the map's area. What does grow with the area:
the ground grid (4 bytes per cell, capped at ``MAX_GROUND_CELLS``) and the index (a line per tile).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from rangemcl.common.pool import kill_point
from rangemcl.errors import InputError
from rangemcl.maps.coarse import write_with_coarse
from rangemcl.maps.meshmap import (
    GroundGrid,
    face_tile_ij,
    fill_cell_medians,
    ground_grid_layout,
    tile_ij,
    tile_keys,
    write_map_files,
)
from rangemcl.maps.store import write_index


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


def assemble_map(
    tile_meshes: list[Path],
    out_dir: Path,
    *,
    tile_size_m: float,
    work_dir: Path,
    ground_cell_m: float = 1.0,
    meta: dict | None = None,
    drive_xy: np.ndarray | None = None,
    coarse_ratio: float | None = None,
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

    # 2. each build tile's faces spooled by the map tile holding their centroid (with the vertices they use,
    #    in the build tile's order), and ground vertices by the tile owning their ground-grid cell
    spool = work / "assemble"
    shutil.rmtree(spool, ignore_errors=True)
    spool.mkdir()
    mesh_parts: dict[int, list[Path]] = {}
    ground_parts: dict[int, list[Path]] = {}
    for n, path in enumerate(used):
        v, f, g = _load_tile(path)
        ij = face_tile_ij(v, f, origin, tile_size_m)
        keys = tile_keys(ij[:, 0], ij[:, 1])
        for key in np.unique(keys):
            fk = f[keys == key]
            verts, inverse = np.unique(fk, return_inverse=True)
            part = spool / f"mesh_{key}_{n}.npz"
            np.savez(
                part, vertices=v[verts], faces=inverse.reshape(-1, 3).astype(np.int32), is_ground=g[verts]
            )
            mesh_parts.setdefault(int(key), []).append(part)
        pg = v[g]
        if len(pg):
            cell = np.clip(np.floor((pg[:, :2] - g_origin) / g_cell).astype(np.int64), 0, [gnx - 1, gny - 1])
            owner = tile_keys(*np.floor((g_origin + cell * g_cell - origin) / tile_size_m).T)
            for key in np.unique(owner):
                part = spool / f"ground_{n}_{key}.npy"  # tile n's ground vertices in key's cells
                np.save(part, pg[owner == key])
                ground_parts.setdefault(int(key), []).append(part)

    # 3. ground grid, one owner tile at a time (a cell's vertices all go to one owner)
    heights = np.full((gny, gnx), np.nan, np.float32)
    for parts in ground_parts.values():
        fill_cell_medians(heights, np.concatenate([np.load(p) for p in parts]), g_origin, g_cell)

    # 4. the map's tiles, one at a time (its parts in build order: the vertex and face order of the whole
    #    map's tile), the index, then ground, drive and map.yaml
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for key in sorted(mesh_parts):
        vs, fs, gs = [], [], []
        offset = 0
        for part in mesh_parts[key]:
            with np.load(part) as z:
                vs.append(z["vertices"])
                fs.append(z["faces"] + np.int32(offset))
                gs.append(z["is_ground"])
            offset += len(vs[-1])
            part.unlink()
        ij = tile_ij(np.array([key]))[0]
        entries.append(
            write_with_coarse(
                out_dir, ij, np.concatenate(vs), np.concatenate(fs), np.concatenate(gs), coarse_ratio
            )
        )
        kill_point("assemble")  # tests: killed with the map folder half written
    write_index(out_dir, tile_size_m, origin, entries)
    counts = write_map_files(
        out_dir,
        entries,
        ground=GroundGrid(g_origin, g_cell, heights),
        drive_xy=drive_xy,
        tile_size_m=tile_size_m,
        meta=meta or {},
    )
    shutil.rmtree(spool, ignore_errors=True)
    return counts
