"""The mesh map the localizer renders from: a triangle mesh in the world frame, its ground labels, a tiling
and a ground-height grid, and the map folder they live in.

A map folder of format 2 (written by :meth:`MeshMap.save` and ``rangemcl build-map``) holds one mesh file
per tile and an index, ``tiles/I_J.npz`` and ``tiles.json`` (:mod:`rangemcl.maps.store`), with
``ground.npz``, ``drive.npz`` and ``map.yaml`` as below. A folder of the older format 1 (one mesh file;
still read, and rewritten as format 2 by ``rangemcl map-upgrade``) holds the whole mesh::

    mesh.ply     binary little-endian PLY: float64 x, y, z and uchar red, green, blue per vertex (ground
                 (128, 128, 128), everything else (200, 120, 60)); int32 triangle indices
    tiles.npz    tile_size_m, tile_origin_xy (2,), tiles (T, 2) int32 (i, j), face_tile (F,) int32
    ground.npz   origin_xy (2,), cell_m, heights (ny, nx) float32 (NaN: no ground seen in that cell)
    map.yaml     format, format_version, counts, tile size, extent and ``meta`` (frame, sensor height,
                 build parameters, source, created_by …)
    drive.npz    optional: xy (K, 2), the mapping drive's sensor positions about 1 m apart (the localizer
                 spreads its particles near them: the area a car was seen to drive)

Every file is written to a temporary file in the folder and renamed into place; ``map.yaml`` goes last.

Tiles: square cells of ``tile_size_m`` whose grid starts at ``tile_origin_xy`` (the mesh's minimum x, y
floored to a multiple of the tile size). Tile (i, j) covers ``[ox + i·s, ox + (i+1)·s) × [oy + j·s, oy +
(j+1)·s)``. Each face belongs to exactly one tile: the one holding its centroid (faces that straddle a
border are not split or duplicated). Only tiles that hold a face exist; ``tiles`` lists them sorted by
(i, j).

Ground labels, when none are given (:func:`label_ground_vertices`): a vertex is ground when (1) the sum of
the normals of its faces, each weighted by the face's area and flipped to point up (so a mesh's winding
does not matter), lies within 30° of +z, and (2) it lies within 0.3 m of the lowest vertex of its 1 m × 1 m
xy cell. Rule (2) keeps roofs and tops of walls out wherever the ground under or beside them is in the
same cell; a large flat roof with no ground vertex in its cells (e.g. the top of a car over unseen ground)
is labelled ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import yaml

from rangemcl.common.atomic import atomic_write, savez_stable
from rangemcl.common.yamlio import parse_yaml, read_text
from rangemcl.errors import InputError
from rangemcl.maps.ply_v1 import read_ply_binary
from rangemcl.maps.store import file_sha256

FORMAT_NAME = "rangemcl-mesh-map"
FORMAT_VERSION = 2  # tiles/ + tiles.json (rangemcl.maps.store); 1: mesh.ply + tiles.npz, still read
GROUND_RGB = (128, 128, 128)
NON_GROUND_RGB = (200, 120, 60)
MAP_FILES = ("tiles.json", "ground.npz", "map.yaml")  # format 2 (and its tiles/ folder)
MAP_FILES_V1 = ("mesh.ply", "tiles.npz", "ground.npz", "map.yaml")

# Grids with more cells than this are coarsened (4 bytes a cell: 100 MB), e.g. a ground grid for a
# mesh with a stray vertex kilometres away.
MAX_GROUND_CELLS = 25_000_000
# map.yaml's ground_labels for a map whose ground the rule of label_ground_vertices labelled
GROUND_RULE_LABEL = "rule: up-facing normal within 30 deg, lowest 0.3 m of 1 m cell"


# ---------------------------------------------------------------------------------------------- ground grid


@dataclass(eq=False)
class GroundGrid:
    """Ground height lookup: the map's ground z at any x, y (the localizer puts particles at this height
    plus the sensor's mounting height).

    ``heights[j, i]`` is the ground height measured in the cell ``[ox + i·c, ox + (i+1)·c) × [oy + j·c,
    oy + (j+1)·c)`` (row = y, column = x), NaN where no ground was seen. Queries interpolate bilinearly
    between cell centres; unmeasured cells take the value of the nearest measured cell (filled once, here),
    and points outside the grid take the value at the nearest edge. With no measured cell at all every
    query is NaN.
    """

    origin_xy: np.ndarray  # (2,) world x, y of cell (0, 0)'s lower-left corner
    cell_m: float
    heights: np.ndarray  # (ny, nx) float32, NaN where no ground was seen
    measured: np.ndarray = field(init=False, repr=False)  # (ny, nx) bool
    filled: np.ndarray = field(init=False, repr=False)  # (ny, nx) float64, NaN only if nothing measured

    def __post_init__(self) -> None:
        self.origin_xy = np.asarray(self.origin_xy, np.float64).reshape(2)
        self.cell_m = float(self.cell_m)
        self.heights = np.asarray(self.heights, np.float32)
        if self.heights.ndim != 2 or self.heights.size == 0:
            raise ValueError(f"ground heights must be a non-empty 2-D array, got shape {self.heights.shape}")
        if not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise ValueError(f"ground cell size must be positive, got {self.cell_m}")
        self.measured = np.isfinite(self.heights)
        filled = self.heights.astype(np.float64)
        if self.measured.any() and not self.measured.all():
            from scipy.ndimage import distance_transform_edt

            idx = distance_transform_edt(~self.measured, return_distances=False, return_indices=True)
            filled = filled[idx[0], idx[1]]
        self.filled = filled

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    def height_at(self, x, y) -> np.ndarray:
        """Ground z at world ``x, y`` (arrays broadcast together), float64."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        ny, nx = self.filled.shape
        fx = np.clip((x - self.origin_xy[0]) / self.cell_m - 0.5, 0.0, nx - 1.0)
        fy = np.clip((y - self.origin_xy[1]) / self.cell_m - 0.5, 0.0, ny - 1.0)
        fx = np.nan_to_num(fx, nan=0.0)  # NaN queries get NaN below, not an index error
        fy = np.nan_to_num(fy, nan=0.0)
        i0 = np.minimum(np.floor(fx).astype(np.intp), max(nx - 2, 0))
        j0 = np.minimum(np.floor(fy).astype(np.intp), max(ny - 2, 0))
        i1 = np.minimum(i0 + 1, nx - 1)
        j1 = np.minimum(j0 + 1, ny - 1)
        tx = fx - i0
        ty = fy - j0
        h = self.filled
        z = (1 - ty) * ((1 - tx) * h[j0, i0] + tx * h[j0, i1]) + ty * ((1 - tx) * h[j1, i0] + tx * h[j1, i1])
        return np.where(np.isfinite(x) & np.isfinite(y), z, np.nan)

    @classmethod
    def from_vertices(cls, vertices, is_ground, cell_m: float = 1.0) -> GroundGrid:
        """The median z of the ground vertices in each cell, on a grid that covers all ``vertices`` in x, y.

        The grid is coarsened (``cell_m`` multiplied by a whole number) when it would have more than
        ``MAX_GROUND_CELLS`` cells.
        """
        v = np.asarray(vertices, np.float64).reshape(-1, 3)
        g = np.asarray(is_ground, bool).reshape(-1)
        if len(v) == 0:
            raise ValueError("no vertices to build a ground grid from")
        origin, cell_m, (nx, ny) = ground_grid_layout(v[:, :2].min(axis=0), v[:, :2].max(axis=0), cell_m)
        heights = np.full((ny, nx), np.nan, np.float32)
        fill_cell_medians(heights, v[g], origin, cell_m)
        return cls(origin, cell_m, heights)


def ground_grid_layout(lo_xy, hi_xy, cell_m: float) -> tuple[np.ndarray, float, tuple[int, int]]:
    """``(origin_xy, cell_m, (nx, ny))`` of a ground grid covering ``lo_xy .. hi_xy``: the origin floored to
    a multiple of the cell size; the cell coarsened (multiplied by a whole number) while the grid would
    have more than ``MAX_GROUND_CELLS`` cells."""
    lo, hi = np.asarray(lo_xy, np.float64), np.asarray(hi_xy, np.float64)
    cell_m = float(cell_m)
    while True:
        origin = np.floor(lo / cell_m) * cell_m
        n = np.floor((hi - origin) / cell_m).astype(np.int64) + 1  # (nx, ny)
        if n[0] * n[1] <= MAX_GROUND_CELLS:
            return origin, cell_m, (int(n[0]), int(n[1]))
        cell_m *= math.ceil(math.sqrt(n[0] * n[1] / MAX_GROUND_CELLS))


def fill_cell_medians(heights: np.ndarray, points, origin_xy, cell_m: float) -> None:
    """Set each cell of ``heights`` (ny, nx) that holds any of ``points`` (N, 3) to the median of their z
    (points beyond the far edge count in the edge cell); other cells are left as they are."""
    pg = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(pg):
        return
    ny, nx = heights.shape
    ij = np.floor((pg[:, :2] - np.asarray(origin_xy, np.float64)) / cell_m).astype(np.int64)
    ij = np.clip(ij, 0, [nx - 1, ny - 1])  # rounding at the far edge
    cell = ij[:, 1] * nx + ij[:, 0]
    order = np.lexsort((pg[:, 2], cell))
    cell, z = cell[order], pg[order, 2]
    starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    counts = np.diff(np.r_[starts, len(cell)])
    median = 0.5 * (z[starts + (counts - 1) // 2] + z[starts + counts // 2])
    heights.reshape(-1)[cell[starts]] = median


# ---------------------------------------------------------------------------------------------- ground labels


def label_ground_vertices(
    vertices, faces, *, max_angle_deg: float = 30.0, cell_m: float = 1.0, layer_m: float = 0.3
) -> np.ndarray:
    """Ground labels ``(V,)`` bool for a mesh by the rule in the module docstring."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nv = len(v)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)  # (F, 3), length = 2 · area
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    vn = np.stack(
        [sum(np.bincount(f[:, k], weights=n[:, d], minlength=nv) for k in range(3)) for d in range(3)],
        axis=1,
    )  # (V, 3)
    norm = np.linalg.norm(vn, axis=1)
    flat = (norm > 0) & (vn[:, 2] >= math.cos(math.radians(max_angle_deg)) * norm)
    used = np.zeros(nv, bool)
    used[f.reshape(-1)] = True
    ij = np.floor(v[:, :2] / cell_m)
    _, cell = np.unique(tile_keys(ij[:, 0], ij[:, 1]), return_inverse=True)
    lowest = np.full(cell.max() + 1, np.inf)
    np.minimum.at(lowest, cell[used], v[used, 2])
    return flat & used & (v[:, 2] <= lowest[cell] + layer_m)


# ---------------------------------------------------------------------------------------------- the map


@runtime_checkable
class Map(Protocol):
    """What the localizer reads of a map, whether held whole (:class:`MeshMap`) or within a memory budget
    (:class:`rangemcl.maps.view.MapView`). A budgeted map (``budgeted`` true) also has the budget's
    methods (``update``, ``preload``, ``consult``, ``reserve``, ``check_budget``, ``summary``,
    ``background_points``, ``close``); a whole map has the mesh itself (``vertices``, ``faces``,
    ``is_ground``). Code asks ``budgeted``, never which methods an object happens to have."""

    budgeted: bool
    meta: dict
    ground: GroundGrid
    drive_xy: np.ndarray | None  # (K, 2) the mapping drive, if the map keeps it
    source_dir: Path | None  # the folder it was read from
    tiles: np.ndarray  # (T, 2) int32 (i, j)
    tile_size_m: float
    tile_origin_xy: np.ndarray  # (2,)

    @property
    def extent(self) -> tuple[float, float, float, float, float, float]: ...

    @property
    def n_triangles(self) -> int: ...

    def tile_at(self, x, y) -> np.ndarray: ...


@dataclass(eq=False)
class MeshMap:
    """A triangle-mesh map in the world frame, tiled (see the module docstring).

    Build one with :meth:`from_mesh` (validates and tiles), :meth:`load` or :func:`import_mesh`.
    """

    vertices: np.ndarray  # (V, 3) float64, world frame
    faces: np.ndarray  # (F, 3) int32
    is_ground: np.ndarray  # (V,) bool
    tile_size_m: float
    tile_origin_xy: np.ndarray  # (2,)
    face_tile: np.ndarray  # (F,) int32 index into `tiles`
    tiles: np.ndarray  # (T, 2) int32 (i, j)
    ground: GroundGrid
    meta: dict = field(default_factory=dict)
    drive_xy: np.ndarray | None = field(default=None, repr=False)  # (K, 2) the mapping drive, if known
    source_dir: Path | None = field(default=None, repr=False)  # the folder it was loaded from
    format_version: int = field(default=FORMAT_VERSION, repr=False)  # of that folder
    budgeted: ClassVar[bool] = False  # held whole (the Map protocol)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, np.float64)
        self.faces = np.asarray(self.faces, np.int32)
        self.is_ground = np.asarray(self.is_ground, bool)
        self.tile_size_m = float(self.tile_size_m)
        self.tile_origin_xy = np.asarray(self.tile_origin_xy, np.float64).reshape(2)
        self.face_tile = np.asarray(self.face_tile, np.int32)
        self.tiles = np.asarray(self.tiles, np.int32).reshape(-1, 2)
        if self.drive_xy is not None:
            self.drive_xy = np.asarray(self.drive_xy, np.float64).reshape(-1, 2)
        # faces grouped by tile: faces of tile k are _face_order[_tile_start[k]:_tile_start[k + 1]]
        self._face_order = np.argsort(self.face_tile, kind="stable")
        self._tile_start = np.searchsorted(self.face_tile[self._face_order], np.arange(len(self.tiles) + 1))
        keys = tile_keys(self.tiles[:, 0], self.tiles[:, 1])
        self._key_order = np.argsort(keys)
        self._keys_sorted = keys[self._key_order]

    # --- building ---------------------------------------------------------------------------------------

    @classmethod
    def from_mesh(
        cls,
        vertices,
        faces,
        is_ground=None,
        *,
        tile_size_m: float = 100.0,
        ground_cell_m: float = 1.0,
        meta: dict | None = None,
    ) -> MeshMap:
        """Validate a triangle mesh, label its ground (rule in the module docstring when ``is_ground`` is
        None), tile it and grid its ground. Problems are an :class:`InputError` naming them."""
        v, f = _validate_mesh(vertices, faces)
        meta = dict(meta or {})
        if is_ground is None:
            g = label_ground_vertices(v, f)
            meta.setdefault("ground_labels", GROUND_RULE_LABEL)
        else:
            g = np.asarray(is_ground)
            if g.shape != (len(v),):
                raise InputError(f"mesh: is_ground has shape {g.shape}, expected ({len(v)},)")
            g = g.astype(bool)
        for name, value in (("tile_size_m", tile_size_m), ("ground_cell_m", ground_cell_m)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise InputError(f"mesh: {name} must be a positive number, got {value!r}")
        tile_size_m = float(tile_size_m)
        origin = np.floor(v[:, :2].min(axis=0) / tile_size_m) * tile_size_m
        ij = face_tile_ij(v, f, origin, tile_size_m)
        keys, face_tile = np.unique(tile_keys(ij[:, 0], ij[:, 1]), return_inverse=True)
        tiles = tile_ij(keys)  # sorted by (i, j), as the keys are
        return cls(
            vertices=v,
            faces=f,
            is_ground=g,
            tile_size_m=tile_size_m,
            tile_origin_xy=origin,
            face_tile=face_tile.reshape(-1).astype(np.int32),
            tiles=tiles.astype(np.int32),
            ground=GroundGrid.from_vertices(v, g, ground_cell_m),
            meta=meta,
        )

    # --- tiles ------------------------------------------------------------------------------------------

    def tile_faces(self, tile_ids) -> np.ndarray:
        """Indices (ascending, no duplicates) of the faces in the given tiles (indices into ``tiles``)."""
        ids = np.unique(np.asarray(tile_ids, np.int64).reshape(-1))
        bad = ids[(ids < 0) | (ids >= len(self.tiles))]
        if len(bad):
            raise IndexError(f"tile index {bad[0]} out of range 0..{len(self.tiles) - 1}")
        parts = [self._face_order[self._tile_start[k] : self._tile_start[k + 1]] for k in ids]
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.intp)

    def tile_at(self, x, y) -> np.ndarray:
        """Index into ``tiles`` of the tile holding each world ``x, y``; -1 outside every non-empty tile."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        ok = np.isfinite(x) & np.isfinite(y)
        i = np.floor((np.where(ok, x, 0.0) - self.tile_origin_xy[0]) / self.tile_size_m)
        j = np.floor((np.where(ok, y, 0.0) - self.tile_origin_xy[1]) / self.tile_size_m)
        keys = tile_keys(i, j)
        pos = np.clip(np.searchsorted(self._keys_sorted, keys), 0, max(len(self._keys_sorted) - 1, 0))
        found = ok & (self._keys_sorted[pos] == keys) if len(self._keys_sorted) else np.zeros_like(ok)
        return np.where(found, self._key_order[pos], -1).astype(np.int64)

    def tile_bounds(self, k: int) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of tile ``k`` (index into ``tiles``)."""
        i, j = (int(t) for t in self.tiles[k])
        ox, oy = self.tile_origin_xy
        s = self.tile_size_m
        return (ox + i * s, oy + j * s, ox + (i + 1) * s, oy + (j + 1) * s)

    def submesh(self, tile_ids) -> tuple[np.ndarray, np.ndarray]:
        """``(vertices (n, 3) float64, faces (m, 3) int32)`` of the given tiles, with only the vertices
        those faces use (in ascending order of their index in the whole map)."""
        f = self.faces[self.tile_faces(tile_ids)]
        used, inverse = np.unique(f, return_inverse=True)
        return self.vertices[used], inverse.reshape(-1, 3).astype(np.int32)

    # --- sizes ------------------------------------------------------------------------------------------

    @property
    def extent(self) -> tuple[float, float, float, float, float, float]:
        """``(xmin, ymin, zmin, xmax, ymax, zmax)`` over all vertices."""
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        return (*(float(t) for t in lo), *(float(t) for t in hi))

    @property
    def n_triangles(self) -> int:
        return len(self.faces)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    # --- disk -------------------------------------------------------------------------------------------

    def save(self, map_dir, *, coarse_ratio: float | None = None) -> Path:
        """Write the map folder (format 2, created if needed): each tile's mesh file (and its coarse level
        when ``coarse_ratio`` is set: :mod:`rangemcl.maps.coarse`), the index, the ground grid and the
        drive, each atomically, ``map.yaml`` last; then files of an older map there (format 1's
        ``mesh.ply`` and ``tiles.npz``, tiles no longer listed) are removed."""
        from rangemcl.maps.coarse import write_with_coarse
        from rangemcl.maps.store import write_index

        map_dir = Path(map_dir)
        try:
            map_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(f"cannot write map folder {map_dir}: {err.strerror or err}") from None
        entries = []
        for k in range(len(self.tiles)):
            v, f = self.submesh([k])
            used = np.unique(self.faces[self.tile_faces([k])])
            entries.append(
                write_with_coarse(map_dir, self.tiles[k], v, f, self.is_ground[used], coarse_ratio)
            )
        write_index(map_dir, self.tile_size_m, self.tile_origin_xy, entries)
        write_map_files(
            map_dir,
            entries,
            ground=self.ground,
            drive_xy=self.drive_xy,
            tile_size_m=self.tile_size_m,
            meta=self.meta,
        )
        return map_dir

    @classmethod
    def load(cls, map_dir, *, opened: tuple | None = None) -> MeshMap:
        """Read a map folder written by :meth:`save` (format 2) or by the builders of format 1; any problem
        is an InputError naming the file. ``opened``: what :func:`open_map_folder` gave for it (read
        once per run)."""
        map_dir = Path(map_dir)
        version, doc, store = opened if opened is not None else open_map_folder(map_dir)
        counts, meta = doc["counts"], doc["meta"]
        if version == 1:
            return cls._load_v1(map_dir, counts, meta)
        v, f, g, face_tile = store.read_all()
        ground, drive = read_ground_and_drive(map_dir, doc)
        return cls(
            vertices=v,
            faces=f,
            is_ground=g,
            tile_size_m=store.tile_size_m,
            tile_origin_xy=store.origin_xy,
            face_tile=face_tile,
            tiles=store.tiles,
            ground=ground,
            meta=meta,
            drive_xy=drive,
            source_dir=map_dir,
        )

    @classmethod
    def _load_v1(cls, map_dir: Path, counts: dict, meta: dict) -> MeshMap:
        """A format-1 folder: the whole mesh in ``mesh.ply``, the tiling in ``tiles.npz``."""
        ypath = map_dir / "map.yaml"
        ppath = map_dir / "mesh.ply"
        vertices, faces, colours = read_ply_binary(ppath)
        if colours is None:
            raise InputError(f"{ppath}: vertices have no red, green, blue colours (the ground labels)")
        is_ground = np.all(colours == GROUND_RGB, axis=1)
        for what, found, key in (
            ("vertices", len(vertices), "vertices"),
            ("triangles", len(faces), "triangles"),
            ("ground vertices", int(is_ground.sum()), "ground_vertices"),
        ):
            if found != counts[key]:
                raise InputError(f"{ppath}: has {found} {what} but {ypath.name} says {counts[key]}")
        try:
            v, f = _validate_mesh(vertices, faces)
        except InputError as err:
            raise InputError(f"{ppath}: {str(err).removeprefix('mesh: ')}") from None

        tpath = map_dir / "tiles.npz"
        t = _read_npz(
            tpath, {"tile_size_m": (), "tile_origin_xy": (2,), "tiles": (-1, 2), "face_tile": (-1,)}
        )
        tile_size = float(t["tile_size_m"])
        if not (math.isfinite(tile_size) and tile_size > 0):
            raise InputError(f"{tpath}: tile_size_m must be positive, got {tile_size}")
        if len(t["face_tile"]) != len(f):
            raise InputError(
                f"{tpath}: face_tile has {len(t['face_tile'])} entries but mesh.ply has {len(f)} faces"
            )
        if len(t["tiles"]) != counts["tiles"]:
            raise InputError(f"{tpath}: has {len(t['tiles'])} tiles but {ypath.name} says {counts['tiles']}")
        face_tile = t["face_tile"].astype(np.int64)
        if len(face_tile) and (face_tile.min() < 0 or face_tile.max() >= len(t["tiles"])):
            raise InputError(f"{tpath}: face_tile indices out of range 0..{len(t['tiles']) - 1}")
        origin = t["tile_origin_xy"].astype(np.float64)
        if not _tiling_matches(t["tiles"], face_tile, v, f, origin, tile_size):
            raise InputError(f"{tpath}: the tiling does not match the faces' centroids in mesh.ply")

        ground, drive = read_ground_and_drive(map_dir)
        return cls(
            vertices=v,
            faces=f,
            is_ground=is_ground,
            tile_size_m=tile_size,
            tile_origin_xy=origin,
            face_tile=face_tile,
            tiles=t["tiles"],
            ground=ground,
            meta=meta,
            drive_xy=drive,
            source_dir=map_dir,
            format_version=1,
        )


def read_map_yaml(map_dir: Path) -> tuple[int, dict]:
    """``(format_version, document)`` of a map folder's ``map.yaml`` after checking that the folder and the
    files of its format are there; ``document["counts"]`` and ``document["meta"]`` are checked mappings."""
    if not map_dir.exists():
        raise InputError(f"{map_dir}: map folder does not exist")
    if not map_dir.is_dir():
        raise InputError(f"{map_dir}: not a folder (expected a map folder)")
    ypath = map_dir / "map.yaml"
    if not ypath.is_file():
        raise InputError(f"{ypath}: missing (is {map_dir} a map folder?)")
    doc = parse_yaml(read_text(ypath), str(ypath))
    if not isinstance(doc, dict):
        raise InputError(f"{ypath}: expected a mapping at the top level")
    version = doc.get("format_version")
    if version not in (1, FORMAT_VERSION) or isinstance(version, bool):
        raise InputError(
            f"{ypath}: format_version {version!r} is not supported (expected 1 or {FORMAT_VERSION})"
        )
    for name in MAP_FILES_V1 if version == 1 else MAP_FILES:
        if not (map_dir / name).is_file():
            raise InputError(f"{map_dir / name}: missing (is {map_dir} a map folder?)")
    counts = doc.get("counts")
    if not isinstance(counts, dict) or not all(
        isinstance(counts.get(k), int) for k in ("vertices", "triangles", "ground_vertices", "tiles")
    ):
        raise InputError(
            f"{ypath}: 'counts' must map vertices, triangles, ground_vertices, tiles to integers"
        )
    meta = doc.get("meta") or {}
    if not isinstance(meta, dict):
        raise InputError(f"{ypath}: 'meta' must be a mapping")
    doc["meta"] = meta
    return int(version), doc


def open_map_folder(map_dir) -> tuple[int, dict, Any]:
    """``(format_version, map.yaml's document, tile index)`` of a map folder, each checked (the index,
    a :class:`~rangemcl.maps.store.TileStore`, against map.yaml's counts; None for format 1): what
    :meth:`MeshMap.load` and :class:`rangemcl.maps.view.MapView` start from, read once."""
    map_dir = Path(map_dir)
    version, doc = read_map_yaml(map_dir)
    store = open_checked_store(map_dir, doc["counts"]) if version >= 2 else None
    return version, doc, store


def open_checked_store(map_dir: Path, counts: dict):
    """The tile index of a format-2 map folder (:class:`~rangemcl.maps.store.TileStore`), its counts
    checked against ``map.yaml``'s ``counts``."""
    from rangemcl.maps.store import INDEX_NAME, TileStore

    store = TileStore.open(map_dir)
    ipath = Path(map_dir) / INDEX_NAME
    for what, found, key in (
        ("tiles", len(store.entries), "tiles"),
        ("vertices", store.n_vertices, "vertices"),
        ("triangles", store.n_triangles, "triangles"),
        ("ground vertices", sum(e.ground_vertices for e in store.entries), "ground_vertices"),
    ):
        if found != counts[key]:
            raise InputError(f"{ipath}: lists {found} {what} but map.yaml says {counts[key]}")
    return store


def read_ground_and_drive(map_dir: Path, doc: dict | None = None) -> tuple[GroundGrid, np.ndarray | None]:
    """The ground grid and the mapping drive of a map folder, each checked against the sha256 that
    ``map.yaml`` (``doc``) lists for it (maps written before the checksums were kept list none)."""
    gpath = map_dir / "ground.npz"
    gz = _read_npz(gpath, {"origin_xy": (2,), "cell_m": (), "heights": (-1, -1)})
    try:
        ground = GroundGrid(gz["origin_xy"], float(gz["cell_m"]), gz["heights"])
    except ValueError as err:
        raise InputError(f"{gpath}: {err}") from None
    drive = None
    dpath = map_dir / "drive.npz"
    if dpath.is_file():
        drive = _read_npz(dpath, {"xy": (-1, 2)})["xy"].astype(np.float64)
        if not np.isfinite(drive).all():
            raise InputError(f"{dpath}: xy holds non-finite values")
    # readable is not enough: a byte outside the arrays (which zip's CRC does not cover), or the file of
    # another map
    sums = (doc or {}).get("sha256") or {}
    if not isinstance(sums, dict):
        raise InputError(f"{map_dir / 'map.yaml'}: 'sha256' must map file names to checksums")
    for name, want in sums.items():
        path = map_dir / str(name)
        if path.is_file() and file_sha256(path) != want:
            raise InputError(
                f"{path}: does not match its checksum in map.yaml (damaged?); rebuild the map, or copy the "
                "file again from where the map came from"
            )
    return ground, drive


def write_map_files(
    map_dir: Path, entries, *, ground: GroundGrid, drive_xy, tile_size_m: float, meta: dict
) -> dict:
    """After the tiles and ``tiles.json``: ``ground.npz``, ``drive.npz`` and ``map.yaml`` (last, format 2),
    then the files of an older map in the folder are removed. Returns the counts written."""
    from rangemcl.maps.store import COARSE_DIR, INDEX_NAME, TILE_DIR

    atomic_write(
        map_dir / "ground.npz",
        lambda fh: savez_stable(
            fh, origin_xy=ground.origin_xy, cell_m=np.float64(ground.cell_m), heights=ground.heights
        ),
    )
    files = {"index": INDEX_NAME, "tiles": f"{TILE_DIR}/", "ground": "ground.npz"}
    if drive_xy is not None:
        atomic_write(map_dir / "drive.npz", lambda fh: savez_stable(fh, xy=np.asarray(drive_xy, np.float64)))
        files["drive"] = "drive.npz"
    sums = {name: file_sha256(map_dir / name) for name in (files["ground"], files.get("drive")) if name}
    counts = {
        "vertices": sum(e.vertices for e in entries),
        "triangles": sum(e.triangles for e in entries),
        "ground_vertices": sum(e.ground_vertices for e in entries),
        "tiles": len(entries),
    }
    b = np.array([e.bounds for e in entries])
    extent = (*b[:, :3].min(axis=0).tolist(), *b[:, 3:].max(axis=0).tolist())
    text = map_yaml_text(files, counts, tile_size_m, ground.cell_m, extent, meta, sums)
    from rangemcl.common.pool import kill_point

    kill_point("map-files")  # tests: killed with every file but map.yaml written
    atomic_write(map_dir / "map.yaml", lambda fh: fh.write(text.encode()))
    # the map is complete: what an older map left here goes
    for name in ("mesh.ply", "tiles.npz"):
        (map_dir / name).unlink(missing_ok=True)
    listed = {e.file for e in entries} | {e.coarse.file for e in entries if e.coarse is not None}
    for folder in (TILE_DIR, COARSE_DIR):
        for path in (map_dir / folder).glob("*.npz"):
            if f"{folder}/{path.name}" not in listed:
                path.unlink(missing_ok=True)
    return counts


def map_yaml_text(
    files: dict,
    counts: dict,
    tile_size_m: float,
    ground_cell_m: float,
    extent,
    meta,
    sha256: dict | None = None,
) -> str:
    """The text of a map folder's ``map.yaml`` (written last: its presence marks a complete folder);
    ``sha256``: the checksums of the ground grid and the drive file (the tiles' are in the index)."""
    doc = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "files": files,
        "counts": counts,
        "tile_size_m": float(tile_size_m),
        "ground_cell_m": float(ground_cell_m),
        "extent_m": [float(x) for x in extent],
        "sha256": dict(sha256 or {}),
        "meta": _plain(meta),
    }
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


_CHUNK_FACES = 1 << 20  # faces per pass of the whole-mesh checks: bounds their temporaries (about 70 MB)


def face_tile_ij(vertices: np.ndarray, faces: np.ndarray, origin_xy, tile_size_m: float) -> np.ndarray:
    """``(F, 2)`` int64 tile grid indices (i, j) of each face's centroid (computed a chunk of faces at a
    time, so the temporaries stay small for maps of millions of triangles)."""
    out = np.empty((len(faces), 2), np.int64)
    origin = np.asarray(origin_xy, np.float64)
    for a in range(0, len(faces), _CHUNK_FACES):
        tri = vertices[faces[a : a + _CHUNK_FACES], :2]  # (n, 3, 2)
        centroid = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3.0
        out[a : a + len(tri)] = np.floor((centroid - origin) / tile_size_m)
    return out


def _tiling_matches(tiles: np.ndarray, face_tile: np.ndarray, v, f, origin, tile_size: float) -> bool:
    """Whether every face's stored tile is the tile of its centroid (chunk by chunk)."""
    for a in range(0, len(f), _CHUNK_FACES):
        b = a + _CHUNK_FACES
        if not np.array_equal(tiles[face_tile[a:b]], face_tile_ij(v, f[a:b], origin, tile_size)):
            return False
    return True


def tile_keys(i, j) -> np.ndarray:
    """One sortable int64 per (i, j) grid index pair (indices clipped to ±2**30)."""
    lim = 2**30
    i = np.clip(np.asarray(i, np.float64), -lim, lim - 1).astype(np.int64) + lim
    j = np.clip(np.asarray(j, np.float64), -lim, lim - 1).astype(np.int64) + lim
    return i * (2 * lim) + j


def tile_ij(keys: np.ndarray) -> np.ndarray:
    """Inverse of :func:`tile_keys`: ``(n, 2)`` int64 (i, j)."""
    lim = 2**30
    return np.stack([keys // (2 * lim) - lim, keys % (2 * lim) - lim], axis=1)


def _validate_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Checked ``(vertices float64 (V, 3), faces int32 (F, 3))`` or an InputError naming the problem."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.size == 0 or f.size == 0:
        raise InputError(f"mesh: empty mesh ({len(v)} vertices, {len(f)} triangles)")
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"mesh: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"mesh: faces must have shape (F, 3) (triangles), got {f.shape}")
    if not np.issubdtype(v.dtype, np.number):
        raise InputError(f"mesh: vertices must be numbers, got {v.dtype}")
    whole = np.issubdtype(f.dtype, np.floating) and np.all(f == np.round(f))
    if not (np.issubdtype(f.dtype, np.integer) or whole):
        raise InputError(f"mesh: face indices must be integers, got {f.dtype}")
    v = np.asarray(v, np.float64)  # no copy when it is float64 already
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise InputError(
            f"mesh: {int(bad.sum())} vertices are NaN or infinite (first: vertex {np.argmax(bad)})"
        )
    lo, hi = f.min(), f.max()
    if lo < 0 or hi >= len(v):
        raise InputError(f"mesh: face indices out of range 0..{len(v) - 1} (found {lo:g}..{hi:g})")
    f32 = np.asarray(f, np.int32)  # no copy when it is int32 already
    # at least one triangle with an area; a chunk at a time (the whole mesh's corners would be 72 B a face)
    for a in range(0, len(f32), _CHUNK_FACES):
        tri = v[f32[a : a + _CHUNK_FACES]]
        if (np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 0).any():
            break
    else:
        raise InputError(f"mesh: all {len(f)} triangles are degenerate (zero area)")
    return v, f32


# ---------------------------------------------------------------------------------------------- import


def import_mesh(path, *, tile_size_m: float = 100.0, is_ground=None, meta: dict | None = None) -> MeshMap:
    """A map from any triangle mesh file trimesh reads (PLY, OBJ, STL, …; e.g. published range-mcl maps).

    Ground labels: ``is_ground`` when given; else the vertex colours when every vertex is coloured either
    our ground or our non-ground colour (a mesh written by :meth:`MeshMap.save`); else the rule of
    :func:`label_ground_vertices`. ``meta`` is merged over ``source_mesh`` and ``created_by``. Errors name
    the file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: mesh file does not exist")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises anything on a broken file
        why = " ".join(str(err).split()) or type(err).__name__
        raise InputError(f"{path}: cannot read as a triangle mesh: {why}") from None
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise InputError(f"{path}: holds no triangles (a point cloud or an empty mesh?)")
    vertices = np.asarray(mesh.vertices, np.float64)
    base = {"source_mesh": str(path), "created_by": "rangemcl import-mesh"}
    if is_ground is None:
        rgb = _vertex_rgb(mesh)
        if rgb is not None and len(rgb) == len(vertices):
            ground = np.all(rgb == GROUND_RGB, axis=1)
            if np.all(ground | np.all(rgb == NON_GROUND_RGB, axis=1)):
                is_ground = ground
                base["ground_labels"] = "vertex colours"
    try:
        return MeshMap.from_mesh(
            vertices, np.asarray(faces), is_ground, tile_size_m=tile_size_m, meta={**base, **(meta or {})}
        )
    except InputError as err:
        raise InputError(f"{path}: {str(err).removeprefix('mesh: ')}") from None


def _vertex_rgb(mesh) -> np.ndarray | None:
    visual = getattr(mesh, "visual", None)
    if visual is None or getattr(visual, "kind", None) != "vertex":
        return None
    return np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)


# ---------------------------------------------------------------------------------------------- summary


def map_summary(m: MeshMap) -> dict[str, Any]:
    """Plain figures about a map for ``rangemcl map-info`` (keys in print order)."""
    xmin, ymin, zmin, xmax, ymax, zmax = m.extent
    g = m.ground
    out: dict[str, Any] = {}
    if m.source_dir is not None:
        out["map_dir"] = str(m.source_dir)
    out["size_m"] = f"{xmax - xmin:.1f} x {ymax - ymin:.1f} x {zmax - zmin:.1f}"
    out["extent_m"] = f"x [{xmin:.2f}, {xmax:.2f}]  y [{ymin:.2f}, {ymax:.2f}]  z [{zmin:.2f}, {zmax:.2f}]"
    out["triangles"] = m.n_triangles
    out["vertices"] = m.n_vertices
    out["ground_vertex_share"] = round(float(m.is_ground.mean()), 4)
    out["ground_triangle_share"] = round(float(m.is_ground[m.faces].all(axis=1).mean()), 4)
    out["tiles"] = len(m.tiles)
    out["tile_size_m"] = m.tile_size_m
    per_tile = np.bincount(m.face_tile, minlength=len(m.tiles))
    out["triangles_per_tile"] = (
        f"min {per_tile.min()}, median {int(np.median(per_tile))}, max {per_tile.max()}"
    )
    ny, nx = g.shape
    out["ground_grid"] = f"{nx} x {ny} cells of {g.cell_m:g} m, {g.measured.mean():.0%} measured"
    if m.source_dir is not None:
        files = [m.source_dir / n for n in {*MAP_FILES, *MAP_FILES_V1, "drive.npz"}]
        files += list((m.source_dir / "tiles").glob("*.npz"))
        out["bytes_on_disk"] = sum(p.stat().st_size for p in files if p.is_file())
        out["format_version"] = m.format_version
    for key in (
        "frame",
        "sensor_height_m",
        "created_by",
        "source_sequence",
        "source_mesh",
        "scene",
        "sensor",
    ):
        if m.meta.get(key) is not None:
            out[key] = m.meta[key]
    return out


def thin_path(xy, spacing_m: float) -> np.ndarray:
    """The points of a path ``(N, 2)`` kept so that consecutive kept points are at least ``spacing_m``
    apart (the first and last point always kept); non-finite points are dropped."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy) <= 2:
        return xy.copy()
    keep = [0]
    last = xy[0]
    for k in range(1, len(xy) - 1):
        if np.hypot(*(xy[k] - last)) >= spacing_m:
            keep.append(k)
            last = xy[k]
    keep.append(len(xy) - 1)
    return xy[keep]


# ---------------------------------------------------------------------------------------------- file helpers


def _read_npz(path: Path, shapes: dict[str, tuple]) -> dict[str, np.ndarray]:
    """The named arrays of an npz file, checked against shapes (-1: any length)."""
    try:
        with open(path, "rb") as fh:
            is_zip = fh.read(2) == b"PK"
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror or err}") from None
    if not is_zip:  # else numpy would try it as a pickle, and say so
        raise InputError(f"{path}: cannot read: not an .npz file (damaged, or another kind of file)")
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in shapes if k in z.files}
    except Exception as err:  # zipfile, pickle and format errors all mean a broken file
        raise InputError(f"{path}: cannot read: {' '.join(str(err).split()) or type(err).__name__}") from None
    for key, shape in shapes.items():
        if key not in out:
            raise InputError(f"{path}: lacks the array '{key}'")
        a = out[key]
        if a.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, a.shape, strict=True)):
            raise InputError(f"{path}: '{key}' has shape {a.shape}, expected {shape}")
        if not np.issubdtype(a.dtype, np.number):
            raise InputError(f"{path}: '{key}' is not numeric ({a.dtype})")
    return out


def _plain(x):
    """Meta as plain YAML types (numpy scalars and arrays, paths and tuples converted)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if x is None or isinstance(x, bool | int | float | str):
        return x
    return str(x)


def read_drive_xy(path, spacing_m: float = 1.0) -> np.ndarray:
    """Where the car drives in a map without a mapping drive (an imported mesh), from a text file: ``x y``
    per line (a waypoint file, ``simbed export-mesh --route-out``), or poses, KITTI (12 numbers a line) or
    TUM (``t x y z qx qy qz qw``); thinned to a point every ``spacing_m``. Global localization spreads its
    particles and renders its place prior within ``init.drive_radius_m`` of it. A malformed line is an
    InputError naming the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        why = err.strerror if isinstance(err, OSError) else "not a text file"
        raise InputError(f"{path}: cannot read the drive ({why or err})") from None
    rows = []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#")[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            v = [float(x) for x in line.split()]
        except ValueError:
            raise InputError(f"{path}:{n}: expected numbers, got {raw.strip()!r}") from None
        if len(v) in (2, 3):
            xy = v[:2]
        elif len(v) == 12:  # KITTI: a 3x4 matrix, row by row
            xy = [v[3], v[7]]
        elif len(v) == 8:  # TUM
            xy = v[1:3]
        else:
            raise InputError(
                f"{path}:{n}: expected 'x y', a KITTI pose (12 numbers) or a TUM pose (8), "
                f"got {len(v)} numbers"
            )
        if not np.isfinite(xy).all():
            raise InputError(f"{path}:{n}: not finite: {raw.strip()!r}")
        rows.append(xy)
    if len(rows) < 2:
        raise InputError(f"{path}: a drive needs at least two points, found {len(rows)}")
    return thin_path(np.asarray(rows, np.float64), spacing_m)
