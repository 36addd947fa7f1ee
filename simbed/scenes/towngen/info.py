"""What a generated town says about itself: :class:`TownInfo` (road graph, spawn pose, :class:`Terrain`), its
YAML sidecar (:func:`write_yaml`, :func:`load_town_info`), and the parked-car variants of a compiled town
model (:func:`parked_variant_bodies`, :func:`use_parked_variant`)."""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rangemcl.errors import InputError
from rangemcl.se2 import quat_wxyz_from_ypr

_YAML_KEYS = (
    "name",
    "seed",
    "size_m",
    "road_width_m",
    "lane_width_m",
    "roads",
    "terrain",
    "parked_variants",
    "spawn",
)
_TERRAIN_KEYS = ("hfield_file", "center", "half_size", "nrow", "ncol", "z_min", "z_range")


@dataclass(frozen=True, eq=False)
class Terrain:
    """A MuJoCo height field as the town uses it, and its exact surface.

    ``data`` is ``(nrow, ncol)`` float32 in [0, 1] (min 0 and max 1, so MuJoCo's own normalisation leaves
    it unchanged); row r lies at ``y = cy - hy + r·2hy/(nrow-1)``, column c at
    ``x = cx - hx + c·2hx/(ncol-1)``; the surface height is ``z_min + z_range·value``. Each cell is split
    along its diagonal from (x_c, y_r) to (x_c+1, y_r+1) into two planar triangles, as MuJoCo does.
    """

    center: tuple[float, float]
    half_size: tuple[float, float]
    z_min: float
    z_range: float
    data: np.ndarray
    file: str  # the binary hfield file's name, next to the XML and the sidecar

    @property
    def cell_m(self) -> tuple[float, float]:
        nrow, ncol = self.data.shape
        return 2 * self.half_size[0] / (ncol - 1), 2 * self.half_size[1] / (nrow - 1)

    def height(self, x: Any, y: Any) -> np.ndarray:
        """Surface height at (x, y), vectorised; points outside the field take the nearest border value."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        data = self.data
        nrow, ncol = data.shape
        dx, dy = self.cell_m
        fx = np.clip((x - (self.center[0] - self.half_size[0])) / dx, 0.0, ncol - 1)
        fy = np.clip((y - (self.center[1] - self.half_size[1])) / dy, 0.0, nrow - 1)
        c = np.minimum(np.floor(fx).astype(np.int64), ncol - 2)
        r = np.minimum(np.floor(fy).astype(np.int64), nrow - 2)
        u = fx - c
        v = fy - r
        h00 = data[r, c].astype(np.float64)
        h10 = data[r, c + 1].astype(np.float64)
        h01 = data[r + 1, c].astype(np.float64)
        h11 = data[r + 1, c + 1].astype(np.float64)
        upper = h00 + (h11 - h01) * u + (h01 - h00) * v  # triangle (00, 11, 01): v >= u
        lower = h00 + (h10 - h00) * u + (h11 - h10) * v  # triangle (00, 10, 11): u > v
        return self.z_min + self.z_range * np.where(v >= u, upper, lower)


@dataclass(frozen=True, eq=False)
class TownInfo:
    """What a town sidecar says: the road graph, the spawn pose and the terrain surface.

    Attributes:
        name, seed, size_m: the town's name, generator seed and side length (the town spans
            ``[-size_m/2, size_m/2]`` in x and y).
        road_width_m, lane_width_m: the style's, 8.0 and 3.5 by default (two lanes, one each way,
            right-hand traffic).
        nodes: (K, 2) junction positions, then the bend nodes of bent roads (styles ``suburb``, ``mixed``);
            edges: (E, 2) int node index pairs, each a straight two-way road (a bent road is several).
        total_length_m: summed length of the edges (node to node).
        parked_variants: number of parked-car sets ``parked_v{k}_*`` in the XML.
        spawn: (x, y, yaw) a start pose in the right-hand lane of a road, heading along it.
        terrain: the height field (:class:`Terrain`).
        yaml_path: the sidecar this came from (the XML is ``yaml_path.with_suffix(".xml")``).
        style: the generator's named style (``grid``, ``suburb``, ``mixed``: ``simbed make-town --style``),
            ``custom`` for another :class:`~simbed.scenes.towngen.style.TownStyle`; a sidecar without the
            key (the grid's, and every older one) reads as ``grid``.
    """

    name: str
    seed: int
    size_m: float
    road_width_m: float
    lane_width_m: float
    nodes: np.ndarray
    edges: np.ndarray
    total_length_m: float
    parked_variants: int
    spawn: tuple[float, float, float]
    terrain: Terrain
    yaml_path: Path | None = None
    style: str = "grid"

    @property
    def xml_path(self) -> Path | None:
        return None if self.yaml_path is None else self.yaml_path.with_suffix(".xml")

    def ground_height(self, x: Any, y: Any) -> np.ndarray:
        """Ground (terrain = road surface on roads) height at world (x, y), vectorised over arrays."""
        return self.terrain.height(x, y)

    def segments(self) -> tuple[np.ndarray, np.ndarray]:
        """Road centre lines as (E, 2) start and (E, 2) end points."""
        return self.nodes[self.edges[:, 0]], self.nodes[self.edges[:, 1]]

    def spawn_qpos(self) -> np.ndarray:
        """The 7 qpos values of the car's free joint ``car_root`` at the spawn pose: x y z qw qx qy qz."""
        return self.car_qpos(*self.spawn)

    def car_qpos(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Free-joint qpos (x y z qw qx qy qz) that rests the car (``scenes/car.xml``) at (x, y, yaw).

        z is the ground height under the rear-axle centre (the car's springs are preloaded so that its base
        origin rests on the ground); pitch and roll follow the ground under the four wheels
        (wheelbase 2.7 m, track 1.6 m), so that the car starts settled on a graded road.
        """
        c, s = math.cos(yaw), math.sin(yaw)
        fwd = np.array([c, s])
        left = np.array([-s, c])
        p = np.array([x, y], dtype=np.float64)
        wheels = np.array(
            [p + 0.8 * left, p - 0.8 * left, p + 2.7 * fwd + 0.8 * left, p + 2.7 * fwd - 0.8 * left]
        )
        h = self.ground_height(wheels[:, 0], wheels[:, 1])
        z = float(self.ground_height(x, y))
        pitch = -math.atan2((h[2] + h[3] - h[0] - h[1]) / 2, 2.7)  # nose up on an uphill road
        roll = math.atan2((h[0] + h[2] - h[1] - h[3]) / 2, 1.6)  # left side up where the ground is higher
        q = quat_wxyz_from_ypr(yaw, pitch, roll)
        return np.array([x, y, z, *q])


def format_number(v: float, nd: int = 4) -> str:
    """``v`` with at most ``nd`` decimals, no trailing zeros (``-0`` written ``0``): the numbers of the XML
    and the sidecar."""
    s = f"{v:.{nd}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_yaml(path: Path, info: TownInfo) -> None:
    """Write ``info`` as a town sidecar, the keys in the order :func:`load_town_info` expects them."""
    t = info.terrain
    nodes = ", ".join(f"[{format_number(x, 3)}, {format_number(y, 3)}]" for x, y in info.nodes)
    edges = ", ".join(f"[{int(i)}, {int(j)}]" for i, j in info.edges)
    x, y, yaw = info.spawn
    plain = re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.-]*", info.name) and info.name not in (
        "null",
        "true",
        "false",
    )
    lines = [
        f"name: {info.name if plain else json.dumps(info.name)}",
        f"seed: {info.seed}",
        f"size_m: {float(info.size_m)!r}",
        *([] if info.style == "grid" else [f"style: {info.style}"]),  # the grid's sidecar as it always was
        f"road_width_m: {info.road_width_m!r}",
        f"lane_width_m: {info.lane_width_m!r}",
        "roads:",
        f"  nodes: [{nodes}]",
        f"  edges: [{edges}]",
        f"  total_length_m: {info.total_length_m:.3f}",
        "terrain:",
        "  # MuJoCo hfield (binary: int32 nrow, int32 ncol, float32 rows; row 0 at y = center_y - half_y,",
        "  # values in [0, 1]); height = z_min + z_range * value, each cell split along the diagonal",
        "  # (x_c, y_r)-(x_c+1, y_r+1) into two planar triangles",
        f"  hfield_file: {t.file}",
        f"  center: [{t.center[0]!r}, {t.center[1]!r}]",
        f"  half_size: [{t.half_size[0]!r}, {t.half_size[1]!r}]",
        f"  nrow: {t.data.shape[0]}",
        f"  ncol: {t.data.shape[1]}",
        f"  z_min: {t.z_min:.6f}",
        f"  z_range: {t.z_range:.6f}",
        f"parked_variants: {info.parked_variants}",
        f"spawn: {{x: {x:.4f}, y: {y:.4f}, yaw: {yaw:.6f}}}",
        "",
    ]
    path.write_text("\n".join(lines))


def _fail(path: Path, problem: str) -> InputError:
    return InputError(f"{path}: {problem}")


def load_town_info(yaml_path: Path | str) -> TownInfo:
    """Read a town sidecar (and its terrain file); every problem is one :class:`InputError` line naming it."""
    path = Path(yaml_path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise _fail(path, "town sidecar not found") from None
    except OSError as exc:
        raise _fail(path, f"cannot read town sidecar ({exc.strerror})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise _fail(path, f"not valid YAML{where}") from None
    if not isinstance(doc, dict):
        raise _fail(path, f"a town sidecar must be a mapping, got {type(doc).__name__}")
    missing = [k for k in _YAML_KEYS if k not in doc]
    if missing:
        raise _fail(path, f"missing key(s) {', '.join(map(repr, missing))}")

    def number(value, key, integer=False):
        ok = isinstance(value, int) if integer else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok or not math.isfinite(value):
            raise _fail(path, f"{key} must be {'an integer' if integer else 'a number'}, got {value!r}")
        return int(value) if integer else float(value)

    def section(key, keys):
        sec = doc[key]
        if not isinstance(sec, dict):
            raise _fail(path, f"{key} must be a mapping")
        gone = [k for k in keys if k not in sec]
        if gone:
            raise _fail(path, f"{key}: missing key(s) {', '.join(map(repr, gone))}")
        return sec

    roads = section("roads", ("nodes", "edges", "total_length_m"))
    try:
        nodes = np.array(roads["nodes"], dtype=np.float64)
        edges = np.array(roads["edges"], dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, "roads.nodes and roads.edges must be lists of number pairs") from None
    if nodes.ndim != 2 or nodes.shape[1] != 2 or len(nodes) < 2 or not np.all(np.isfinite(nodes)):
        raise _fail(path, f"roads.nodes must be a (K, 2) list of [x, y] with K >= 2, got shape {nodes.shape}")
    if edges.ndim != 2 or edges.shape[1] != 2 or len(edges) < 1 or np.any(edges != np.round(edges)):
        raise _fail(path, f"roads.edges must be an (E, 2) list of node index pairs, got shape {edges.shape}")
    edges = edges.astype(np.int64)
    if edges.min() < 0 or edges.max() >= len(nodes):
        raise _fail(path, f"roads.edges refer to nodes outside 0..{len(nodes) - 1}")
    spawn = section("spawn", ("x", "y", "yaw"))
    terr = section("terrain", _TERRAIN_KEYS)
    nrow = number(terr["nrow"], "terrain.nrow", integer=True)
    ncol = number(terr["ncol"], "terrain.ncol", integer=True)
    pairs = {}
    for key in ("center", "half_size"):
        v = terr[key]
        if not (isinstance(v, list) and len(v) == 2):
            raise _fail(path, f"terrain.{key} must be [x, y]")
        pairs[key] = (number(v[0], f"terrain.{key}"), number(v[1], f"terrain.{key}"))
    if min(pairs["half_size"]) <= 0 or nrow < 2 or ncol < 2:
        raise _fail(path, "terrain: half_size must be positive and nrow, ncol at least 2")
    hfile = path.parent / str(terr["hfield_file"])
    try:
        raw = hfile.read_bytes()
    except OSError:
        raise _fail(path, f"terrain file {hfile.name} not found next to the sidecar") from None
    if len(raw) != 8 + 4 * nrow * ncol or tuple(np.frombuffer(raw[:8], "<i4")) != (nrow, ncol):
        raise _fail(path, f"terrain file {hfile.name} does not hold a {nrow} x {ncol} float32 height field")
    data = np.frombuffer(raw[8:], "<f4").reshape(nrow, ncol).astype(np.float32)
    terrain = Terrain(
        center=pairs["center"],
        half_size=pairs["half_size"],
        z_min=number(terr["z_min"], "terrain.z_min"),
        z_range=number(terr["z_range"], "terrain.z_range"),
        data=data,
        file=hfile.name,
    )
    name = doc["name"]
    if not isinstance(name, str) or not name:
        raise _fail(path, f"name must be a non-empty string, got {name!r}")
    style = doc.get("style", "grid")
    if not isinstance(style, str) or not re.fullmatch(r"[a-z][a-z0-9_-]*", style):
        raise _fail(path, f"style must be a style name such as grid, suburb or mixed, got {style!r}")
    return TownInfo(
        name=name,
        seed=number(doc["seed"], "seed", integer=True),
        size_m=number(doc["size_m"], "size_m"),
        road_width_m=number(doc["road_width_m"], "road_width_m"),
        lane_width_m=number(doc["lane_width_m"], "lane_width_m"),
        nodes=nodes,
        edges=edges,
        total_length_m=number(roads["total_length_m"], "roads.total_length_m"),
        parked_variants=number(doc["parked_variants"], "parked_variants", integer=True),
        spawn=(
            number(spawn["x"], "spawn.x"),
            number(spawn["y"], "spawn.y"),
            number(spawn["yaw"], "spawn.yaw"),
        ),
        terrain=terrain,
        yaml_path=path,
        style=style,
    )


def parked_variant_bodies(model) -> dict[int, list[int]]:
    """Body ids of the parked cars in a compiled town model, per variant k (bodies ``parked_v{k}_{i}``)."""
    out: dict[int, list[int]] = {}
    rx = re.compile(r"parked_v(\d+)_(\d+)")
    for b in range(model.nbody):
        match = rx.fullmatch(model.body(b).name)
        if match:
            out.setdefault(int(match[1]), []).append(b)
    return out


def use_parked_variant(model, k: int | None) -> None:
    """Keep parked-car variant ``k`` (``None``: none) in a compiled town model; take the others out.

    The other variants' geoms stop colliding (contype = conaffinity = 0) and become invisible (alpha 0,
    which also hides them from ``mj_ray``). A LiDAR that builds its own meshes must skip those bodies itself
    (:func:`parked_variant_bodies`).
    """
    variants = parked_variant_bodies(model)
    if k is not None and k not in variants:
        raise InputError(f"town model has no parked-car variant {k} (it has {sorted(variants)})")
    for kk, bodies in variants.items():
        if kk == k:
            continue
        for b in bodies:
            g = slice(model.body_geomadr[b], model.body_geomadr[b] + model.body_geomnum[b])
            model.geom_contype[g] = 0
            model.geom_conaffinity[g] = 0
            model.geom_rgba[g, 3] = 0.0
