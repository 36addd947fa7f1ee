"""What the town generator draws from: :class:`TownStyle` (every size, offset, spacing and random range, each
field documented, its unit in its name), the named styles (:data:`TOWN_STYLES`) and the towns shipped in
``scenes/`` (:class:`TownPreset`, :data:`SHIPPED_TOWNS`)."""

from __future__ import annotations  # TownStyle checks its fields by their annotations' text ("Range", ...)

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from rangemcl.errors import InputError

Range = tuple[float, float]
"""A closed interval (low, high) that a value is drawn from uniformly, unless its field says otherwise."""


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
    layout: str = "grid"
    """Where the junctions lie: ``"grid"`` (a jittered grid, the fields above) or ``"organic"`` (scattered
    junctions joined by a planar graph, the fields below); either way roads are then removed as
    ``removed_roads_frac``, ``min_loops_count`` and ``min_loops_frac`` say."""
    junction_spacing_m: float = 45.0
    """Organic layout: least distance between two junctions (Poisson-disc points inside the town's border
    less ``graph_margin_m``)."""
    junction_candidates_count: int = 40
    """Organic layout: candidate points drawn per ``junction_spacing_m``² of area; each is kept if no kept one
    lies nearer than ``junction_spacing_m`` (more candidates fill the town more tightly)."""
    max_road_length_m: float = 120.0
    """Organic layout: edges of the junctions' Delaunay triangulation longer than this are no roads."""
    min_road_angle_deg: float = 60.0
    """Least angle between two roads leaving one node: the organic layout drops the longer road of a sharper
    pair, and a bend that makes a sharper angle is not taken. A route turning between two roads rounds the
    corner with a fillet of up to 7 m radius, which at sharper angles leaves the asphalt toward the poles
    and parked cars of the wedge between them."""
    road_clearance_m: float = 14.0
    """Least distance between the centre lines of two road pieces that share no node (a road width plus
    margins): the organic layout drops the longer road of a closer pair, and a bend that comes closer to
    another road is not taken."""
    bent_road_prob: float = 0.0
    """Probability that a road (junction to junction) is bent: cut into pieces joined at bend nodes displaced
    sideways, so that it winds (0: every road straight, the grid towns of ``scenes/``)."""
    bend_piece_m: Range = (20.0, 35.0)
    """Wanted length of the pieces of a bent road: ``round(length / drawn value)`` pieces, as many as keep
    every piece at least the low end long; a road too short for two pieces stays straight."""
    bend_amplitude_frac: Range = (0.05, 0.15)
    """Largest sideways displacement of a bent road's centre line, as a fraction of its length (to either
    side at random; halved, then the road left straight, where the bend would come too near a road)."""
    bend_s_curve_prob: float = 0.35
    """Probability that a bent road is an S (a full sine period) rather than an arc (half a period)."""
    bend_margin_m: float = 2.0
    """Lots, poles, street trees and parking spots of a road piece reach this near a bend node (at a junction
    they stop at the junction disc, ``junction_radius_m``; parking ``parking_end_clearance_m`` beyond)."""

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
    building_height_outskirts_frac: float = 1.0
    """The top of ``building_height_m`` shrinks toward the town's border: the span above the low end is scaled
    by 1 at the centre, falling linearly with the distance from the centre to this fraction at half the
    town's size (and beyond); 1 keeps the range everywhere."""
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
# The string fields and the values each may take.
_CHOICES = {"layout": ("grid", "organic")}
# Numbers (or ranges' low ends) that must be > 0: sizes of geoms, divisors, steps of the placement loops.
_POSITIVE = frozenset(
    {
        "road_width_m",
        "lane_width_m",
        "road_thickness_m",
        "max_grade_m_per_m",
        "block_pitch_m",
        "max_block_pitch_m",
        "junction_spacing_m",
        "max_road_length_m",
        "road_clearance_m",
        "bend_piece_m",
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
    """``value`` of TownStyle field ``name`` (annotation ``kind``) as float, int, tuple or one of the field's
    string choices; or InputError."""

    def number(v: Any) -> float:
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float, np.integer, np.floating))
            or not math.isfinite(v)
        ):
            raise _style_error(name, f"must be a finite number, got {value!r}")
        return float(v)

    if kind == "str":
        allowed = _CHOICES[name]
        if not isinstance(value, str) or value not in allowed:
            raise _style_error(name, f"must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        return value
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

TOWN_STYLES: dict[str, TownStyle] = {
    "grid": DEFAULT_STYLE,
    "suburb": replace(
        DEFAULT_STYLE,
        layout="organic",
        removed_roads_frac=0.15,
        min_loops_count=2,
        min_loops_frac=0.6,
        bent_road_prob=1.0,
        lot_width_m=(10.0, 16.0),
        lot_gap_m=(2.0, 6.0),
        lot_kind_prob=(0.68, 0.24, 0.08),
        building_setback_m=(2.0, 6.0),
        building_depth_m=(8.0, 12.0),
        building_height_m=(4.0, 10.0),
        building_height_beta_shape=(1.5, 2.5),
        l_shape_prob=0.3,
        wing_depth_m=(4.0, 8.0),
        wall_height_m=(0.8, 1.6),
        street_tree_prob=0.85,
        street_tree_spacing_m=(8.0, 16.0),
        street_tree_crown_radius_m=(1.6, 2.6),
        block_tree_area_m2=300.0,
        block_tree_crown_radius_m=(2.0, 4.5),
        tree_trunk_height_m=(3.0, 5.0),
        parked_car_prob=0.15,
    ),
    "mixed": replace(
        DEFAULT_STYLE,
        bent_road_prob=0.35,
        building_height_m=(4.0, 40.0),
        building_height_beta_shape=(1.2, 2.0),
        building_height_outskirts_frac=0.2,
        lot_kind_prob=(0.76, 0.12, 0.12),
        parked_car_prob=0.35,
    ),
}
"""Named styles (``simbed make-town --style``): ``grid``, the shipped towns' jittered grid of straight roads
(:data:`DEFAULT_STYLE`); ``suburb``, scattered junctions and winding roads, low houses on small footprints set
back from the road, more and bigger trees, low walls more often, fewer parked cars; ``mixed``, the grid with
about a third of its roads bent, tall buildings in the centre and low ones toward the border."""


def town_style(name: str) -> TownStyle:
    """The named style ``name`` of :data:`TOWN_STYLES`, or one :class:`InputError` line naming the choices."""
    if not isinstance(name, str) or name not in TOWN_STYLES:
        raise InputError(f"unknown town style {name!r}; expected one of: {', '.join(TOWN_STYLES)}")
    return TOWN_STYLES[name]


def style_name(style: TownStyle) -> str:
    """The name under which :data:`TOWN_STYLES` holds ``style`` (equal fields), else ``"custom"``."""
    return next((nm for nm, st in TOWN_STYLES.items() if st == style), "custom")


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
