"""The coarse level of a tiled map: each tile decimated to a few per cent of its triangles.

A localizer within a memory budget holds the tiles near the particles at full resolution and, where the
tiles within the sensor's range do not all fit, the farther ones at this level (``rangemcl.maps.view``).
Each tile is simplified on its own by quadric error decimation (Garland and Heckbert, through Open3D's
``simplify_quadric_decimation``) with a heavy weight on boundary edges, so that the tile's border, where
its neighbour begins, stays where it was, and each boundary vertex is put back on the full-resolution
vertex it came from (the collapses move them by millimetres), so that a ray does not slip through the
seam. A coarse vertex is ground when the nearest full-resolution vertex is.

Files: ``coarse/I_J.npz`` beside ``tiles/I_J.npz`` (the same deflated ``.npz`` layout), listed under
``coarse`` in each tile's entry of ``tiles.json``; the index is rewritten last and atomically, so an
interrupted run leaves the map as it was. ``rangemcl map-coarse MAP`` adds the level to a map.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError
from rangemcl.maps.store import TileEntry, TileStore, write_index, write_tile

COARSE_RATIO = 0.05  # triangles kept
BOUNDARY_WEIGHT = 100.0  # how much more a boundary edge resists collapse
MIN_TRIANGLES = 64  # a tile this small is kept whole


def decimate_tile(
    vertices: np.ndarray,
    faces: np.ndarray,
    is_ground: np.ndarray,
    ratio: float = COARSE_RATIO,
    boundary_weight: float = BOUNDARY_WEIGHT,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(vertices, faces, is_ground)`` of the tile simplified to about ``ratio`` of its triangles (at
    least :data:`MIN_TRIANGLES`); unused vertices dropped."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int32)
    target = max(MIN_TRIANGLES, int(round(ratio * len(f))))
    if target >= len(f):
        return v, f, np.asarray(is_ground, bool)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    small = mesh.simplify_quadric_decimation(target, boundary_weight=boundary_weight)
    small.remove_unreferenced_vertices()
    small.remove_degenerate_triangles()
    cv = np.asarray(small.vertices, np.float64)
    cf = np.asarray(small.triangles, np.int32)
    if len(cf) == 0:  # nothing left to simplify to: keep the tile whole
        return v, f, np.asarray(is_ground, bool)
    _d, nearest = cKDTree(v).query(cv)
    # the border back where it was: a boundary vertex (on an edge of one face) goes to the full-resolution
    # vertex it came from, so that the seam with the neighbour tile is not opened by the collapses' shifts
    edges = np.sort(np.concatenate([cf[:, [0, 1]], cf[:, [1, 2]], cf[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    border = np.unique(uniq[count == 1])
    cv = cv.copy()
    cv[border] = v[nearest[border]]
    return cv, cf, np.asarray(is_ground, bool)[nearest]


def write_with_coarse(map_dir, ij, vertices, faces, is_ground, coarse_ratio: float | None) -> TileEntry:
    """Write a tile's file and, when ``coarse_ratio`` is set, its coarse level; its index entry."""
    entry = write_tile(map_dir, ij, vertices, faces, is_ground)
    if not coarse_ratio:
        return entry
    cv, cf, cg = decimate_tile(vertices, faces, is_ground, coarse_ratio)
    return replace(entry, coarse=write_tile(map_dir, ij, cv, cf, cg, coarse=True))


def add_coarse_level(map_dir, ratio: float = COARSE_RATIO, *, progress=None) -> dict:
    """Write the coarse level of every tile of the map in ``map_dir`` (format 2), then the index with it;
    what it did."""
    if not (np.isfinite(ratio) and 0.0 < ratio <= 1.0):
        raise InputError(f"--ratio must lie in (0, 1], got {ratio}")
    map_dir = Path(map_dir)
    store = TileStore.open(map_dir)
    t0 = time.perf_counter()
    entries = []
    try:
        for k, e in enumerate(store.entries):
            v, f, g = store.read(k)
            cv, cf, cg = decimate_tile(v, f, g, ratio)
            entries.append(replace(e, coarse=write_tile(map_dir, e.ij, cv, cf, cg, coarse=True)))
            if progress is not None:
                progress(k + 1, len(store.entries))
    except InputError:  # a broken tile: the files of this run go, the map stays as it was
        listed = {e.coarse.file for e in store.entries if e.coarse is not None}
        for e in entries:
            if e.coarse.file not in listed:
                (map_dir / e.coarse.file).unlink(missing_ok=True)
        raise
    write_index(map_dir, store.tile_size_m, store.origin_xy, entries)
    full = sum(e.triangles for e in entries)
    coarse = sum(e.coarse.triangles for e in entries)
    return {
        "tiles": len(entries),
        "triangles": full,
        "coarse_triangles": coarse,
        "coarse_share": coarse / max(1, full),
        "coarse_bytes_on_disk": sum(e.coarse.bytes for e in entries),
        "seconds": time.perf_counter() - t0,
    }
