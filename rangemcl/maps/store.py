"""The map store of tiles: one mesh file per tile and an index, read tile by tile.

A map folder of format 2 holds::

    map.yaml        format, format_version 2, files, counts, tile size, extent, meta (written last: its
                    presence marks a complete folder)
    tiles.json      the index: format, version, tile_size_m, tile_origin_xy and one entry per tile (grid
                    index ij, file, vertices, triangles, ground_vertices, bounds [xmin, ymin, zmin, xmax,
                    ymax, zmax], bytes, sha256), sorted by (i, j)
    tiles/I_J.npz   tile (I, J): vertices (V, 3) float64 world, faces (F, 3) int32 into them, is_ground (V,)
                    bool; deflated numpy ``.npz`` with fixed zip timestamps (the same tile gives the same
                    bytes, so two builds compare by checksum)
    ground.npz      the ground-height grid, as in format 1; drive.npz (optional) likewise

A tile holds the faces whose centroid lies in it (the rule of :mod:`rangemcl.maps.meshmap`) and only the
vertices those faces use, in the order of the whole map; a vertex shared by faces of two tiles is in both
files with the same float64 value, so the tiles' union casts exactly the rays the whole mesh casts.

Why ``.npz`` (``docs/architecture.md``, "Design decisions and why"): measured against PLY through Open3D
and trimesh on ``town_large``'s tiles, a deflated npz reads in 12-18 ms a 150k-triangle tile, is exact in
float64 (Open3D's tensor reader returns float32 positions, trimesh writes float32) and 3.3× smaller than
PLY; zip's CRC-32 turns a truncated or damaged file into an error, and the index's sha256 a tile of
another map or build.

:class:`TileStore` opens a folder by reading ``map.yaml`` and ``tiles.json`` only; :meth:`TileStore.read`
reads one tile, checked against its index entry; a missing, truncated or corrupt tile is one
:class:`~rangemcl.errors.InputError` naming the file, and the other tiles stay readable.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write, savez_stable
from rangemcl.errors import InputError

INDEX_NAME = "tiles.json"
INDEX_FORMAT = "rangemcl-tile-index"
STORE_VERSION = 2
TILE_DIR = "tiles"
COARSE_DIR = "coarse"  # the coarse level: a decimated copy of each tile (rangemcl.maps.coarse)


@dataclass(frozen=True)
class TileEntry:
    """One tile of the index."""

    ij: tuple[int, int]
    file: str  # relative to the map folder
    vertices: int
    triangles: int
    ground_vertices: int
    bounds: tuple[float, float, float, float, float, float]  # xmin, ymin, zmin, xmax, ymax, zmax
    bytes: int
    sha256: str
    coarse: TileEntry | None = None  # the tile's coarse level, when the map has one

    def as_json(self) -> dict:
        doc = {
            "ij": list(self.ij),
            "file": self.file,
            "vertices": self.vertices,
            "triangles": self.triangles,
            "ground_vertices": self.ground_vertices,
            "bounds": list(self.bounds),
            "bytes": self.bytes,
            "sha256": self.sha256,
        }
        if self.coarse is not None:
            doc["coarse"] = {k: v for k, v in self.coarse.as_json().items() if k != "ij"}
        return doc

    @classmethod
    def from_json(cls, t: dict, ij=None) -> TileEntry:
        ij = t["ij"] if ij is None else ij
        return cls(
            ij=(int(ij[0]), int(ij[1])),
            file=str(t["file"]),
            vertices=int(t["vertices"]),
            triangles=int(t["triangles"]),
            ground_vertices=int(t["ground_vertices"]),
            bounds=tuple(float(x) for x in t["bounds"]),
            bytes=int(t["bytes"]),
            sha256=str(t["sha256"]),
            coarse=None if t.get("coarse") is None else cls.from_json(t["coarse"], ij),
        )


def tile_file(i: int, j: int, *, coarse: bool = False) -> str:
    """The file of tile (i, j) (or of its coarse level), relative to the map folder."""
    return f"{COARSE_DIR if coarse else TILE_DIR}/{int(i)}_{int(j)}.npz"


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_tile(map_dir, ij, vertices, faces, is_ground, *, coarse: bool = False) -> TileEntry:
    """Write tile ``ij``'s mesh (or its coarse level) into ``map_dir`` (atomically) and return its index
    entry."""
    map_dir = Path(map_dir)
    v = np.ascontiguousarray(vertices, np.float64).reshape(-1, 3)
    f = np.ascontiguousarray(faces, np.int32).reshape(-1, 3)
    g = np.ascontiguousarray(is_ground, bool).reshape(-1)
    if len(g) != len(v) or len(f) == 0:
        raise ValueError(f"tile {ij}: {len(v)} vertices, {len(g)} labels, {len(f)} faces")
    name = tile_file(*ij, coarse=coarse)
    path = map_dir / name
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: savez_stable(fh, compressed=True, vertices=v, faces=f, is_ground=g))
    lo, hi = v.min(axis=0), v.max(axis=0)
    return TileEntry(
        ij=(int(ij[0]), int(ij[1])),
        file=name,
        vertices=len(v),
        triangles=len(f),
        ground_vertices=int(g.sum()),
        bounds=(*(float(x) for x in lo), *(float(x) for x in hi)),
        bytes=path.stat().st_size,
        sha256=file_sha256(path),
    )


def write_index(map_dir, tile_size_m: float, origin_xy, entries: list[TileEntry]) -> Path:
    """Write ``tiles.json`` (atomically), the entries sorted by (i, j)."""
    doc = {
        "format": INDEX_FORMAT,
        "version": STORE_VERSION,
        "tile_size_m": float(tile_size_m),
        "tile_origin_xy": [float(x) for x in np.asarray(origin_xy, np.float64).reshape(2)],
        "tiles": [e.as_json() for e in sorted(entries, key=lambda e: e.ij)],
    }
    return atomic_write(Path(map_dir) / INDEX_NAME, json.dumps(doc, indent=1) + "\n")


class TileStore:
    """A format-2 map folder's tiles: the index in memory, each tile read on demand (module docstring)."""

    def __init__(self, map_dir, tile_size_m: float, origin_xy, entries: list[TileEntry]):
        self.map_dir = Path(map_dir)
        self.tile_size_m = float(tile_size_m)
        self.origin_xy = np.asarray(origin_xy, np.float64).reshape(2)
        self.entries = list(entries)

    @classmethod
    def open(cls, map_dir) -> TileStore:
        """Read the index ``tiles.json`` of ``map_dir`` (no tile is read); problems name the file."""
        path = Path(map_dir) / INDEX_NAME
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{path}: missing (is {path.parent} a map folder?)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise InputError(f"{path}: cannot read the tile index: {err}") from None
        if not isinstance(doc, dict) or doc.get("format") != INDEX_FORMAT:
            raise InputError(f"{path}: not a tile index (format {INDEX_FORMAT!r} expected)")
        if doc.get("version") != STORE_VERSION:
            raise InputError(f"{path}: version {doc.get('version')!r} is not supported ({STORE_VERSION})")
        try:
            size = float(doc["tile_size_m"])
            origin = [float(x) for x in doc["tile_origin_xy"]]
            entries = [TileEntry.from_json(t) for t in doc["tiles"]]
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise InputError(f"{path}: malformed tile index: {type(err).__name__} {err}") from None
        if not (math.isfinite(size) and size > 0) or len(origin) != 2:
            raise InputError(f"{path}: tile_size_m must be positive and tile_origin_xy two numbers")
        if not entries:
            raise InputError(f"{path}: the index lists no tile")
        ij = [e.ij for e in entries]
        if ij != sorted(set(ij)):
            raise InputError(f"{path}: tiles must be listed once each, sorted by (i, j)")
        for e in [*entries, *(e.coarse for e in entries if e.coarse is not None)]:
            if len(e.bounds) != 6 or Path(e.file).is_absolute() or ".." in Path(e.file).parts:
                raise InputError(f"{path}: tile {e.ij}: bad bounds or file name {e.file!r}")
        return cls(path.parent, size, origin, entries)

    @property
    def tiles(self) -> np.ndarray:
        """``(T, 2)`` int32 grid indices (i, j), sorted."""
        return np.array([e.ij for e in self.entries], np.int32).reshape(-1, 2)

    @property
    def n_triangles(self) -> int:
        return sum(e.triangles for e in self.entries)

    @property
    def n_vertices(self) -> int:
        return sum(e.vertices for e in self.entries)

    @property
    def bytes_on_disk(self) -> int:
        return sum(e.bytes for e in self.entries)

    def extent(self) -> tuple[float, float, float, float, float, float]:
        b = np.array([e.bounds for e in self.entries])
        return (*(float(x) for x in b[:, :3].min(axis=0)), *(float(x) for x in b[:, 3:].max(axis=0)))

    @property
    def has_coarse(self) -> bool:
        """Whether every tile has a coarse level."""
        return all(e.coarse is not None for e in self.entries)

    def read(
        self, k: int, *, verify: bool = True, coarse: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tile ``k`` (index into ``entries``), or its coarse level: ``(vertices float64 (V, 3), faces int32
        (F, 3), is_ground bool (V,))``, checked against its index entry (counts, sha256 when ``verify``,
        face indices, finite vertices, the centroid rule; a coarse level's faces may straddle the border
        by a little); any problem is an InputError naming the file."""
        e = self.entries[k]
        if coarse:
            if e.coarse is None:
                raise InputError(f"{self.map_dir}: tile {e.ij} has no coarse level (rangemcl map-coarse)")
            e = e.coarse
        path = self.map_dir / e.file
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise InputError(f"{path}: tile {e.ij} is missing") from None
        except OSError as err:
            raise InputError(f"{path}: cannot read tile {e.ij}: {err.strerror or err}") from None
        if size != e.bytes:
            raise InputError(f"{path}: tile {e.ij} has {size} bytes, the index says {e.bytes} (truncated?)")
        if verify and file_sha256(path) != e.sha256:
            raise InputError(f"{path}: tile {e.ij} does not match its checksum in {INDEX_NAME} (damaged?)")
        try:
            with np.load(path, allow_pickle=False) as z:
                v = np.asarray(z["vertices"], np.float64)
                f = np.asarray(z["faces"], np.int32)
                g = np.asarray(z["is_ground"], bool)
        except Exception as err:  # zipfile, format and key errors all mean a broken file
            why = " ".join(str(err).split()) or type(err).__name__
            raise InputError(f"{path}: cannot read tile {e.ij}: {why}") from None
        if v.shape != (e.vertices, 3) or f.shape != (e.triangles, 3) or g.shape != (e.vertices,):
            raise InputError(
                f"{path}: tile {e.ij} holds {v.shape} vertices, {f.shape} faces, {g.shape} labels; the "
                f"index says {e.vertices} vertices and {e.triangles} triangles"
            )
        if int(g.sum()) != e.ground_vertices:
            raise InputError(
                f"{path}: tile {e.ij} has {int(g.sum())} ground vertices, the index says {e.ground_vertices}"
            )
        if not np.isfinite(v).all():
            raise InputError(f"{path}: tile {e.ij} has NaN or infinite vertices")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise InputError(f"{path}: tile {e.ij}: face indices out of range 0..{len(v) - 1}")
        if coarse:
            return v, f, g
        tri = v[f, :2]
        centroid = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3.0
        ij = np.floor((centroid - self.origin_xy) / self.tile_size_m)
        if not (ij == np.asarray(e.ij, np.float64)).all():
            raise InputError(f"{path}: tile {e.ij} holds faces whose centroids lie outside it")
        return v, f, g

    def read_all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The whole map as one mesh: ``(vertices, faces, is_ground, face_tile)``, the tiles' meshes
        concatenated in index order (a vertex shared by two tiles appears once per tile)."""
        vs, fs, gs, ts = [], [], [], []
        offset = 0
        for k in range(len(self.entries)):
            v, f, g = self.read(k)
            vs.append(v)
            fs.append(f + np.int32(offset))
            gs.append(g)
            ts.append(np.full(len(f), k, np.int32))
            offset += len(v)
        return np.concatenate(vs), np.concatenate(fs), np.concatenate(gs), np.concatenate(ts)
