"""What each surface of a scene is made of, as the LiDAR's return model needs it.

A :class:`Material` is four numbers at the sensor's wavelength (about 905 nm): diffuse ``reflectivity``,
specular ``mirror`` reflectance, ``retro``-reflection and ``transmission`` (their meaning and the default
table with sources: ``simbed/sim/materials.yaml``; ``docs/testbed.md``, "Materials").

:class:`SceneMaterials` gives every ray hit its material. Each geom of the scene gets one, resolved in this
order (the first that applies):

1. the scene's sidecar ``<scene>.materials.yaml``: ``geoms`` (glob on the geom's name, or its body's, to a
   material), then ``mjcf_materials`` (an MJCF material's name to a material);
2. the geom's MJCF material: a table entry of that name, the generated towns' names (``road``, ``wall``,
   ``building2``, ...: :data:`TOWN_MATERIALS`), or the longest table name it contains (``old_asphalt`` is
   asphalt);
3. what the geom is in a generated town: a parked car's body is car paint whose diffuse reflectivity
   follows its colour, its cabin glass; a moving actor's car body car paint, its cabin glass, a person or
   cyclist fabric;
4. the sidecar's ``default``, else ``unknown`` (a mid-grey diffuse surface).

Some surfaces vary across one geom; they are patterns evaluated at the hit point:

* a generated town's terrain takes its material from its painted ground texture (asphalt, parking,
  sidewalk, grass);
* a generated town's road surfaces carry lane markings (a dashed centre line and solid edge lines, from
  the road graph): :class:`RoadMarkings`;
* a generated town's buildings have windows (glass) in a grid of floors and bays on every façade:
  :class:`WindowGrid`.

The sidecar's format (every key optional)::

    default: concrete               # the material of geoms nothing else names
    materials:                      # new table entries, or new values for existing ones
      tinted_glass: {reflectivity: 0.0, mirror: 0.05, transmission: 0.6}
    mjcf_materials:                 # MJCF material name -> table entry
      facade: brick
    geoms:                          # geom or body name (glob) -> table entry; the first match wins
      "shop_window_*": glass
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from rangemcl.common.yamlio import parse_yaml, read_text
from rangemcl.errors import InputError
from simbed.scenes.towngen.mjcf import ASPHALT_RGB, GRASS_RGB, PARKING_RGB, SIDEWALK_RGB

TABLE_FILE = Path(__file__).with_name("materials.yaml")
MATERIAL_KEYS = ("reflectivity", "mirror", "retro", "transmission", "source")
UNKNOWN = "unknown"

# The generated towns' MJCF material names (simbed.scenes.towngen.mjcf) and what they are made of.
TOWN_MATERIALS = {
    "road": "asphalt",
    "junction": "asphalt",
    "wall": "concrete",
    "pole": "steel",
    "trunk": "bark",
    "crown": "vegetation",
    "building0": "plaster",
    "building1": "concrete",
    "building2": "brick",
    "building3": "plaster",
    "building4": "concrete",
}
TOWN_TERRAIN_MATERIAL = "terrain"  # the towns' terrain material: its texture says what lies where

# The towns' ground texture colours (simbed.scenes.towngen.mjcf paints them) and their materials; grass
# is shaded by the relief, so each pixel takes the material of the nearest reference colour.
GROUND_COLOURS = {
    ASPHALT_RGB: "asphalt",
    PARKING_RGB: "asphalt",
    SIDEWALK_RGB: "concrete",
    GRASS_RGB: "grass",
}

# Car paint: the diffuse part of its reflectance follows the pigment. A car's colour stands in for it:
# reflectivity = CAR_PAINT_DARK + (CAR_PAINT_LIGHT - CAR_PAINT_DARK) x relative luminance, in steps of
# CAR_PAINT_STEP (an assumption: near-infrared and visible reflectance of paints correlate loosely).
CAR_PAINT_DARK = 0.05
CAR_PAINT_LIGHT = 0.70
CAR_PAINT_STEP = 0.05

PATTERN_NONE, PATTERN_GROUND, PATTERN_WINDOWS = 0, 1, 2


@dataclass(frozen=True)
class Material:
    """A surface at the LiDAR's wavelength (see ``materials.yaml`` for the meaning of each number)."""

    name: str
    reflectivity: float  # diffuse (Lambertian) reflectance, 0..1
    mirror: float = 0.0  # specular reflectance, 0..1
    retro: float = 0.0  # retro-reflection, as an equivalent diffuse reflectivity at normal incidence
    transmission: float = 0.0  # share passing through, each way, 0..1
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        for key in ("reflectivity", "mirror", "transmission"):
            value = getattr(self, key)
            if not (isinstance(value, float | int) and 0.0 <= value <= 1.0):
                raise InputError(f"material {self.name!r}: {key} must be a number in [0, 1], got {value!r}")
        if not (isinstance(self.retro, float | int) and 0.0 <= self.retro < math.inf):
            raise InputError(f"material {self.name!r}: retro must be a number >= 0, got {self.retro!r}")
        if self.reflectivity + self.mirror + self.transmission > 1.0 + 1e-9:
            raise InputError(
                f"material {self.name!r}: reflectivity + mirror + transmission is "
                f"{self.reflectivity + self.mirror + self.transmission:.3g} (> 1: more light than arrives)"
            )


def _material(name: str, entry: Any, where: str) -> Material:
    if not isinstance(entry, dict):
        raise InputError(f"{where}: material {name!r} must be a mapping of {', '.join(MATERIAL_KEYS)}")
    unknown = sorted(set(entry) - set(MATERIAL_KEYS))
    if unknown:
        raise InputError(
            f"{where}: material {name!r}: unknown key {unknown[0]!r} (keys: {', '.join(MATERIAL_KEYS)})"
        )
    if "reflectivity" not in entry:
        raise InputError(f"{where}: material {name!r} has no reflectivity")
    values = {k: entry[k] for k in MATERIAL_KEYS if k in entry}
    for k, v in values.items():
        if k != "source" and (isinstance(v, bool) or not isinstance(v, int | float)):
            raise InputError(f"{where}: material {name!r}: {k} must be a number, got {v!r}")
    try:
        return Material(name, **{k: float(v) if k != "source" else str(v) for k, v in values.items()})
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


class MaterialTable:
    """Materials by name, and their numbers as arrays indexed by material id (for the return model)."""

    def __init__(self, materials: list[Material]):
        self.materials = list(materials)
        self.index = {m.name: i for i, m in enumerate(self.materials)}
        self._arrays()

    def _arrays(self) -> None:
        ms = self.materials
        self.reflectivity = np.array([m.reflectivity for m in ms], np.float32)
        self.mirror = np.array([m.mirror for m in ms], np.float32)
        self.retro = np.array([m.retro for m in ms], np.float32)
        self.transmission = np.array([m.transmission for m in ms], np.float32)

    @classmethod
    def load(cls, path: Path = TABLE_FILE) -> MaterialTable:
        data = parse_yaml(read_text(path), path)
        if not isinstance(data, dict) or not data:
            raise InputError(f"{path}: a material table must be a mapping of names to materials")
        return cls([_material(str(k), v, str(path)) for k, v in data.items()])

    def add(self, material: Material) -> int:
        """Add ``material`` (or replace the entry of its name); returns its id."""
        if material.name in self.index:
            self.materials[self.index[material.name]] = material
        else:
            self.index[material.name] = len(self.materials)
            self.materials.append(material)
        self._arrays()
        return self.index[material.name]

    def id(self, name: str, where: str = "") -> int:
        if name not in self.index:
            close = ", ".join(sorted(self.index))
            raise InputError(f"{where + ': ' if where else ''}no material {name!r} (materials: {close})")
        return self.index[name]

    def named_in(self, text: str) -> str | None:
        """The table's name ``text`` is, or the longest table name it contains (``old_asphalt``: asphalt)."""
        t = text.lower()
        if t in self.index:
            return t
        hits = [n for n in self.index if n != UNKNOWN and n in t]
        return max(hits, key=len) if hits else None


# ---------------------------------------------------------------------- the scene's sidecar
@dataclass
class MaterialRules:
    """A scene's ``<scene>.materials.yaml`` (see the module's docstring); empty when there is none."""

    default: str | None = None
    mjcf_materials: dict[str, str] = field(default_factory=dict)
    geoms: list[tuple[str, str]] = field(default_factory=list)
    path: Path | None = None

    @classmethod
    def for_scene(cls, scene_xml: Path, table: MaterialTable) -> MaterialRules:
        path = Path(scene_xml).with_suffix(".materials.yaml")
        if not path.is_file():
            return cls()
        data = parse_yaml(read_text(path), path)
        if data is None:
            return cls(path=path)
        keys = ("default", "materials", "mjcf_materials", "geoms")
        if not isinstance(data, dict) or set(data) - set(keys):
            bad = sorted(set(data) - set(keys)) if isinstance(data, dict) else None
            what = f"unknown key {bad[0]!r}" if bad else "it must be a mapping"
            raise InputError(f"{path}: {what} (keys: {', '.join(keys)})")
        for name, entry in (data.get("materials") or {}).items():
            table.add(_material(str(name), entry, str(path)))
        rules = cls(path=path)
        if data.get("default") is not None:
            rules.default = str(data["default"])
            table.id(rules.default, str(path))
        for section in ("mjcf_materials", "geoms"):
            entries = data.get(section) or {}
            if not isinstance(entries, dict):
                raise InputError(f"{path}: {section} must be a mapping of names to materials")
            for pattern, name in entries.items():
                table.id(str(name), f"{path}: {section}: {pattern}")
            pairs = [(str(k), str(v)) for k, v in entries.items()]
            if section == "mjcf_materials":
                rules.mjcf_materials = dict(pairs)
            else:
                rules.geoms = pairs
        return rules


# ---------------------------------------------------------------------- patterns
class GroundTexture:
    """A generated town's terrain material at (x, y), read off its painted ground texture."""

    def __init__(self, image: np.ndarray, center, half_size, table: MaterialTable):
        colours = np.array(list(GROUND_COLOURS), np.float32)
        ids = np.array([table.id(m) for m in GROUND_COLOURS.values()], np.int16)
        px = image.reshape(-1, 3).astype(np.float32)
        nearest = np.argmin(((px[:, None, :] - colours[None]) ** 2).sum(-1), axis=1)
        self.ids = ids[nearest].reshape(image.shape[:2])  # row 0 at +y, column 0 at -x
        self.x0 = float(center[0] - half_size[0])
        self.y1 = float(center[1] + half_size[1])
        self.px_x = 2 * float(half_size[0]) / image.shape[1]
        self.px_y = 2 * float(half_size[1]) / image.shape[0]

    def at(self, xy: np.ndarray) -> np.ndarray:
        h, w = self.ids.shape
        c = np.clip(((xy[:, 0] - self.x0) / self.px_x).astype(np.int64), 0, w - 1)
        r = np.clip(((self.y1 - xy[:, 1]) / self.px_y).astype(np.int64), 0, h - 1)
        return self.ids[r, c]


class RoadMarkings:
    """Lane markings on a town's road surfaces, from its road graph (``nodes`` (K, 2), ``edges`` (E, 2)):
    a dashed centre line and a solid line ``EDGE_INSET_M`` inside each road edge, ``LINE_WIDTH_M`` wide;
    none within ``road_width_m`` of a junction (degree other than 2), where the roads meet. Dashes:
    ``DASH_M`` painted, ``GAP_M`` not (a common two-lane road's pattern; an assumption, not any one
    country's rule)."""

    LINE_WIDTH_M = 0.15
    EDGE_INSET_M = 0.3
    DASH_M = 3.0
    GAP_M = 6.0
    SAMPLE_M = 0.25  # spacing of the centre-line samples the lookup searches
    RASTER_M = 1.0  # cells of the raster that says where a line may be

    def __init__(self, nodes: np.ndarray, edges: np.ndarray, road_width_m: float):
        self.road_width_m = float(road_width_m)
        pts, dirs, along, lengths = [], [], [], []
        for a, b in edges:
            pa, pb = nodes[a], nodes[b]
            length = float(np.linalg.norm(pb - pa))
            if length <= 0:
                continue
            n = max(2, math.ceil(length / self.SAMPLE_M) + 1)
            s = np.linspace(0.0, length, n)
            pts.append(pa + s[:, None] * ((pb - pa) / length))
            dirs.append(np.repeat(((pb - pa) / length)[None], n, 0))
            along.append(s)
            lengths.append(np.full(n, length))
        self._pts, self._dirs = np.concatenate(pts), np.concatenate(dirs)
        self._along, self._length = np.concatenate(along), np.concatenate(lengths)
        self._tree = cKDTree(self._pts)
        junctions = nodes[np.bincount(edges.ravel(), minlength=len(nodes)) != 2]
        self._junctions = cKDTree(junctions) if len(junctions) else None
        # a coarse raster of the cells near any line: only points there are looked up in the tree
        cell = self.RASTER_M
        self._raster_lo = self._pts.min(axis=0) - self.road_width_m
        shape = np.ceil((self._pts.max(axis=0) + self.road_width_m - self._raster_lo) / cell).astype(int) + 1
        gx, gy = (self._raster_lo[i] + (np.arange(shape[i]) + 0.5) * cell for i in range(2))
        centres = np.column_stack([c.ravel() for c in np.meshgrid(gx, gy, indexing="ij")])
        d, _, lateral, _ = self._nearest(centres)
        slack = cell * 0.75 + self.LINE_WIDTH_M  # a cell's half diagonal and the line's width
        near = (lateral <= slack) | (np.abs(lateral - self._edge_offset) <= slack)
        self._raster = (near & (d <= self.road_width_m / 2 + slack)).reshape(shape)

    @property
    def _edge_offset(self) -> float:
        return self.road_width_m / 2 - self.EDGE_INSET_M

    def _nearest(self, xy: np.ndarray):
        """Per point: distance to the nearest centre-line sample, its index, the point's distance across
        the road from the centre line and its position along its road (m)."""
        dist, k = self._tree.query(xy)
        d = xy - self._pts[k]
        u = self._dirs[k]
        return dist, k, np.abs(d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0]), self._along[k] + (d * u).sum(1)

    def painted(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: the points ``xy`` (N, 2) lie on a marking."""
        out = np.zeros(len(xy), bool)
        if len(xy) == 0:
            return out
        ij = np.floor((xy - self._raster_lo) / self.RASTER_M).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < np.array(self._raster.shape)), axis=1)
        cand = np.flatnonzero(inside)
        cand = cand[self._raster[ij[cand, 0], ij[cand, 1]]]
        out[cand] = self._painted(xy[cand])
        return out

    def _painted(self, xy: np.ndarray) -> np.ndarray:
        if len(xy) == 0:
            return np.zeros(0, bool)
        _, k, lateral, s = self._nearest(xy)
        half = self.LINE_WIDTH_M / 2
        centre = (lateral <= half) & (np.mod(s, self.DASH_M + self.GAP_M) < self.DASH_M)
        edge = np.abs(lateral - self._edge_offset) <= half
        on = (centre | edge) & (s >= 0) & (s <= self._length[k])  # on the road, not beyond its ends
        if self._junctions is not None:
            dj, _ = self._junctions.query(xy)
            on &= dj > self.road_width_m
        return on


@dataclass(frozen=True)
class WindowGrid:
    """Windows on a box building's façades (its vertical faces): floors of ``FLOOR_M`` from the box's
    foot, each with a window from ``SILL_M`` to ``SILL_M + HEIGHT_M`` above its floor; along the façade,
    bays of ``BAY_M`` centred on it, leaving ``MARGIN_M`` at each corner, each with a window ``WIDTH_M``
    wide in its middle; no window within ``MARGIN_M`` of the roof (typical residential dimensions)."""

    FLOOR_M = 3.0
    SILL_M = 0.9
    HEIGHT_M = 1.4
    BAY_M = 2.6
    WIDTH_M = 1.3
    MARGIN_M = 0.6

    @classmethod
    def glass(cls, local: np.ndarray, half: np.ndarray) -> np.ndarray:
        """(N,) bool: points ``local`` (N, 3) in their box's frame (half sizes ``half`` (N, 3)) lie on a
        window. Points on the top or bottom face never do."""
        on_x = np.abs(np.abs(local[:, 0]) - half[:, 0]) <= np.abs(np.abs(local[:, 1]) - half[:, 1])
        u = np.where(on_x, local[:, 1], local[:, 0])  # along the façade, from its middle
        length = 2 * np.where(on_x, half[:, 1], half[:, 0])
        z = local[:, 2] + half[:, 2]  # above the box's foot
        top = np.abs(local[:, 2] - half[:, 2]) < 1e-3
        bottom = np.abs(local[:, 2] + half[:, 2]) < 1e-3
        bays = np.floor((length - 2 * cls.MARGIN_M) / cls.BAY_M)
        off = np.mod(u + bays * cls.BAY_M / 2, cls.BAY_M)  # within the bay, from its start
        in_bays = np.abs(u) <= bays * cls.BAY_M / 2
        across = np.abs(off - cls.BAY_M / 2) <= cls.WIDTH_M / 2
        fz = np.mod(z, cls.FLOOR_M)
        up = (fz >= cls.SILL_M) & (fz <= cls.SILL_M + cls.HEIGHT_M)
        under_roof = z + (cls.SILL_M + cls.HEIGHT_M - fz) <= 2 * half[:, 2] - cls.MARGIN_M
        return in_bays & across & up & under_roof & ~top & ~bottom & (bays > 0)


# ---------------------------------------------------------------------- a scene's materials
def _luminance(rgb) -> float:
    """Relative luminance of an sRGB colour (components 0..1)."""
    lin = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in rgb]
    return 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]


class SceneMaterials:
    """Every geom's material and the patterns of a scene, and the lookup of each ray hit's material.

    Args:
        model, data: the compiled scene (``data`` after a forward pass: static geoms' poses).
        scene_xml: the scene's file (its sidecar ``.materials.yaml`` is read when present).
        town: the generated town's info (patterns need it), or None.
        table: the material table (default: ``materials.yaml``).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, scene_xml: Path, town=None, table=None):
        self.model = model
        self.table = table or MaterialTable.load()
        self.rules = MaterialRules.for_scene(Path(scene_xml), self.table)
        self.pattern = np.zeros(model.ngeom, np.int8)
        self.geom_material = np.array(
            [self._resolve(g) for g in range(model.ngeom)], np.int16
        )  # patterns set self.pattern
        self.ground: GroundTexture | None = None
        self.markings: RoadMarkings | None = None
        if town is not None:
            self._town_patterns(Path(scene_xml), town)
        else:
            self.pattern[self.pattern == PATTERN_GROUND] = PATTERN_NONE
        self._asphalt = self.table.index.get("asphalt")
        self._lane_paint = self.table.index.get("lane_paint")
        self._glass = self.table.index.get("glass")
        # boxes with windows: world-to-geom transforms and half sizes (static geoms only)
        win = np.flatnonzero(self.pattern == PATTERN_WINDOWS)
        self._win_R = np.asarray(data.geom_xmat[win]).reshape(-1, 3, 3)
        self._win_t = np.asarray(data.geom_xpos[win]).reshape(-1, 3)
        self._win_half = np.asarray(model.geom_size[win]).reshape(-1, 3)
        self._win_slot = np.full(model.ngeom, -1, np.int64)
        self._win_slot[win] = np.arange(len(win))
        self._face_geoms: dict[int, np.ndarray] = {}
        self._flat: np.ndarray | None = None

    # --- resolution ------------------------------------------------------------------------------------
    def _name(self, obj, i: int) -> str:
        return mujoco.mj_id2name(self.model, obj, int(i)) or ""

    def _resolve(self, g: int) -> int:
        m, t = self.model, self.table
        geom = self._name(mujoco.mjtObj.mjOBJ_GEOM, g)
        body = self._name(mujoco.mjtObj.mjOBJ_BODY, m.geom_bodyid[g])
        mat_id = int(m.geom_matid[g])
        mjcf = self._name(mujoco.mjtObj.mjOBJ_MATERIAL, mat_id) if mat_id >= 0 else ""
        for pattern, name in self.rules.geoms:
            if (geom and fnmatch.fnmatchcase(geom, pattern)) or (body and fnmatch.fnmatchcase(body, pattern)):
                return t.id(name)
        if mjcf in self.rules.mjcf_materials:
            return t.id(self.rules.mjcf_materials[mjcf])
        if mjcf:
            if mjcf == TOWN_TERRAIN_MATERIAL:
                self.pattern[g] = PATTERN_GROUND  # kept only for a town (its texture is known)
            if mjcf in TOWN_MATERIALS:
                if mjcf.startswith("building"):
                    self.pattern[g] = PATTERN_WINDOWS * (int(m.geom_type[g]) == mujoco.mjtGeom.mjGEOM_BOX)
                return t.id(TOWN_MATERIALS[mjcf])
            named = t.named_in(mjcf)
            if named is not None:
                return t.id(named)
        if body.startswith("parked_v"):  # a generated town's parked car
            if geom.endswith("_cabin"):
                return t.id("glass")
            return self._car_paint(m.geom_rgba[g][:3])
        if body.startswith("actor_"):  # a moving actor (simbed.sim.actors): the first geom is the body
            kind = body.rsplit("_", 1)[-1]
            if kind == "car":
                first = int(m.body_geomadr[m.geom_bodyid[g]])
                return self._car_paint(m.geom_rgba[g][:3]) if g == first else t.id("glass")
            return t.id("fabric")
        return t.id(self.rules.default or UNKNOWN)

    def _car_paint(self, rgb) -> int:
        base = self.table.materials[self.table.id("car_paint")]
        refl = CAR_PAINT_DARK + (CAR_PAINT_LIGHT - CAR_PAINT_DARK) * _luminance([float(c) for c in rgb])
        refl = round(round(refl / CAR_PAINT_STEP) * CAR_PAINT_STEP, 4)
        name = f"car_paint_{refl:.2f}"
        if name not in self.table.index:
            self.table.add(
                Material(name, min(refl, 1.0 - base.mirror), base.mirror, base.retro, 0.0, base.source)
            )
        return self.table.index[name]

    def _town_patterns(self, scene_xml: Path, town) -> None:
        ground = np.flatnonzero(self.pattern == PATTERN_GROUND)
        if len(ground):
            texture = scene_xml.with_name(f"{scene_xml.stem}_ground.img")
            if texture.is_file():
                from PIL import Image

                with Image.open(texture) as im:
                    image = np.asarray(im.convert("RGB"))
                self.ground = GroundTexture(image, town.terrain.center, town.terrain.half_size, self.table)
            else:
                self.pattern[ground] = PATTERN_NONE
        if len(town.edges):
            self.markings = RoadMarkings(
                np.asarray(town.nodes, float), np.asarray(town.edges, int), float(town.road_width_m)
            )

    # --- lookup ------------------------------------------------------------------------------------------
    def add_mesh(self, handle: int, geom_ids_per_face: np.ndarray, face_map: np.ndarray) -> None:
        """Tell the lookup which geom each face of caster mesh ``handle`` came from (``face_map``: the
        caster's kept faces, :attr:`rangemcl.raycast.MeshInfo.face_map`)."""
        self._face_geoms[int(handle)] = np.asarray(geom_ids_per_face, np.int32)[np.asarray(face_map)]
        self._flat = None  # rebuilt at the next lookup

    def _gather_table(self) -> None:
        """Every mesh's faces in one array, each mesh at its offset (one gather per lookup)."""
        handles = sorted(self._face_geoms)
        self._offset = np.full(handles[-1] + 2, -1, np.int64)
        sizes = np.array([len(self._face_geoms[h]) for h in handles], np.int64)
        self._offset[handles] = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self._flat = np.concatenate([self._face_geoms[h] for h in handles])

    def geoms_of(self, mesh_ids: np.ndarray, face_ids: np.ndarray) -> np.ndarray:
        """(N,) geom id of each hit (-1 for a miss or a mesh the lookup does not know)."""
        out = np.full(len(mesh_ids), -1, np.int32)
        if not self._face_geoms:
            return out
        if self._flat is None:
            self._gather_table()
        m = np.asarray(mesh_ids, np.int64)
        inside = (m >= 0) & (m < len(self._offset))
        off = np.where(inside, self._offset[np.where(inside, m, -1)], -1)
        known = off >= 0
        out[known] = self._flat[off[known] + face_ids[known]]
        return out

    def lookup(self, mesh_ids: np.ndarray, face_ids: np.ndarray, points: np.ndarray, normals: np.ndarray):
        """(N,) material id of each hit at world ``points`` (N, 3) with unit ``normals`` (N, 3); misses
        (and meshes the lookup does not know) get ``unknown``."""
        geoms = self.geoms_of(mesh_ids, face_ids)
        known = geoms >= 0
        ids = np.full(len(geoms), self.table.id(UNKNOWN), np.int16)
        ids[known] = self.geom_material[geoms[known]]
        pattern = np.zeros(len(geoms), np.int8)
        pattern[known] = self.pattern[geoms[known]]
        if self.ground is not None:
            sel = np.flatnonzero(pattern == PATTERN_GROUND)
            ids[sel] = self.ground.at(points[sel, :2])
        sel = np.flatnonzero(pattern == PATTERN_WINDOWS)
        if len(sel) and self._glass is not None:
            slot = self._win_slot[geoms[sel]]
            local = np.einsum("nji,nj->ni", self._win_R[slot], points[sel] - self._win_t[slot])
            glass = WindowGrid.glass(local, self._win_half[slot])
            ids[sel[glass]] = self._glass
        if self.markings is not None and self._asphalt is not None and self._lane_paint is not None:
            sel = np.flatnonzero((ids == self._asphalt) & (np.abs(normals[:, 2]) > 0.9))
            ids[sel[self.markings.painted(points[sel, :2])]] = self._lane_paint
        return ids
