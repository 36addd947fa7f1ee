"""Seeded town generator: a road network with loops, mild terrain, buildings, street furniture, parked cars.

:func:`generate_town` writes a MuJoCo scene (``town.xml``), its height field (``town_terrain.bin``), the
terrain's texture (``town_ground.img``, a PNG) and a sidecar (``town.yaml``) that :func:`load_town_info`
reads back into a :class:`TownInfo`. All randomness comes from ``np.random.default_rng(seed)``: the same
seed and style write byte-identical files. Sizes, offsets, spacings and random ranges are the fields of a
:class:`TownStyle`; the towns shipped in ``scenes/`` are the :class:`TownPreset` values of
:data:`SHIPPED_TOWNS`.

What a town holds with the default style (world frame: metres, z up, the town centred on the origin):

* **Roads**: a jittered grid of junction nodes (60–90 m apart) with some grid edges removed; the graph
  stays connected, every node keeps degree ≥ 2 (no dead ends) and it keeps loops. Each edge is a straight
  two-way road 8 m wide (two 3.5 m lanes plus 0.5 m margins): a thin box whose top is the road surface,
  tilted along the road (grade ≤ 2.5 %) from 7.5 m after one node to 7.5 m before the next; each
  junction is a flat disc of radius 8 m at the node's height. Beside each lane (3.7–5.7 m from the
  centre line) is a parking strip, then the sidewalk with poles (6.6 m) and trees (7.8 m); buildings
  and walls start at least 9.5 m from the centre line (5.5 m beyond the road edge).
* **Terrain**: a MuJoCo ``<hfield>`` with smooth long-wavelength relief (about 1.3 m peak to peak over the
  town) that equals the road surface within 9.5 m of every road centre line and blends into the natural
  relief over the next 16 m. :meth:`TownInfo.ground_height` reproduces MuJoCo's surface exactly (the same
  float32 samples, the same triangles), so everything is placed on it.
* **Static objects** (geom group 0, colliding): buildings (boxes and L shapes of two boxes, 4–30 m high),
  walls along some frontages, poles, trees (trunk cylinder and ellipsoid crown), and
  ``n_parked_variants`` sets of parked cars (each set its own cars; sets may reuse a parking spot), each
  car a static body ``parked_v{k}_{i}`` (k: variant, i: car) of two boxes (body and cabin,
  4.2–4.8 × 1.75–1.9 × 1.4–1.6 m), parallel to the road in the parking strip, facing the traffic of its
  side (right-hand traffic).
* **The car**: ``<include file="car.xml"/>`` (copied next to the town XML when written elsewhere); it
  stands at the origin, the simulator sets ``qpos`` of the free joint ``car_root`` (see
  :meth:`TownInfo.spawn_qpos` and :meth:`TownInfo.car_qpos`). Enable one parked-car set with
  :func:`use_parked_variant`.

Geom names: ``terrain``, ``road_{e}``, ``junction_{n}``, ``bldg_{b}_a``/``bldg_{b}_b``, ``wall_{w}``,
``pole_{p}``, ``tree_{t}_trunk``/``tree_{t}_crown``, ``parked_v{k}_{i}_body``/``parked_v{k}_{i}_cabin``.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from collections import defaultdict
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image

from rangemcl.common.outdir import check_output_files
from rangemcl.errors import InputError
from rangemcl.se2 import quat_wxyz_from_ypr, wrap_angle

CAR_XML = Path(__file__).resolve().parents[2] / "scenes" / "car.xml"

Range = tuple[float, float]
"""A closed interval (low, high) that a value is drawn from uniformly, unless its field says otherwise."""

# The ground texture's colours (sRGB 0..255); grass is shaded by the relief, ± this fraction at its extremes.
_ASPHALT_RGB = (56, 56, 61)
_PARKING_RGB = (74, 74, 79)
_SIDEWALK_RGB = (152, 150, 144)
_GRASS_RGB = (92, 124, 70)
_GRASS_SHADE_FRAC = 0.12
_N_BUILDING_MATERIALS = 5  # building0 .. building4 in the XML's assets


# ------------------------------------------------------------------------------------------------ parameters


@dataclass(frozen=True)
class TownStyle:
    """What the town generator draws from: sizes, offsets, spacings and random ranges, with their units.

    Distances are metres (``_m``) in the ground plane unless a field says otherwise; ``_frac`` is a fraction
    of another quantity that the field names; ``_prob`` a probability; a :data:`Range` ``(low, high)`` is
    drawn from uniformly. Offsets beside a road are measured from its centre line. The defaults write the
    towns in ``scenes/`` (:data:`SHIPPED_TOWNS`). Invalid values raise one :class:`InputError` line naming
    the field; ``dataclasses.replace(style, field=value)`` checks again.
    """

    # roads
    road_width_m: float = 8.0
    """Width of a two-way road: two lanes plus margins (the road box, the asphalt paint)."""
    lane_width_m: float = 3.5
    """Width of one lane; the spawn pose lies on the right lane's centre, half of it from the centre line."""
    road_thickness_m: float = 0.2
    """Thickness of the road boxes and junction discs, whose tops are the road surface."""
    junction_radius_m: float = 8.0
    """Radius of the flat junction disc on each node; frontages, poles, trees and parking start beyond it."""
    ramp_start_m: float = 7.5
    """A road box starts (flat) this far from its node; the grade runs between the two ends."""
    max_grade_m_per_m: float = 0.025
    """Steepest road grade, rise over run: node heights are relaxed from the relief until roads keep it."""

    # road graph
    graph_margin_m: float = 25.0
    """The grid's outer junctions lie this far inside the town's border (before jitter)."""
    block_pitch_m: float = 75.0
    """Wanted distance between neighbouring grid junctions: a side of the town has
    ``max(2, round((size_m - 2 graph_margin_m) / block_pitch_m) + 1)`` junctions, spread over the span."""
    max_block_pitch_m: float = 85.0
    """Largest distance between neighbouring grid junctions (a wider grid shrinks toward the centre)."""
    node_jitter_frac: Range = (-0.12, 0.12)
    """Random offset of each junction in x and in y, as a fraction of the grid pitch."""
    removed_roads_frac: float = 0.18
    """Fraction of the grid's roads removed at random, as far as connectivity, degree >= 2 and loops allow."""
    min_loops_count: int = 3
    """The road graph keeps at least this many independent loops (all the grid's if it has fewer) ..."""
    min_loops_frac: float = 0.5
    """... or this fraction of the grid's independent loops (rounded down), whichever is more."""

    # terrain
    flat_half_width_m: float = 9.5
    """The terrain equals the road surface this far from every road centre line and junction node."""
    relief_blend_m: float = 16.0
    """Beyond ``flat_half_width_m`` the terrain blends (smoothstep) into the natural relief over this."""
    relief_peak_to_peak_m: float = 1.3
    """Peak-to-peak height of the natural relief over the town (before the roads flatten it)."""
    relief_waves_count: int = 7
    """The natural relief is a sum of this many plane waves of random direction and phase."""
    relief_wavelength_m: Range = (140.0, 520.0)
    """Wavelength of each relief wave."""
    relief_wave_weight_frac: Range = (0.5, 1.0)
    """Relative amplitude of each relief wave (the sum is then scaled to ``relief_peak_to_peak_m``)."""
    fine_max_size_m: float = 300.0
    """Towns up to this size get ``terrain_cell_m`` and ``texture_px_m``; larger ones the coarse values."""
    terrain_cell_m: float = 1.0
    """Height-field cell of a town up to ``fine_max_size_m``."""
    coarse_terrain_cell_m: float = 2.0
    """Height-field cell of a larger town."""
    texture_px_m: float = 0.5
    """Ground-texture pixel of a town up to ``fine_max_size_m``."""
    coarse_texture_px_m: float = 1.0
    """Ground-texture pixel of a larger town."""

    # frontages: buildings and walls
    border_margin_m: float = 2.0
    """Buildings, walls, poles and trees stay this far inside the town's border."""
    building_min_offset_m: float = 9.5
    """Nearest building or wall face from any road centre line."""
    lot_start_m: Range = (0.0, 4.0)
    """The first lot of a frontage starts this far beyond the junction disc."""
    lot_width_m: Range = (10.0, 24.0)
    """Width of a lot along the road (cut short before the next junction disc)."""
    lot_min_width_m: float = 6.0
    """Narrower lots stay empty, and no lot starts within this distance of the next junction disc."""
    lot_gap_m: Range = (2.0, 8.0)
    """Gap between neighbouring lots along the road."""
    lot_kind_prob: tuple[float, float, float] = (0.72, 0.14, 0.14)
    """Probabilities that a lot holds a building, a wall or nothing (summing to 1)."""
    building_setback_m: Range = (0.5, 4.0)
    """A building's front lies this far beyond ``building_min_offset_m``."""
    building_depth_m: Range = (10.0, 22.0)
    """Depth of a building's main box, away from the road."""
    building_height_m: Range = (4.0, 30.0)
    """Height of a building above its highest ground corner; also the least height of an L shape's wing."""
    building_height_beta_shape: Range = (1.4, 3.0)
    """Shapes (a, b) of the Beta distribution of heights within ``building_height_m`` (mostly low)."""
    l_shape_prob: float = 0.35
    """Probability that a building is an L shape: the main box and a wing behind one end of it."""
    wing_width_frac: Range = (0.35, 0.6)
    """Width of the wing along the road, as a fraction of the lot width."""
    wing_depth_m: Range = (6.0, 14.0)
    """Depth of the wing, away from the road."""
    wing_height_frac: Range = (0.4, 1.0)
    """Height of the wing, as a fraction of the main box's height."""
    wing_overlap_m: float = 0.5
    """The wing reaches this far into the main box."""
    building_shrink_frac: tuple[float, ...] = (1.0, 0.75, 0.55)
    """Scales of a building's footprint tried in turn until it fits (else the lot stays empty)."""
    building_gap_m: float = 1.5
    """Least distance between a building and anything placed before it."""
    building_sink_m: float = 0.5
    """A building reaches this far below its lowest ground corner."""
    wall_thickness_m: float = 0.3
    """Thickness of a wall."""
    wall_setback_m: Range = (0.0, 1.0)
    """A wall's road-side face lies this far beyond ``building_min_offset_m``."""
    wall_height_m: Range = (1.2, 2.6)
    """Height of a wall above its highest ground point."""
    wall_gap_m: float = 0.5
    """Least distance between a wall and anything placed before it."""
    sink_m: float = 0.3
    """Walls, poles and tree trunks reach this far below the ground."""

    # street furniture: poles and trees
    pole_offset_m: float = 6.6
    """Poles stand this far from their road's centre line, alternating sides."""
    pole_radius_m: float = 0.15
    """Radius of a pole."""
    pole_height_m: Range = (5.0, 8.0)
    """Height of a pole above the ground."""
    pole_start_m: Range = (4.0, 12.0)
    """The first pole of a road stands this far beyond the junction disc (the last one at least the low end
    before the next disc)."""
    pole_spacing_m: Range = (25.0, 38.0)
    """Distance between successive poles along a road."""
    pole_road_slack_m: float = 0.5
    """A pole may come this much closer to another road's centre line than ``pole_offset_m``."""
    pole_gap_m: float = 0.5
    """Least distance between a pole and anything placed before it."""
    tree_offset_m: float = 7.8
    """Street trees stand this far from their road's centre line ..."""
    tree_offset_jitter_m: Range = (-0.2, 0.2)
    """... plus this."""
    street_tree_start_m: Range = (3.0, 13.0)
    """The first street-tree spot of a road side lies this far beyond the junction disc (the last one at least
    the low end before the next disc)."""
    street_tree_spacing_m: Range = (9.0, 20.0)
    """Distance between successive street-tree spots along a road side."""
    street_tree_prob: float = 0.55
    """Probability that a street-tree spot gets a tree."""
    street_tree_road_slack_m: float = 0.6
    """A street tree may come this much closer to another road's centre line than ``tree_offset_m``."""
    street_tree_crown_radius_m: Range = (1.2, 1.9)
    """Horizontal radius of a street tree's crown."""
    block_tree_area_m2: float = 1200.0
    """One block-tree candidate per this much town area, at a uniform random place."""
    block_tree_border_m: float = 4.0
    """Block-tree candidates lie this far inside the town's border."""
    block_tree_room_m: Range = (1.5, 3.5)
    """Half side of the square that must be free (``block_tree_room_gap_m`` apart) around a candidate."""
    block_tree_room_gap_m: float = 0.5
    """Least distance between that square and anything placed before it."""
    block_tree_road_clearance_m: float = 10.5
    """Least distance between a block tree's trunk and any road centre line."""
    block_tree_crown_radius_m: Range = (1.2, 3.5)
    """Horizontal radius of a block tree's crown."""
    tree_trunk_radius_m: Range = (0.12, 0.25)
    """Radius of a tree trunk."""
    tree_trunk_height_m: Range = (2.8, 4.5)
    """Height of the crown's centre above the ground, less ``tree_trunk_into_crown_frac`` of its semi-height
    (unless ``tree_crown_min_bottom_m`` raises the crown)."""
    tree_trunk_into_crown_frac: float = 0.3
    """The trunk reaches this fraction of the crown's vertical semi-axis into the crown."""
    tree_crown_height_frac: Range = (0.8, 1.3)
    """Vertical semi-axis of the crown (an ellipsoid), as a fraction of its radius."""
    tree_crown_min_bottom_m: float = 2.8
    """The crown's bottom lies at least this high above the ground."""
    tree_gap_m: float = 1.2
    """Least distance between a trunk and anything placed before it."""

    # parking
    parking_offset_m: float = 4.7
    """Parked cars' centres lie this far from the road's centre line (the parking strip beside each lane)."""
    parking_pitch_m: float = 6.5
    """Distance between parking spots along a road (the row is centred on the road)."""
    parking_end_clearance_m: float = 6.0
    """Parking spots keep this far beyond the junction discs."""
    parking_spot_length_m: float = 5.2
    """Length of a spot's footprint, which must be free (``parking_spot_gap_m`` apart) of poles, trees..."""
    parking_spot_width_m: float = 2.0
    """Width of a spot's footprint."""
    parking_spot_gap_m: float = 0.3
    """Least distance between a spot's footprint and anything placed before it."""
    parking_spot_road_clearance_m: float = 0.5
    """A spot's footprint keeps this far beyond the edge of any other road."""
    parking_paint_beyond_m: float = 1.1
    """The parking strip is painted this far beyond the parked cars' centre line."""
    sidewalk_paint_inset_m: float = 1.0
    """The sidewalk is painted up to this far before ``building_min_offset_m``."""
    parked_car_prob: float = 0.4
    """Probability that a spot holds a car, in each parked-car variant."""
    parked_car_jitter_along_m: Range = (-0.4, 0.4)
    """A parked car's offset from its spot along the road."""
    parked_car_jitter_across_m: Range = (-0.1, 0.1)
    """A parked car's offset from its spot across the road."""
    parked_car_yaw_jitter_deg: Range = (-2.0, 2.0)
    """A parked car's heading offset from the road's."""
    parked_car_length_m: Range = (4.2, 4.8)
    """Length of a parked car."""
    parked_car_width_m: Range = (1.75, 1.9)
    """Width of a parked car."""
    parked_car_height_m: Range = (1.4, 1.6)
    """Height of a parked car."""
    parked_car_rgb_frac: Range = (0.05, 0.95)
    """Each colour channel of a parked car's body (0 black .. 1 full)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            object.__setattr__(self, f.name, _checked_style_value(f.name, f.type, value))
        kinds = self.lot_kind_prob
        if abs(sum(kinds) - 1.0) > 1e-9:
            raise _style_error("lot_kind_prob", f"must sum to 1, got {kinds!r}")


# Ranges that may reach below zero (offsets either way); every other range and number must be >= 0.
_SIGNED_RANGES = frozenset(
    {
        "node_jitter_frac",
        "tree_offset_jitter_m",
        "parked_car_jitter_along_m",
        "parked_car_jitter_across_m",
        "parked_car_yaw_jitter_deg",
    }
)
# Numbers (or ranges' low ends) that must be > 0: sizes of geoms, divisors, steps of the placement loops.
_POSITIVE = frozenset(
    {
        "road_width_m",
        "lane_width_m",
        "road_thickness_m",
        "max_grade_m_per_m",
        "block_pitch_m",
        "max_block_pitch_m",
        "relief_blend_m",
        "relief_peak_to_peak_m",
        "relief_wavelength_m",
        "terrain_cell_m",
        "coarse_terrain_cell_m",
        "texture_px_m",
        "coarse_texture_px_m",
        "lot_width_m",
        "building_depth_m",
        "building_height_m",
        "building_height_beta_shape",
        "wing_width_frac",
        "wing_depth_m",
        "wing_height_frac",
        "building_shrink_frac",
        "wall_thickness_m",
        "wall_height_m",
        "pole_radius_m",
        "pole_height_m",
        "pole_spacing_m",
        "street_tree_spacing_m",
        "block_tree_area_m2",
        "block_tree_room_m",
        "street_tree_crown_radius_m",
        "block_tree_crown_radius_m",
        "tree_trunk_radius_m",
        "tree_trunk_height_m",
        "tree_crown_height_frac",
        "parking_pitch_m",
        "parking_spot_length_m",
        "parking_spot_width_m",
        "parked_car_length_m",
        "parked_car_width_m",
        "parked_car_height_m",
    }
)


def _style_error(name: str, problem: str) -> InputError:
    return InputError(f"TownStyle.{name} {problem}")


def _checked_style_value(name: str, kind: str, value: Any) -> Any:
    """``value`` of TownStyle field ``name`` (annotation ``kind``) as float, int or tuple; or InputError."""

    def number(v: Any) -> float:
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float, np.integer, np.floating))
            or not math.isfinite(v)
        ):
            raise _style_error(name, f"must be a finite number, got {value!r}")
        return float(v)

    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise _style_error(name, f"must be a positive integer, got {value!r}")
        return int(value)
    if kind == "float":
        values = (number(value),)
    else:  # Range, or a tuple of fractions
        if not isinstance(value, (tuple, list)) or not value:
            raise _style_error(name, f"must be a tuple of numbers, got {value!r}")
        values = tuple(number(v) for v in value)
        if kind == "Range" and len(values) != 2:
            raise _style_error(name, f"must be a range (low, high), got {value!r}")
        if kind == "tuple[float, float, float]" and len(values) != 3:
            raise _style_error(name, f"must hold 3 numbers, got {value!r}")
        if kind == "Range" and values[0] > values[1]:
            raise _style_error(name, f"must be a range (low, high) with low <= high, got {value!r}")
    if name.endswith(("_prob", "_shrink_frac")) and not all(0.0 <= v <= 1.0 for v in values):
        raise _style_error(name, f"must lie in [0, 1], got {value!r}")
    if name in _POSITIVE and min(values) <= 0.0:
        raise _style_error(name, f"must be positive, got {value!r}")
    if name not in _SIGNED_RANGES and min(values) < 0.0:
        raise _style_error(name, f"must not be negative, got {value!r}")
    return values[0] if kind == "float" else values


DEFAULT_STYLE = TownStyle()
"""The style of the shipped towns."""


@dataclass(frozen=True)
class TownPreset:
    """A named town of ``scenes/``: the arguments that :func:`generate_town` writes it from."""

    seed: int
    """Seed of the generator (``np.random.default_rng(seed)``)."""
    size_m: float
    """Side of the square town."""
    n_parked_variants: int = 2
    """Number of parked-car sets ``parked_v{k}_{i}``."""
    style: TownStyle = DEFAULT_STYLE
    """Sizes, offsets, spacings and random ranges of the generator."""


SHIPPED_TOWNS: dict[str, TownPreset] = {
    "town_small": TownPreset(seed=1, size_m=200.0),
    "town_medium": TownPreset(seed=3, size_m=300.0),
    "town_large": TownPreset(seed=2, size_m=600.0),
}
"""Scenes shipped in ``scenes/``, by name. town_medium is the second town of the global-localization suites
(another seed and size than town_large's)."""

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


# ----------------------------------------------------------------------------------------------- data types


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
        nodes: (K, 2) junction positions; edges: (E, 2) int node index pairs, each a straight two-way road.
        total_length_m: summed length of the edges (node to node).
        parked_variants: number of parked-car sets ``parked_v{k}_*`` in the XML.
        spawn: (x, y, yaw) a start pose in the right-hand lane of a road, heading along it.
        terrain: the height field (:class:`Terrain`).
        yaml_path: the sidecar this came from (the XML is ``yaml_path.with_suffix(".xml")``).
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


# ------------------------------------------------------------------------------------------------ geometry


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _rect_corners(center, yaw: float, half) -> np.ndarray:
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * np.asarray(half, float)
    return local @ _rot(yaw).T + np.asarray(center, float)


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between points p (..., 2) and segments a-b (..., 2), broadcast."""
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def rect_segment_distance(center, yaw: float, half, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance between an oriented rectangle and each segment a[i]-b[i] (0 where they intersect)."""
    center = np.asarray(center, float)
    hx, hy = (float(h) for h in half)
    R = _rot(yaw)
    la = (np.atleast_2d(a) - center) @ R  # world -> rectangle frame
    lb = (np.atleast_2d(b) - center) @ R
    # segment intersects the box? (Liang-Barsky clipping)
    d = lb - la
    t0 = np.zeros(len(la))
    t1 = np.ones(len(la))
    ok = np.ones(len(la), dtype=bool)
    for k, h in ((0, hx), (1, hy)):
        p = d[:, k]
        q0 = la[:, k]
        flat = np.abs(p) < 1e-12
        ok &= ~flat | (np.abs(q0) <= h)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-h - q0) / p
            tb = (h - q0) / p
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(flat, t1, np.minimum(t1, np.maximum(ta, tb)))
    hit = ok & (t0 <= t1)
    # otherwise: endpoints to the box, box corners to the segment
    h2 = np.array([hx, hy])
    d_end = np.minimum(
        np.linalg.norm(np.maximum(np.abs(la) - h2, 0.0), axis=1),
        np.linalg.norm(np.maximum(np.abs(lb) - h2, 0.0), axis=1),
    )
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    d_corner = _point_segment_distance(corners[None, :, :], la[:, None, :], lb[:, None, :]).min(axis=1)
    return np.where(hit, 0.0, np.minimum(d_end, d_corner))


def _rects_overlap(c1, yaw1, half1, c2, yaw2, half2, margin: float) -> bool:
    """Whether two oriented rectangles come closer than ``margin`` (separating axis test, inflated)."""
    p1 = _rect_corners(c1, yaw1, np.asarray(half1) + margin / 2)
    p2 = _rect_corners(c2, yaw2, np.asarray(half2) + margin / 2)
    for yaw in (yaw1, yaw2):
        for axis in (np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])):
            s1, s2 = p1 @ axis, p2 @ axis
            if s1.max() < s2.min() or s2.max() < s1.min():
                return False
    return True


class _Occupancy:
    """Placed footprints (oriented rectangles) in a spatial hash, for overlap tests."""

    def __init__(self, cell: float = 32.0):
        self.cell = cell
        self.items: list[tuple[np.ndarray, float, np.ndarray]] = []
        self.grid: dict[tuple[int, int], list[int]] = defaultdict(list)

    def _cells(self, center, radius: float):
        c = self.cell
        i0, i1 = math.floor((center[0] - radius) / c), math.floor((center[1] - radius) / c)
        j0, j1 = math.floor((center[0] + radius) / c), math.floor((center[1] + radius) / c)
        for i in range(i0, j0 + 1):
            for j in range(i1, j1 + 1):
                yield (i, j)

    def free(self, center, yaw: float, half, margin: float) -> bool:
        radius = float(np.hypot(*half)) + margin  # items are filed under every cell they touch
        seen: set[int] = set()
        for key in self._cells(center, radius):
            for k in self.grid.get(key, ()):
                if k in seen:
                    continue
                seen.add(k)
                c2, yaw2, half2 = self.items[k]
                if _rects_overlap(center, yaw, half, c2, yaw2, half2, margin):
                    return False
        return True

    def add(self, center, yaw: float, half) -> None:
        k = len(self.items)
        self.items.append((np.asarray(center, float), float(yaw), np.asarray(half, float)))
        for key in self._cells(center, float(np.hypot(*half))):
            self.grid[key].append(k)


# ------------------------------------------------------------------------------------------------ road graph


def _connected(n: int, edges: list[tuple[int, int]]) -> bool:
    adj: dict[int, list[int]] = defaultdict(list)
    for i, j in edges:
        adj[i].append(j)
        adj[j].append(i)
    seen = {0}
    stack = [0]
    while stack:
        for j in adj[stack.pop()]:
            if j not in seen:
                seen.add(j)
                stack.append(j)
    return len(seen) == n


def _road_graph(rng: np.random.Generator, size_m: float, style: TownStyle) -> tuple[np.ndarray, np.ndarray]:
    span = size_m - 2 * style.graph_margin_m
    n = max(2, round(span / style.block_pitch_m) + 1)
    spacing = min(span / (n - 1), style.max_block_pitch_m)
    grid = (np.arange(n) - (n - 1) / 2) * spacing
    gx, gy = np.meshgrid(grid, grid)  # node k = row * n + col, row along y
    nodes = np.stack([gx.ravel(), gy.ravel()], axis=1)
    nodes = nodes + rng.uniform(*style.node_jitter_frac, size=nodes.shape) * spacing
    nodes = np.round(nodes, 3)
    edges = [(r * n + c, r * n + c + 1) for r in range(n) for c in range(n - 1)]
    edges += [(r * n + c, (r + 1) * n + c) for r in range(n - 1) for c in range(n)]
    k = len(nodes)
    loops = len(edges) - k + 1
    min_loops = min(loops, max(style.min_loops_count, math.floor(loops * style.min_loops_frac)))
    n_remove = int(round(style.removed_roads_frac * len(edges)))
    removed = 0
    candidates = list(edges)
    for idx in rng.permutation(len(edges)).tolist():
        if removed >= n_remove or len(edges) - 1 - k + 1 < min_loops:
            break
        e = candidates[idx]
        trial = [f for f in edges if f != e]
        deg = np.bincount(np.array(trial).ravel(), minlength=k)
        if deg.min() >= 2 and _connected(k, trial):
            edges = trial
            removed += 1
    return nodes, np.array(sorted(edges), dtype=np.int64)


def _node_heights(nodes, edges, natural, max_grade: float, ramp_start_m: float) -> np.ndarray:
    """Node heights: the natural relief, relaxed until every road's grade is at most ``max_grade``."""
    h = natural(nodes[:, 0], nodes[:, 1]).astype(np.float64)
    length = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
    allowed = 0.98 * max_grade * (length - 2 * ramp_start_m)  # 2 % to spare
    for _ in range(10000):
        dh = h[edges[:, 1]] - h[edges[:, 0]]
        excess = np.abs(dh) - allowed
        if excess.max() <= 0:
            break
        fix = np.where(excess > 0, np.sign(dh) * excess / 2 * 1.01, 0.0)
        np.add.at(h, edges[:, 0], fix)
        np.add.at(h, edges[:, 1], -fix)
    return np.round(h, 4)


# -------------------------------------------------------------------------------------------------- terrain


def _natural_relief(rng: np.random.Generator, style: TownStyle):
    """A smooth random relief: a sum of long-wavelength plane waves; returns f(x, y) -> z."""
    k = style.relief_waves_count
    wavelength = rng.uniform(*style.relief_wavelength_m, k)
    theta = rng.uniform(0, 2 * np.pi, k)
    phase = rng.uniform(0, 2 * np.pi, k)
    amp = rng.uniform(*style.relief_wave_weight_frac, k)
    kx = 2 * np.pi / wavelength * np.cos(theta)
    ky = 2 * np.pi / wavelength * np.sin(theta)

    def f(x, y):
        x = np.asarray(x, float)[..., None]
        y = np.asarray(y, float)[..., None]
        return (amp * np.sin(kx * x + ky * y + phase)).sum(-1)

    return f


def _road_profile(s, length, ha, hb, ramp_start_m: float):
    """Road surface height at arc length s along an edge: flat near the nodes, one grade between."""
    t = np.clip((s - ramp_start_m) / (length - 2 * ramp_start_m), 0.0, 1.0)
    return ha + (hb - ha) * t


def _terrain_grid(xs, ys, nodes, edges, hnode, natural, relief_scale, style: TownStyle) -> np.ndarray:
    flat = style.flat_half_width_m
    a = nodes[edges[:, 0]]
    b = nodes[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    u = (b - a) / length[:, None]
    ha, hb = hnode[edges[:, 0]], hnode[edges[:, 1]]
    out = np.empty((len(ys), len(xs)))
    for r, y in enumerate(ys):
        p = np.stack([xs, np.full_like(xs, y)], axis=1)  # (N, 2)
        rel = p[:, None, :] - a[None, :, :]  # (N, E, 2)
        s = (rel * u[None]).sum(-1)
        lat = np.abs(rel[..., 0] * u[None, :, 1] - rel[..., 1] * u[None, :, 0])
        in_span = (s >= 0) & (s <= length[None])
        dseg = np.where(
            in_span,
            lat,
            np.minimum(np.linalg.norm(rel, axis=-1), np.linalg.norm(p[:, None, :] - b[None], axis=-1)),
        )
        prof = _road_profile(s, length[None], ha[None], hb[None], style.ramp_start_m)
        cand = np.where(in_span & (lat <= flat), prof, -np.inf).max(axis=1)
        dnode = np.linalg.norm(p[:, None, :] - nodes[None], axis=-1)
        cand = np.maximum(cand, np.where(dnode <= flat, hnode[None], -np.inf).max(axis=1))
        nearest = dseg.argmin(axis=1)
        dist = dseg[np.arange(len(p)), nearest]
        road = np.where(np.isfinite(cand), cand, prof[np.arange(len(p)), nearest])
        t = np.clip((dist - flat) / style.relief_blend_m, 0.0, 1.0)
        w = t * t * (3 - 2 * t)
        nat = natural(p[:, 0], p[:, 1]) * relief_scale
        out[r] = road + w * (nat - road)
    return out


def _paint_ground(size_m: float, px_m: float, nodes, edges, natural, style: TownStyle) -> np.ndarray:
    """The terrain's texture (H, W, 3) uint8: asphalt, parking strips, sidewalks and grass.

    Row 0 is the town's +y edge, column 0 its -x edge (how MuJoCo maps a 2D texture onto a height field
    with texrepeat 1 1). Painting the roads into the terrain hides the z-fighting of the coplanar road boxes.
    """
    n = round(size_m / px_m)
    centres = -size_m / 2 + (np.arange(n) + 0.5) * size_m / n
    a = nodes[edges[:, 0]]
    b = nodes[edges[:, 1]]
    img = np.empty((n, n, 3), dtype=np.uint8)
    asphalt = np.array(_ASPHALT_RGB)
    parking = np.array(_PARKING_RGB)
    sidewalk = np.array(_SIDEWALK_RGB)
    grass = np.array(_GRASS_RGB)
    sidewalk_m = style.building_min_offset_m - style.sidewalk_paint_inset_m
    parking_m = style.parking_offset_m + style.parking_paint_beyond_m
    for i in range(n):
        y = centres[n - 1 - i]
        p = np.stack([centres, np.full(n, y)], axis=1)
        d = _point_segment_distance(p[:, None, :], a[None], b[None]).min(axis=1)
        dn = np.linalg.norm(p[:, None, :] - nodes[None], axis=-1).min(axis=1)
        shade = 1.0 + _GRASS_SHADE_FRAC * natural(p[:, 0], p[:, 1]) / style.relief_peak_to_peak_m
        row = np.clip(grass[None] * shade[:, None], 0, 255)
        row = np.where((d <= sidewalk_m)[:, None], sidewalk[None], row)
        row = np.where((d <= parking_m)[:, None], parking[None], row)
        road = (d <= style.road_width_m / 2) | (dn <= style.junction_radius_m)
        row = np.where(road[:, None], asphalt[None], row)
        img[i] = np.round(row).astype(np.uint8)
    return img


def _write_png(path: Path, img: np.ndarray) -> None:
    """``img`` (H, W, 3) uint8 as an RGB8 PNG (no metadata chunks: the same pixels write the same bytes)."""
    Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)).save(path, format="PNG", compress_level=9)


# ------------------------------------------------------------------------------------------------- objects


@dataclass
class _Box:
    name: str
    pos: tuple[float, float, float]
    size: tuple[float, float, float]  # half sizes
    yaw: float
    material: str
    pitch: float = 0.0


@dataclass
class _Pole:
    name: str
    xy: tuple[float, float]
    z0: float
    radius: float
    height: float


@dataclass
class _Tree:
    name: str
    xy: tuple[float, float]
    z0: float
    trunk_r: float
    trunk_h: float
    crown: tuple[float, float, float]  # ellipsoid semi-axes
    crown_z: float  # crown centre height above z0


@dataclass
class _ParkedCar:
    name: str
    pos: tuple[float, float, float]
    yaw: float
    length: float
    width: float
    height: float
    rgba: tuple[float, float, float]


class _Planner:
    """Places buildings, walls, poles, trees and parked cars beside the roads without overlaps."""

    def __init__(self, rng, size_m, nodes, edges, ground, style: TownStyle):
        self.rng = rng
        self.style = style
        self.size_m = size_m
        self.nodes = nodes
        self.edges = edges
        self.a = nodes[edges[:, 0]]
        self.b = nodes[edges[:, 1]]
        self.ground = ground
        self.occ = _Occupancy()
        self.boxes: list[_Box] = []
        self.poles: list[_Pole] = []
        self.trees: list[_Tree] = []
        self.n_buildings = 0
        self.n_walls = 0

    # -- helpers
    def _road_distance(self, center, yaw, half, skip: int | None = None) -> float:
        d = rect_segment_distance(center, yaw, half, self.a, self.b)
        if skip is not None:
            d[skip] = np.inf
        return float(d.min())

    def _inside(self, center, yaw, half, margin: float) -> bool:
        lim = self.size_m / 2 - margin
        return bool(np.all(np.abs(_rect_corners(center, yaw, half)) <= lim))

    def _frame(self, e: int):
        a, b = self.a[e], self.b[e]
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        n = np.array([-u[1], u[0]])
        return a, u, n, length, math.atan2(u[1], u[0])

    def _base_top(self, center, yaw, half):
        corners = _rect_corners(center, yaw, half)
        pts = np.vstack([corners, center])
        z = self.ground(pts[:, 0], pts[:, 1])
        return float(z.min()), float(z.max())

    # -- buildings and walls along the frontages
    def frontages(self) -> None:
        rng, st = self.rng, self.style
        jr = st.junction_radius_m
        for e in range(len(self.edges)):
            a, u, n, length, yaw = self._frame(e)
            for side in (1.0, -1.0):
                s = jr + rng.uniform(*st.lot_start_m)
                while s < length - jr - st.lot_min_width_m:
                    width = rng.uniform(*st.lot_width_m)
                    width = min(width, length - jr - s)
                    kind = rng.choice(["building", "wall", "gap"], p=list(st.lot_kind_prob))
                    if width >= st.lot_min_width_m and kind == "building":
                        self._building(a, u, n, yaw, side, s, width)
                    elif width >= st.lot_min_width_m and kind == "wall":
                        self._wall(a, u, n, yaw, side, s, width)
                    s += width + rng.uniform(*st.lot_gap_m)

    def _building(self, a, u, n, yaw, side, s, width) -> None:
        rng, st = self.rng, self.style
        setback = rng.uniform(
            st.building_min_offset_m + st.building_setback_m[0],
            st.building_min_offset_m + st.building_setback_m[1],
        )
        depth = rng.uniform(*st.building_depth_m)
        h_lo, h_hi = st.building_height_m
        height = h_lo + (h_hi - h_lo) * rng.beta(*st.building_height_beta_shape)
        l_shape = rng.random() < st.l_shape_prob
        wing_w = rng.uniform(*st.wing_width_frac) * width
        wing_d = rng.uniform(*st.wing_depth_m)
        wing_end = rng.choice([-1.0, 1.0])
        wing_h = max(h_lo, height * rng.uniform(*st.wing_height_frac))
        for shrink in st.building_shrink_frac:
            w, d = width * shrink, depth * shrink
            center = a + u * (s + w / 2) + side * n * (setback + d / 2)
            rects = [(center, (w / 2, d / 2), height)]
            if l_shape:
                ww, wd = wing_w * shrink, wing_d * shrink
                wing_lateral = setback + d + wd / 2 - st.wing_overlap_m
                wc = a + u * (s + w / 2 + wing_end * (w - ww) / 2) + side * n * wing_lateral
                rects.append((wc, (ww / 2, wd / 2), wing_h))
            if all(
                self._placeable(c, yaw, h, st.building_min_offset_m, st.building_gap_m) for c, h, _ in rects
            ):
                b = self.n_buildings
                self.n_buildings += 1
                mat = f"building{rng.integers(0, _N_BUILDING_MATERIALS)}"
                for (c, half, tall), tag in zip(rects, "ab", strict=False):
                    self.occ.add(c, yaw, half)
                    zb, zt = self._base_top(c, yaw, half)
                    z0 = zb - st.building_sink_m  # sunk into the ground on its lowest corner
                    z1 = zt + tall
                    self.boxes.append(
                        _Box(
                            f"bldg_{b}_{tag}",
                            (c[0], c[1], (z0 + z1) / 2),
                            (half[0], half[1], (z1 - z0) / 2),
                            yaw,
                            mat,
                        )
                    )
                return

    def _placeable(self, center, yaw, half, road_clearance: float, gap: float, skip=None) -> bool:
        return (
            self._inside(center, yaw, half, self.style.border_margin_m)
            and self._road_distance(center, yaw, half, skip) >= road_clearance
            and self.occ.free(center, yaw, half, gap)
        )

    def _wall(self, a, u, n, yaw, side, s, width) -> None:
        rng, st = self.rng, self.style
        thick = st.wall_thickness_m
        lateral = st.building_min_offset_m + thick / 2 + rng.uniform(*st.wall_setback_m)
        height = rng.uniform(*st.wall_height_m)
        center = a + u * (s + width / 2) + side * n * lateral
        half = (width / 2, thick / 2)
        if self._placeable(center, yaw, half, st.building_min_offset_m, st.wall_gap_m):
            self.occ.add(center, yaw, half)
            zb, zt = self._base_top(center, yaw, half)
            z0, z1 = zb - st.sink_m, zt + height
            self.boxes.append(
                _Box(
                    f"wall_{self.n_walls}",
                    (center[0], center[1], (z0 + z1) / 2),
                    (*half, (z1 - z0) / 2),
                    yaw,
                    "wall",
                )
            )
            self.n_walls += 1

    # -- street furniture
    def poles_and_street_trees(self) -> None:
        rng, st = self.rng, self.style
        jr = st.junction_radius_m
        # a start range (lo, hi) is drawn as lo + U(0, hi - lo), the arithmetic that wrote the shipped towns
        pole_lo, pole_hi = st.pole_start_m
        tree_lo, tree_hi = st.street_tree_start_m
        for e in range(len(self.edges)):
            a, u, n, length, yaw = self._frame(e)
            s = jr + pole_lo + rng.uniform(0.0, pole_hi - pole_lo)
            side = rng.choice([-1.0, 1.0])
            while s < length - jr - pole_lo:
                xy = a + u * s + side * n * st.pole_offset_m
                r = st.pole_radius_m
                clearance = st.pole_offset_m - st.pole_road_slack_m
                if self._placeable(xy, yaw, (r, r), clearance, st.pole_gap_m, skip=None):
                    self.occ.add(xy, yaw, (r, r))
                    self.poles.append(
                        _Pole(
                            f"pole_{len(self.poles)}",
                            (xy[0], xy[1]),
                            float(self.ground(xy[0], xy[1])) - st.sink_m,
                            r,
                            rng.uniform(*st.pole_height_m) + st.sink_m,
                        )
                    )
                s += rng.uniform(*st.pole_spacing_m)
                side = -side
            for side in (1.0, -1.0):
                s = jr + tree_lo + rng.uniform(0.0, tree_hi - tree_lo)
                while s < length - jr - tree_lo:
                    if rng.random() < st.street_tree_prob:
                        xy = a + u * s + side * n * (st.tree_offset_m + rng.uniform(*st.tree_offset_jitter_m))
                        clearance = st.tree_offset_m - st.street_tree_road_slack_m
                        self._tree(xy, st.street_tree_crown_radius_m, road_clearance=clearance)
                    s += rng.uniform(*st.street_tree_spacing_m)

    def _tree(self, xy, crown_radius_m: Range, road_clearance: float) -> None:
        rng, st = self.rng, self.style
        trunk_r = rng.uniform(*st.tree_trunk_radius_m)
        if not self._placeable(xy, 0.0, (trunk_r, trunk_r), road_clearance, st.tree_gap_m):
            return
        crown_r = rng.uniform(*crown_radius_m)
        crown_h = crown_r * rng.uniform(*st.tree_crown_height_frac)
        trunk_h = rng.uniform(*st.tree_trunk_height_m)
        into = st.tree_trunk_into_crown_frac
        crown_z = max(trunk_h + into * crown_h, st.tree_crown_min_bottom_m + crown_h)
        self.occ.add(xy, 0.0, (trunk_r, trunk_r))
        self.trees.append(
            _Tree(
                f"tree_{len(self.trees)}",
                (xy[0], xy[1]),
                float(self.ground(xy[0], xy[1])) - st.sink_m,
                trunk_r,
                trunk_h + st.sink_m + into * crown_h,
                (crown_r, crown_r, crown_h),
                crown_z + st.sink_m,
            )
        )

    def block_trees(self) -> None:
        rng, st = self.rng, self.style
        n = int(self.size_m**2 / st.block_tree_area_m2)
        half = self.size_m / 2 - st.block_tree_border_m
        for _ in range(n):
            xy = rng.uniform(-half, half, 2)
            room = rng.uniform(*st.block_tree_room_m)
            if self.occ.free(xy, 0.0, (room, room), st.block_tree_room_gap_m):
                self._tree(xy, st.block_tree_crown_radius_m, road_clearance=st.block_tree_road_clearance_m)

    # -- parked cars
    def parking_spots(self) -> list[tuple[np.ndarray, float, int]]:
        """Spots (centre xy, yaw facing the traffic of that side, edge index) in the parking strips."""
        st = self.style
        pitch = st.parking_pitch_m
        half = (st.parking_spot_length_m / 2, st.parking_spot_width_m / 2)
        spots = []
        for e in range(len(self.edges)):
            a, u, n, length, yaw = self._frame(e)
            count = int((length - 2 * (st.junction_radius_m + st.parking_end_clearance_m)) // pitch)
            if count <= 0:
                continue
            s0 = (length - (count - 1) * pitch) / 2
            for side in (1.0, -1.0):
                heading = yaw if side < 0 else yaw + math.pi  # right-hand traffic
                heading = float(wrap_angle(heading))
                for i in range(count):
                    xy = a + u * (s0 + i * pitch) + side * n * st.parking_offset_m
                    clearance = st.road_width_m / 2 + st.parking_spot_road_clearance_m
                    if self._road_distance(xy, heading, half, skip=e) < clearance:
                        continue  # would stand on another road
                    if not self.occ.free(xy, heading, half, st.parking_spot_gap_m):
                        continue  # a pole, tree or wall in the way
                    spots.append((xy, heading, e))
        return spots

    def parked_variant(self, k: int, spots) -> list[_ParkedCar]:
        rng, st = self.rng, self.style
        cars = []
        take = rng.random(len(spots)) < st.parked_car_prob
        for idx in np.flatnonzero(take):
            xy, heading, e = spots[idx]
            _, u, n, _, _ = self._frame(e)
            xy = (
                xy
                + u * rng.uniform(*st.parked_car_jitter_along_m)
                + n * rng.uniform(*st.parked_car_jitter_across_m)
            )
            yaw = heading + math.radians(rng.uniform(*st.parked_car_yaw_jitter_deg))
            rgb = tuple(float(c) for c in np.round(rng.uniform(*st.parked_car_rgb_frac, 3), 3))
            cars.append(
                _ParkedCar(
                    f"parked_v{k}_{len(cars)}",
                    (float(xy[0]), float(xy[1]), float(self.ground(xy[0], xy[1]))),
                    yaw,
                    rng.uniform(*st.parked_car_length_m),
                    rng.uniform(*st.parked_car_width_m),
                    rng.uniform(*st.parked_car_height_m),
                    rgb,
                )
            )
        return cars


# ---------------------------------------------------------------------------------------------- XML output


def _f(v: float, nd: int = 4) -> str:
    s = f"{v:.{nd}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _v(*vals: float, nd: int = 4) -> str:
    return " ".join(_f(v, nd) for v in vals)


def _quat(yaw: float, pitch: float = 0.0) -> str:
    """Quaternion (w x y z) of Rz(yaw) @ Ry(pitch), as MJCF text."""
    return _v(*quat_wxyz_from_ypr(yaw, pitch), nd=6)


def _style_note(style: TownStyle) -> str:
    """``, style=TownStyle(field=value, ...)`` with the fields that differ from the default; "" if none."""
    changed = [
        f"{f.name}={getattr(style, f.name)!r}"
        for f in fields(style)
        if getattr(style, f.name) != getattr(DEFAULT_STYLE, f.name)
    ]
    return f", style=TownStyle({', '.join(changed)})" if changed else ""


def _write_xml(
    path: Path,
    name,
    seed,
    size_m,
    style: TownStyle,
    terrain: Terrain,
    texture: str,
    road_boxes,
    junctions,
    plan,
    variants,
) -> None:
    half = size_m / 2
    thick = style.road_thickness_m
    call = f"seed={seed}, size_m={size_m}{_style_note(style)}"
    ex = [
        f'<mujoco model="{name}">',
        f"  <!-- generated by simbed.scenes.towngen.generate_town({call}); do not edit -->",
        '  <option timestep="0.002"/>',
        *_arena_size(1 + _CAR_BODIES_MAX + sum(len(cars) for cars in variants)),
        f'  <statistic center="0 0 1" extent="{_f(half)}"/>',
        "  <visual>",
        '    <global offwidth="1280" offheight="960"/>',
        '    <headlight ambient="0.35 0.35 0.35" diffuse="0.55 0.55 0.55" specular="0.1 0.1 0.1"/>',
        f'    <map znear="{_f(0.05 / half, 6)}" zfar="{_f(4 * size_m / half)}" haze="0.2"/>',
        '    <quality shadowsize="4096"/>',
        "  </visual>",
        '  <include file="car.xml"/>',
        "  <asset>",
        '    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.52 0.68 0.88" rgb2="0.92 0.95 1"'
        ' width="512" height="3072"/>',
        f'    <texture name="ground" type="2d" file="{texture}" content_type="image/png"/>',
        '    <material name="terrain" texture="ground" texrepeat="1 1"/>',
        f'    <hfield name="terrain" file="{terrain.file}"'
        f' size="{_v(*terrain.half_size, terrain.z_range, 1.0, nd=6)}"/>',
        '    <material name="road" rgba="0.22 0.22 0.24 1"/>',
        '    <material name="junction" rgba="0.22 0.22 0.24 1"/>',
        '    <material name="wall" rgba="0.62 0.58 0.52 1"/>',
        '    <material name="pole" rgba="0.45 0.45 0.48 1"/>',
        '    <material name="trunk" rgba="0.40 0.28 0.18 1"/>',
        '    <material name="crown" rgba="0.22 0.45 0.18 1"/>',
        '    <material name="building0" rgba="0.78 0.74 0.66 1"/>',
        '    <material name="building1" rgba="0.62 0.64 0.68 1"/>',
        '    <material name="building2" rgba="0.72 0.52 0.42 1"/>',
        '    <material name="building3" rgba="0.86 0.84 0.80 1"/>',
        '    <material name="building4" rgba="0.50 0.52 0.56 1"/>',
        "  </asset>",
        "  <worldbody>",
        '    <light name="sun" directional="true" pos="0 0 200" dir="-0.3 -0.4 -1" diffuse="0.5 0.5 0.5"'
        ' castshadow="true"/>',
        f'    <camera name="overview" pos="0 0 {_f(size_m * 1.3)}" xyaxes="1 0 0 0 1 0" fovy="45"/>',
        f'    <geom name="terrain" type="hfield" hfield="terrain"'
        f' pos="{_v(*terrain.center, terrain.z_min, nd=6)}" material="terrain"/>',
    ]
    for bx in road_boxes:
        ex.append(
            f'    <geom name="{bx.name}" type="box" pos="{_v(*bx.pos)}" size="{_v(*bx.size)}"'
            f' quat="{_quat(bx.yaw, bx.pitch)}" material="{bx.material}"/>'
        )
    for nm, xy, z in junctions:
        ex.append(
            f'    <geom name="{nm}" type="cylinder" pos="{_v(xy[0], xy[1], z - thick / 2)}"'
            f' size="{_v(style.junction_radius_m, thick / 2)}" material="junction"/>'
        )
    for bx in plan.boxes:
        ex.append(
            f'    <geom name="{bx.name}" type="box" pos="{_v(*bx.pos)}" size="{_v(*bx.size)}"'
            f' quat="{_quat(bx.yaw)}" material="{bx.material}"/>'
        )
    for p in plan.poles:
        ex.append(
            f'    <geom name="{p.name}" type="cylinder" pos="{_v(p.xy[0], p.xy[1], p.z0 + p.height / 2)}"'
            f' size="{_v(p.radius, p.height / 2)}" material="pole"/>'
        )
    for t in plan.trees:
        ex.append(
            f'    <geom name="{t.name}_trunk" type="cylinder"'
            f' pos="{_v(t.xy[0], t.xy[1], t.z0 + t.trunk_h / 2)}"'
            f' size="{_v(t.trunk_r, t.trunk_h / 2)}" material="trunk"/>'
        )
        ex.append(
            f'    <geom name="{t.name}_crown" type="ellipsoid" pos="{_v(t.xy[0], t.xy[1], t.z0 + t.crown_z)}"'
            f' size="{_v(*t.crown)}" material="crown"/>'
        )
    for cars in variants:
        for c in cars:
            body_h = 0.5 * c.height
            cab_h = c.height - 0.2 - body_h
            rgba = f"{_v(*c.rgba, nd=3)} 1"
            ex.append(f'    <body name="{c.name}" pos="{_v(*c.pos)}" quat="{_quat(c.yaw)}">')
            ex.append(
                f'      <geom name="{c.name}_body" type="box" pos="0 0 {_f(0.2 + body_h / 2)}"'
                f' size="{_v(c.length / 2, c.width / 2, body_h / 2)}" rgba="{rgba}"/>'
            )
            ex.append(
                f'      <geom name="{c.name}_cabin" type="box"'
                f' pos="{_f(-0.1 * c.length)} 0 {_f(0.2 + body_h + cab_h / 2)}"'
                f' size="{_v(0.25 * c.length, c.width / 2 - 0.06, cab_h / 2)}" rgba="0.15 0.18 0.22 1"/>'
            )
            ex.append("    </body>")
    ex += ["  </worldbody>", "</mujoco>", ""]
    path.write_text("\n".join(ex))


_CAR_BODIES_MAX = 32  # bodies of car.xml, with room to spare


def _arena_size(n_bodies: int) -> list[str]:
    """MuJoCo's collision step takes a body-pair matrix (2 bytes a pair) from the model's arena, and its
    broad phase as much again: a city's thousands of parked-car bodies need more than MuJoCo's default
    (a 2 km town: 12,472 bodies, 311 MB each). Towns with fewer than 1,500 bodies (the shipped ones) keep
    the default and their bytes."""
    if n_bodies < 1500:
        return []
    mb = math.ceil((2 * 2 * n_bodies**2 * 1.25) / 2**20) + 64
    return [f'  <size memory="{mb}M"/>']


def _write_terrain(path: Path, data: np.ndarray) -> None:
    nrow, ncol = data.shape
    with open(path, "wb") as fh:
        fh.write(np.array([nrow, ncol], dtype="<i4").tobytes())
        fh.write(np.ascontiguousarray(data, dtype="<f4").tobytes())


def _write_yaml(path: Path, info: TownInfo) -> None:
    t = info.terrain
    nodes = ", ".join(f"[{_f(x, 3)}, {_f(y, 3)}]" for x, y in info.nodes)
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


# ------------------------------------------------------------------------------------------------- public


def generate_town(
    seed: int,
    size_m: float,
    out_xml: Path,
    *,
    n_parked_variants: int = 2,
    name: str | None = None,
    style: TownStyle = DEFAULT_STYLE,
    overwrite: bool = True,
) -> TownInfo:
    """Generate a town: write ``out_xml``, ``<stem>_terrain.bin``, ``<stem>_ground.img`` and ``<stem>.yaml``.

    Args:
        seed: the generator seed (``np.random.default_rng(seed)``); the same seed writes the same bytes.
        size_m: side of the square town in metres (at least 120); roads, buildings and terrain lie inside
            ``[-size_m/2, size_m/2]``². The height field has ``style.terrain_cell_m`` cells (1 m) up to
            ``style.fine_max_size_m`` (300 m), ``style.coarse_terrain_cell_m`` cells (2 m) beyond.
        out_xml: the MJCF file to write; ``car.xml`` is copied next to it unless already there.
        n_parked_variants: number of parked-car sets ``parked_v{k}_{i}`` (k = 0 .. n-1).
        name: the town's name (default: ``out_xml``'s stem).
        style: the generator's sizes, offsets, spacings and random ranges (:class:`TownStyle`); the XML's
            header comment names the fields that differ from the default.
        overwrite: replace a town's files that exist; ``False`` refuses them before any work, naming
            ``--overwrite`` (``simbed make-town``'s policy,
            :func:`rangemcl.common.outdir.check_output_files`).

    Returns:
        The :class:`TownInfo` that the sidecar holds.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"town seed must be a non-negative integer, got {seed!r}")
    if not isinstance(size_m, (int, float, np.integer, np.floating)) or not 120.0 <= float(size_m) <= 5000.0:
        raise InputError(f"town size_m must be a number in [120, 5000], got {size_m!r}")
    if isinstance(n_parked_variants, bool) or not isinstance(n_parked_variants, int) or n_parked_variants < 0:
        raise InputError(f"n_parked_variants must be a non-negative integer, got {n_parked_variants!r}")
    if not isinstance(style, TownStyle):
        raise InputError(f"town style must be a TownStyle, got {type(style).__name__}")
    seed = int(seed)
    size_m = float(size_m)
    out_xml = Path(out_xml)
    name = out_xml.stem if name is None else str(name)
    if not name:
        raise InputError("town name must not be empty")
    if out_xml.suffix.lower() != ".xml":
        raise InputError(f"{out_xml}: a town is an MJCF file, give a name ending in .xml")
    check_output_files(town_files(out_xml), overwrite=overwrite, what="the town")
    rng = np.random.default_rng(seed)

    # roads and terrain
    nodes, edges = _road_graph(rng, size_m, style)
    relief = _natural_relief(rng, style)
    fine = size_m <= style.fine_max_size_m
    cell = style.terrain_cell_m if fine else style.coarse_terrain_cell_m
    n = round(size_m / cell) + 1
    xs = np.linspace(-size_m / 2, size_m / 2, n)
    probe = relief(*np.meshgrid(xs[::4], xs[::4]))
    relief_scale = style.relief_peak_to_peak_m / float(probe.max() - probe.min())

    def natural(x, y):
        return relief(x, y) * relief_scale

    hnode = _node_heights(nodes, edges, natural, style.max_grade_m_per_m, style.ramp_start_m)
    grid = _terrain_grid(xs, xs, nodes, edges, hnode, relief, relief_scale, style)
    gmin, gmax = float(grid.min()), float(grid.max())
    data = ((grid - gmin) / (gmax - gmin)).astype(np.float32)
    data = np.clip(data, 0.0, 1.0)
    data[np.unravel_index(np.argmin(grid), grid.shape)] = 0.0
    data[np.unravel_index(np.argmax(grid), grid.shape)] = 1.0
    terrain = Terrain(
        center=(0.0, 0.0),
        half_size=(size_m / 2, size_m / 2),
        z_min=round(gmin, 6),
        z_range=round(gmax - gmin, 6),
        data=data,
        file=f"{out_xml.stem}_terrain.bin",
    )

    # road surfaces: one tilted box per edge (ramp part), one disc per junction
    road_boxes = []
    a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
    lengths = np.linalg.norm(b - a, axis=1)
    for e, (i, j) in enumerate(edges):
        u = (b[e] - a[e]) / lengths[e]
        run = lengths[e] - 2 * style.ramp_start_m
        dh = float(hnode[j] - hnode[i])
        pitch = -math.atan2(dh, run)  # positive pitch about y tips the nose down
        mid = (a[e] + b[e]) / 2
        top = (hnode[i] + hnode[j]) / 2
        # box centre = top-surface centre minus half the thickness along the tilted normal
        nrm = np.array([-math.sin(-pitch) * u[0], -math.sin(-pitch) * u[1], math.cos(pitch)])
        c = np.array([mid[0], mid[1], top]) - nrm * style.road_thickness_m / 2
        road_boxes.append(
            _Box(
                f"road_{e}",
                (float(c[0]), float(c[1]), float(c[2])),
                (math.hypot(run, dh) / 2, style.road_width_m / 2, style.road_thickness_m / 2),
                math.atan2(u[1], u[0]),
                "road",
                pitch,
            )
        )
    junctions = [(f"junction_{k}", nodes[k], float(hnode[k])) for k in range(len(nodes))]

    ground = terrain.height
    e0 = int(rng.integers(len(edges)))
    u0 = (b[e0] - a[e0]) / lengths[e0]
    p0 = a[e0] + u0 * lengths[e0] / 2 - np.array([-u0[1], u0[0]]) * style.lane_width_m / 2
    spawn = (round(float(p0[0]), 4), round(float(p0[1]), 4), round(math.atan2(u0[1], u0[0]), 6))

    plan = _Planner(rng, size_m, nodes, edges, ground, style)
    plan.frontages()
    plan.poles_and_street_trees()
    plan.block_trees()
    spots = plan.parking_spots()
    variants = [plan.parked_variant(k, spots) for k in range(n_parked_variants)]

    info = TownInfo(
        name=name,
        seed=seed,
        size_m=size_m,
        road_width_m=style.road_width_m,
        lane_width_m=style.lane_width_m,
        nodes=nodes,
        edges=edges,
        total_length_m=round(float(lengths.sum()), 3),
        parked_variants=n_parked_variants,
        spawn=spawn,
        terrain=terrain,
        yaml_path=out_xml.with_suffix(".yaml"),
    )
    out_xml.parent.mkdir(parents=True, exist_ok=True)
    _write_terrain(out_xml.parent / terrain.file, data)
    texture = f"{out_xml.stem}_ground.img"  # a PNG; not named *.png, which the repository's .gitignore drops
    px_m = style.texture_px_m if fine else style.coarse_texture_px_m
    _write_png(out_xml.parent / texture, _paint_ground(size_m, px_m, nodes, edges, natural, style))
    _write_xml(out_xml, name, seed, size_m, style, terrain, texture, road_boxes, junctions, plan, variants)
    _write_yaml(out_xml.with_suffix(".yaml"), info)
    car_copy = out_xml.parent / "car.xml"
    if car_copy.resolve() != CAR_XML.resolve():
        shutil.copyfile(CAR_XML, car_copy)
    return info


def town_files(out_xml: Path | str) -> list[Path]:
    """The files :func:`generate_town` writes for ``out_xml`` (beside them it copies ``car.xml``)."""
    out_xml = Path(out_xml)
    stem = out_xml.stem
    return [out_xml, out_xml.with_name(f"{stem}_terrain.bin"), out_xml.with_name(f"{stem}_ground.img"),
            out_xml.with_suffix(".yaml")]  # fmt: skip


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


def generate_preset(preset: TownPreset, out_xml: Path | str, *, name: str | None = None) -> TownInfo:
    """Write the town of ``preset`` (seed, size, parked-car variants and style) to ``out_xml``."""
    return generate_town(
        preset.seed,
        preset.size_m,
        Path(out_xml),
        n_parked_variants=preset.n_parked_variants,
        name=name,
        style=preset.style,
    )


def generate_shipped(scenes_dir: Path | str | None = None) -> dict[str, TownInfo]:
    """(Re)generate the towns shipped in ``scenes/`` (:data:`SHIPPED_TOWNS`)."""
    folder = CAR_XML.parent if scenes_dir is None else Path(scenes_dir)
    return {nm: generate_preset(preset, folder / f"{nm}.xml") for nm, preset in SHIPPED_TOWNS.items()}


if __name__ == "__main__":
    for nm, info in generate_shipped().items():
        print(f"{nm}: {len(info.nodes)} nodes, {len(info.edges)} roads, {info.total_length_m:.0f} m of road")
