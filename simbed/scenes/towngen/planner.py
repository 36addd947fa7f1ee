"""Buildings, walls, poles, trees and parked cars beside the roads, without overlaps (:class:`Planner`)."""

from __future__ import annotations

import math

import numpy as np

from rangemcl.se2 import wrap_angle
from simbed.scenes.towngen.geometry import (
    Box,
    Occupancy,
    ParkedCar,
    Pole,
    Tree,
    rect_corners,
    rect_segment_distance,
)
from simbed.scenes.towngen.style import Range, TownStyle

_N_BUILDING_MATERIALS = 5  # building0 .. building4 in the XML's assets


class Planner:
    """Places buildings, walls, poles, trees and parked cars beside the roads without overlaps."""

    def __init__(self, rng, size_m, nodes, edges, ground, style: TownStyle, n_junctions: int | None = None):
        """``nodes[n_junctions:]`` are bend nodes (:func:`~simbed.scenes.towngen.roads.bend_roads`): a road
        piece's frontage, poles, trees and parking reach to ``style.bend_margin_m`` from them."""
        self.rng = rng
        self.style = style
        self.size_m = size_m
        self.nodes = nodes
        self.edges = edges
        self.a = nodes[edges[:, 0]]
        self.b = nodes[edges[:, 1]]
        self.is_bend = np.arange(len(nodes)) >= (len(nodes) if n_junctions is None else n_junctions)
        self.ground = ground
        self.occ = Occupancy()
        self.boxes: list[Box] = []
        self.poles: list[Pole] = []
        self.trees: list[Tree] = []
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
        return bool(np.all(np.abs(rect_corners(center, yaw, half)) <= lim))

    def _frame(self, e: int):
        a, b = self.a[e], self.b[e]
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        n = np.array([-u[1], u[0]])
        return a, u, n, length, math.atan2(u[1], u[0])

    def _ends(self, e: int, junction_m: float) -> tuple[float, float]:
        """Margins from edge ``e``'s start and end node: ``junction_m`` at a junction, the bend margin at a
        bend node."""
        i, j = self.edges[e]
        bend = self.style.bend_margin_m
        return (bend if self.is_bend[i] else junction_m), (bend if self.is_bend[j] else junction_m)

    def _base_top(self, center, yaw, half):
        corners = rect_corners(center, yaw, half)
        pts = np.vstack([corners, center])
        z = self.ground(pts[:, 0], pts[:, 1])
        return float(z.min()), float(z.max())

    # -- buildings and walls along the frontages
    def frontages(self) -> None:
        rng, st = self.rng, self.style
        jr = st.junction_radius_m
        for e in range(len(self.edges)):
            a, u, n, length, yaw = self._frame(e)
            m0, m1 = self._ends(e, jr)
            for side in (1.0, -1.0):
                s = m0 + rng.uniform(*st.lot_start_m)
                while s < length - m1 - st.lot_min_width_m:
                    width = rng.uniform(*st.lot_width_m)
                    width = min(width, length - m1 - s)
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
        if st.building_height_outskirts_frac != 1.0:  # lower toward the border (1: the shipped towns' draws)
            r = min(1.0, float(np.linalg.norm(a + u * (s + width / 2))) / (self.size_m / 2))
            h_hi = h_lo + (h_hi - h_lo) * (1.0 - (1.0 - st.building_height_outskirts_frac) * r)
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
                        Box(
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
                Box(
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
            m0, m1 = self._ends(e, jr)
            s = m0 + pole_lo + rng.uniform(0.0, pole_hi - pole_lo)
            side = rng.choice([-1.0, 1.0])
            while s < length - m1 - pole_lo:
                xy = a + u * s + side * n * st.pole_offset_m
                r = st.pole_radius_m
                clearance = st.pole_offset_m - st.pole_road_slack_m
                if self._placeable(xy, yaw, (r, r), clearance, st.pole_gap_m, skip=None):
                    self.occ.add(xy, yaw, (r, r))
                    self.poles.append(
                        Pole(
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
                s = m0 + tree_lo + rng.uniform(0.0, tree_hi - tree_lo)
                while s < length - m1 - tree_lo:
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
            Tree(
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
            m0, m1 = self._ends(e, st.junction_radius_m + st.parking_end_clearance_m)
            if self.is_bend[self.edges[e]].any():  # the row centred between the margins
                count = int((length - m0 - m1) // pitch)
                s0 = m0 + (length - m0 - m1 - (count - 1) * pitch) / 2
            else:  # the arithmetic that wrote the shipped towns
                count = int((length - 2 * (st.junction_radius_m + st.parking_end_clearance_m)) // pitch)
                s0 = (length - (count - 1) * pitch) / 2
            if count <= 0:
                continue
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

    def parked_variant(self, k: int, spots) -> list[ParkedCar]:
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
                ParkedCar(
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
