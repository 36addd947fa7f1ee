"""What ``rangemcl map-info`` prints of a map folder, read within the memory of its largest tile.

A map of format 2 is opened by its index alone (timed: what every localizer run pays before its first
tile), then every tile file is read once, checked (size, checksum, counts) and counted, one tile at a time,
so a city's map is described in the memory of one tile rather than of the whole mesh. A map of format 1 is
loaded whole, as before (:func:`rangemcl.maps.meshmap.map_summary`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from rangemcl.maps.meshmap import (
    MAP_FILES,
    map_summary,
    open_checked_store,
    read_ground_and_drive,
    read_map_yaml,
)

_META_KEYS = ("frame", "sensor_height_m", "created_by", "source_sequence", "source_mesh", "scene", "sensor")


def map_info(map_dir, *, describe_prior=None) -> dict[str, Any]:
    """Plain figures about the map in ``map_dir`` (keys in print order); problems are InputErrors naming
    the file."""
    from rangemcl.maps.meshmap import MeshMap

    map_dir = Path(map_dir)
    version, doc = read_map_yaml(map_dir)
    if version < 2:
        return map_summary(MeshMap.load(map_dir))
    t0 = time.perf_counter()
    store = open_checked_store(map_dir, doc["counts"])
    open_ms = (time.perf_counter() - t0) * 1e3
    ground, drive = read_ground_and_drive(map_dir, doc)
    per_tile = np.array([e.triangles for e in store.entries])
    ground_vertices = ground_faces = 0
    for k in range(len(store.entries)):  # every tile checked, one at a time
        _v, f, g = store.read(k)
        ground_vertices += int(g.sum())
        ground_faces += int(g[f].all(axis=1).sum()) if len(f) else 0
        if store.entries[k].coarse is not None:
            store.read(k, coarse=True)
    xmin, ymin, zmin, xmax, ymax, zmax = store.extent()
    out: dict[str, Any] = {"map_dir": str(map_dir)}
    out["size_m"] = f"{xmax - xmin:.1f} x {ymax - ymin:.1f} x {zmax - zmin:.1f}"
    out["extent_m"] = f"x [{xmin:.2f}, {xmax:.2f}]  y [{ymin:.2f}, {ymax:.2f}]  z [{zmin:.2f}, {zmax:.2f}]"
    out["triangles"] = store.n_triangles
    out["vertices"] = f"{store.n_vertices} (in the tile files: a border vertex is in each tile it serves)"
    out["ground_vertex_share"] = round(ground_vertices / max(1, store.n_vertices), 4)
    out["ground_triangle_share"] = round(ground_faces / max(1, store.n_triangles), 4)
    out["tiles"] = len(store.entries)
    out["tile_size_m"] = store.tile_size_m
    out["triangles_per_tile"] = (
        f"min {per_tile.min()}, median {int(np.median(per_tile))}, max {per_tile.max()}"
    )
    ny, nx = ground.shape
    out["ground_grid"] = f"{nx} x {ny} cells of {ground.cell_m:g} m, {ground.measured.mean():.0%} measured"
    out["mapping_drive"] = "kept" if drive is not None else "none"
    coarse = [e.coarse for e in store.entries if e.coarse is not None]
    if coarse:
        tri = sum(c.triangles for c in coarse)
        out["coarse_level"] = (
            f"{len(coarse)} tiles, {tri} triangles ({100 * tri / max(1, store.n_triangles):.1f} %), "
            f"{sum(c.bytes for c in coarse) / 1e6:.1f} MB"
        )
    else:
        out["coarse_level"] = "none (rangemcl map-coarse adds one)"
    files = [map_dir / n for n in (*MAP_FILES, "drive.npz")]
    out["bytes_on_disk"] = (
        store.bytes_on_disk
        + sum(c.bytes for c in coarse)
        + sum(p.stat().st_size for p in files if p.is_file())
    )
    out["index_open_ms"] = round(open_ms, 1)
    if describe_prior is not None:  # the localizer's reading of the map's place prior (the CLI gives it)
        out["place_prior"] = describe_prior(map_dir)
    out["format_version"] = version
    meta = doc.get("meta") or {}
    for key in _META_KEYS:
        if meta.get(key) is not None:
            out[key] = meta[key]
    return out
