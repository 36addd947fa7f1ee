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

Styles (:data:`TOWN_STYLES`, ``simbed make-town --style``; :func:`generate_town` takes a name or a
:class:`TownStyle`):

* ``grid``: the default above (:data:`DEFAULT_STYLE`), the shipped towns.
* ``suburb``: a winding suburb (``layout="organic"``). Junctions are Poisson-disc points at least 45 m apart,
  joined by their Delaunay triangulation less the edges longer than 120 m, those that leave a node at
  less than 60° to another road (the route's corner fillets would leave the asphalt) and those within
  14 m of a road they share no node with; nodes left with one road go, the largest connected part stays,
  and roads are removed as on the grid. Every road is then bent (:func:`roads.bend_roads`): cut into
  20–35 m pieces joined at bend nodes displaced sideways along an arc or an S of up to 15 % of its length;
  a bend that would break those angle or clearance rules is tried on the other side, then halved, else
  dropped. Houses 4–10 m high on smaller, deeper-set lots, low walls more often, more and bigger trees,
  fewer parked cars.
* ``mixed``: the grid with about a third of its roads bent as above, building heights up to 40 m in the
  centre shrinking toward 11 m at the border (``building_height_outskirts_frac``).

Bend nodes follow the junctions in ``nodes`` and carry junction discs like them; frontages, poles, trees
and parking of a road piece reach to ``bend_margin_m`` from a bend node. The sidecar names the style
(``style: suburb``; absent for ``grid``, the key that older sidecars lack).

Geom names: ``terrain``, ``road_{e}``, ``junction_{n}``, ``bldg_{b}_a``/``bldg_{b}_b``, ``wall_{w}``,
``pole_{p}``, ``tree_{t}_trunk``/``tree_{t}_crown``, ``parked_v{k}_{i}_body``/``parked_v{k}_{i}_cabin``.

The package's modules, each importing only those before it: ``style`` (:class:`TownStyle`, the presets),
``info`` (:class:`TownInfo`, the sidecar, the parked-car variants), ``geometry`` (oriented rectangles, the
scene's boxes, poles, trees and parked cars), ``roads`` (road graph, terrain, road surfaces), ``planner``
(buildings, walls, poles, trees and parked cars beside the roads), ``mjcf`` (the XML, the height field and
the ground texture); :func:`generate_town` here puts them together.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from rangemcl.common.outdir import check_output_files
from rangemcl.errors import InputError
from simbed.scenes.towngen.geometry import rect_segment_distance
from simbed.scenes.towngen.info import (
    Terrain,
    TownInfo,
    load_town_info,
    parked_variant_bodies,
    use_parked_variant,
    write_yaml,
)
from simbed.scenes.towngen.mjcf import paint_ground, write_png, write_terrain, write_xml
from simbed.scenes.towngen.planner import Planner
from simbed.scenes.towngen.roads import road_graph, road_surfaces, spawn_pose, town_terrain
from simbed.scenes.towngen.style import (
    DEFAULT_STYLE,
    SHIPPED_TOWNS,
    TOWN_STYLES,
    Range,
    TownPreset,
    TownStyle,
    style_name,
    town_style,
)

__all__ = [
    "CAR_XML",
    "DEFAULT_STYLE",
    "SHIPPED_TOWNS",
    "TOWN_STYLES",
    "Range",
    "Terrain",
    "TownInfo",
    "TownPreset",
    "TownStyle",
    "generate_preset",
    "generate_shipped",
    "generate_town",
    "load_town_info",
    "parked_variant_bodies",
    "rect_segment_distance",
    "style_name",
    "town_files",
    "town_style",
    "use_parked_variant",
]

CAR_XML = Path(__file__).resolve().parents[3] / "scenes" / "car.xml"


def generate_town(
    seed: int,
    size_m: float,
    out_xml: Path,
    *,
    n_parked_variants: int = 2,
    name: str | None = None,
    style: TownStyle | str = DEFAULT_STYLE,
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
        style: the generator's sizes, offsets, spacings and random ranges (:class:`TownStyle`), or the name
            of one of :data:`TOWN_STYLES` (``grid``, ``suburb``, ``mixed``); the XML's header comment names
            the style, or the fields that differ from the default, and the sidecar its name (``custom``
            for a style that is none of them).
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
    if isinstance(style, str):
        style = town_style(style)
    if not isinstance(style, TownStyle):
        raise InputError(f"town style must be a TownStyle or a style name, got {type(style).__name__}")
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
    nodes, edges, n_junctions = road_graph(rng, size_m, style)
    terrain, hnode, natural = town_terrain(rng, size_m, nodes, edges, style, f"{out_xml.stem}_terrain.bin")
    road_boxes, junctions = road_surfaces(nodes, edges, hnode, style)
    spawn = spawn_pose(rng, nodes, edges, style)

    # buildings, walls, poles, trees and parked cars
    plan = Planner(rng, size_m, nodes, edges, terrain.height, style, n_junctions)
    plan.frontages()
    plan.poles_and_street_trees()
    plan.block_trees()
    spots = plan.parking_spots()
    variants = [plan.parked_variant(k, spots) for k in range(n_parked_variants)]

    lengths = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
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
        style=style_name(style),
    )
    out_xml.parent.mkdir(parents=True, exist_ok=True)
    write_terrain(out_xml.parent / terrain.file, terrain.data)
    texture = f"{out_xml.stem}_ground.img"  # a PNG; not named *.png, which the repository's .gitignore drops
    px_m = style.texture_px_m if size_m <= style.fine_max_size_m else style.coarse_texture_px_m
    write_png(out_xml.parent / texture, paint_ground(size_m, px_m, nodes, edges, natural, style))
    write_xml(out_xml, name, seed, size_m, style, terrain, texture, road_boxes, junctions, plan, variants)
    write_yaml(out_xml.with_suffix(".yaml"), info)
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
