"""Moving actors: cars, cyclists and pedestrians that travel the town's roads during a drive.

Actors are MuJoCo mocap bodies (kinematic: they follow their paths exactly and are not pushed by the ego
car). They do not collide with anything (so they can never shove the ego car off its route), but the LiDAR
sees them; as they have no physical effect, their poses are set when the LiDAR is about to cast (each
chunk of a sweep), not at every physics step. Each follows a random walk over the road graph at its own
speed: cars in the right-hand lane,
cyclists at the road edge, pedestrians on the sidewalk.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from simbed.scenes.routes import RoadGraph, lane_polyline, random_walk

# kind: (box half-sizes x, y, z in metres, speed range m/s, lateral place)
ACTOR_KINDS = {
    "car": {"half": (2.25, 0.9, 0.75), "speed": (5.0, 9.0), "rgba": (0.8, 0.2, 0.2, 1)},
    "cyclist": {"half": (0.9, 0.3, 0.85), "speed": (3.5, 6.0), "rgba": (0.2, 0.7, 0.2, 1)},
    "pedestrian": {"half": (0.25, 0.25, 0.88), "speed": (1.0, 1.6), "rgba": (0.2, 0.3, 0.9, 1)},
}
KIND_MIX = ("car", "car", "cyclist", "pedestrian")  # actor k has kind KIND_MIX[k % 4]


def lateral_offset(kind: str, lane_width_m: float, road_width_m: float) -> float:
    """Metres to the right of the road centre line where an actor of this kind travels."""
    if kind == "car":
        return lane_width_m / 2
    if kind == "cyclist":
        return road_width_m / 2 - 0.7
    return road_width_m / 2 + 1.5  # pedestrians on the sidewalk


@dataclass
class Actor:
    name: str
    kind: str
    path: np.ndarray  # (P, 2) closed polyline
    cumlen: np.ndarray  # (P,) arc length at each point
    speed_mps: float
    s0_m: float  # arc length at t = 0
    mocap_id: int = -1
    body_id: int = -1
    alternatives: list = field(default_factory=list)  # other (path, cumlen) to use if this one is blocked

    def pose_at(self, t: float) -> tuple[np.ndarray, float]:
        """(x, y) and heading of the actor at time ``t`` (seconds), looping along its path."""
        s = (self.s0_m + self.speed_mps * t) % self.cumlen[-1]
        k = min(max(int(np.searchsorted(self.cumlen, s, side="right")) - 1, 0), len(self.path) - 2)
        seg = self.path[k + 1] - self.path[k]
        frac = (s - self.cumlen[k]) / max(self.cumlen[k + 1] - self.cumlen[k], 1e-9)
        return self.path[k] + frac * seg, float(np.arctan2(seg[1], seg[0]))


def plan_actors(
    n: int,
    graph: RoadGraph,
    lane_width_m: float,
    road_width_m: float,
    rng: np.random.Generator,
    *,
    keep_clear_xy: tuple[float, float] | None = None,
    keep_clear_m: float = 15.0,
    walk_edges: int = 12,
) -> list[Actor]:
    """``n`` actors with random looping paths; none starts within ``keep_clear_m`` of ``keep_clear_xy``."""
    actors = []
    for k in range(n):
        kind = KIND_MIX[k % len(KIND_MIX)]
        walk = random_walk(graph, rng, walk_edges)
        back = graph.shortest_path(walk[-1], walk[0])  # close the loop so it can repeat forever
        walk = walk + back[1:]
        path = lane_polyline(
            graph, walk, lateral_offset(kind, lane_width_m, road_width_m), corner_radius_m=6.0
        )
        cumlen = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        speed = float(rng.uniform(*ACTOR_KINDS[kind]["speed"]))
        actor = Actor(f"actor_{k}_{kind}", kind, path, cumlen, speed, 0.0)
        for _ in range(50):
            actor.s0_m = float(rng.uniform(0, cumlen[-1]))
            xy, _ = actor.pose_at(0.0)
            if keep_clear_xy is None or np.hypot(*(xy - np.asarray(keep_clear_xy))) > keep_clear_m:
                break
        actors.append(actor)
    return actors


def add_actor_bodies(spec: mujoco.MjSpec, actors: list[Actor]) -> None:
    """Add one mocap body per actor to a model spec (boxes for cars and cyclists, a capsule for people)."""
    for a in actors:
        body = spec.worldbody.add_body(name=a.name, mocap=True, pos=[0, 0, -100.0])
        hx, hy, hz = ACTOR_KINDS[a.kind]["half"]
        rgba = ACTOR_KINDS[a.kind]["rgba"]
        common = {"contype": 0, "conaffinity": 0, "group": 3, "rgba": rgba}  # group 3: actors
        if a.kind == "pedestrian":
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[hx, hz - hx, 0], **common)
        elif a.kind == "car":
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz * 0.55], pos=[0, 0, -hz * 0.45], **common
            )
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[hx * 0.55, hy * 0.95, hz * 0.45],
                pos=[-0.2, 0, hz * 0.55],
                **common,
            )
        else:
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, 0.05, hz * 0.5], pos=[0, 0, -hz * 0.5], **common
            )
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.22, 0.35, 0], pos=[0, 0, hz * 0.45], **common
            )


def bind_actors(model: mujoco.MjModel, actors: list[Actor]) -> None:
    """Look up each actor's body and mocap index in a compiled model."""
    for a in actors:
        a.body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, a.name)
        a.mocap_id = int(model.body_mocapid[a.body_id])


def place_actors(data: mujoco.MjData, actors: list[Actor], t: float, ground_height) -> None:
    """Set every actor's mocap pose for time ``t`` (standing on the ground, heading along its path)."""
    if not actors:
        return
    xy, yaw = zip(*(a.pose_at(t) for a in actors), strict=True)
    xy = np.asarray(xy)  # (A, 2)
    yaw = np.asarray(yaw)
    z = np.asarray(ground_height(xy[:, 0], xy[:, 1]), dtype=float)
    for a, (x, y), zi, h in zip(actors, xy, z, yaw, strict=True):
        data.mocap_pos[a.mocap_id] = (x, y, zi + ACTOR_KINDS[a.kind]["half"][2])
        data.mocap_quat[a.mocap_id] = (np.cos(h / 2), 0.0, 0.0, np.sin(h / 2))


# --- actors in any scene ------------------------------------------------------------------------------


def _loop_path(points: np.ndarray, loop: bool) -> tuple[np.ndarray, np.ndarray]:
    """A closed polyline for :meth:`Actor.pose_at` (which loops): the path closed back to its start, or
    there and back again; and its arc lengths."""
    pts = np.asarray(points, np.float64)
    path = np.vstack([pts, pts[:1]]) if loop else np.vstack([pts, pts[-2::-1]])
    cumlen = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    return path, cumlen


def read_actor_paths(path) -> list[Actor]:
    """Actors from a YAML file (``--actor-paths``)::

        actors:
          - kind: car              # car, cyclist or pedestrian
            speed: 6.0             # m/s (default: the middle of the kind's range)
            loop: true             # false: there and back again (default true)
            start_m: 0.0           # where along the path it is when the drive starts (default 0)
            waypoints: [[0, 0], [40, 0], [40, 30]]

    A malformed file or entry is an ``InputError`` naming the file and the actor."""
    from pathlib import Path

    from rangemcl.common.yamlio import parse_yaml, read_text
    from rangemcl.errors import InputError

    path = Path(path)
    doc = parse_yaml(read_text(path, "actor paths file"), str(path))
    if not isinstance(doc, dict) or not isinstance(doc.get("actors"), list) or not doc["actors"]:
        raise InputError(f"{path}: expected a mapping with a non-empty list 'actors'")
    unknown = set(doc) - {"actors"}
    if unknown:
        raise InputError(f"{path}: unknown key {sorted(unknown)[0]!r} (expected 'actors')")
    actors = []
    for k, entry in enumerate(doc["actors"]):
        where = f"{path}: actors[{k}]"
        if not isinstance(entry, dict):
            raise InputError(f"{where}: expected a mapping with kind, waypoints (speed, loop, start_m)")
        extra = set(entry) - {"kind", "speed", "loop", "start_m", "waypoints"}
        if extra:
            raise InputError(f"{where}: unknown key {sorted(extra)[0]!r}")
        kind = entry.get("kind")
        if kind not in ACTOR_KINDS:
            raise InputError(f"{where}: kind {kind!r}: expected one of {', '.join(ACTOR_KINDS)}")
        lo, hi = ACTOR_KINDS[kind]["speed"]
        speed = entry.get("speed", (lo + hi) / 2)
        if isinstance(speed, bool) or not isinstance(speed, int | float) or not 0 < speed <= 30:
            raise InputError(f"{where}: speed {speed!r}: expected a number of m/s above 0, at most 30")
        loop = entry.get("loop", True)
        if not isinstance(loop, bool):
            raise InputError(f"{where}: loop {loop!r}: expected true or false")
        try:
            pts = np.asarray(entry.get("waypoints"), np.float64)
        except (TypeError, ValueError):
            pts = np.zeros((0,))
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2 or not np.isfinite(pts).all():
            raise InputError(f"{where}: waypoints: expected at least two [x, y] pairs of finite numbers")
        if (np.linalg.norm(np.diff(pts, axis=0), axis=1) < 0.01).any():
            raise InputError(f"{where}: waypoints: two consecutive waypoints coincide")
        closed, cumlen = _loop_path(pts, loop)
        start = entry.get("start_m", 0.0)
        if isinstance(start, bool) or not isinstance(start, int | float) or not np.isfinite(start):
            raise InputError(f"{where}: start_m {start!r}: expected a number of metres")
        actors.append(Actor(f"actor_{k}_{kind}", kind, closed, cumlen, float(speed), float(start)))
    return actors


# metres to the right of the ego lane, and whether against its direction, for actors along a route
ROUTE_PLACES = {"car": (-3.5, True), "cyclist": (2.2, False), "pedestrian": (4.0, False)}


def offset_polyline(points: np.ndarray, right_m: float) -> np.ndarray:
    """A polyline moved ``right_m`` to the right of its direction of travel (left when negative)."""
    p = np.asarray(points, np.float64)
    t = np.gradient(p, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    return p + right_m * np.stack([t[:, 1], -t[:, 0]], axis=1)


def actors_along_route(
    n: int,
    lane: np.ndarray,
    loop: bool,
    rng: np.random.Generator,
    *,
    keep_clear_xy: tuple[float, float] | None = None,
    keep_clear_m: float = 15.0,
) -> list[Actor]:
    """``n`` actors for a scene without a road network, along the ego route's own lane: cars in the
    opposite lane (3.5 m to the left, against the route's direction), cyclists 2.2 m to the right and
    pedestrians 4 m to the right, in its direction (every other pedestrian against it). Each keeps its
    mirror place as ``alternatives`` in case the first turns out blocked (:func:`check_actor_paths`)."""
    actors = []
    for k in range(n):
        kind = KIND_MIX[k % len(KIND_MIX)]
        right, against = ROUTE_PLACES[kind]
        if kind == "pedestrian" and (k // len(KIND_MIX)) % 2:
            against = not against
        places = []
        for side in (right, -right):
            pts = offset_polyline(lane, side)
            places.append(_loop_path(pts[::-1] if against else pts, loop))
        speed = float(rng.uniform(*ACTOR_KINDS[kind]["speed"]))
        (path, cumlen), alternative = places[0], places[1]
        actor = Actor(f"actor_{k}_{kind}", kind, path, cumlen, speed, 0.0, alternatives=[alternative])
        for _ in range(50):
            actor.s0_m = float(rng.uniform(0, cumlen[-1]))
            xy, _ = actor.pose_at(0.0)
            if keep_clear_xy is None or np.hypot(*(xy - np.asarray(keep_clear_xy))) > keep_clear_m:
                break
        actors.append(actor)
    return actors


def check_actor_paths(actors: list[Actor], ground, caster, static_handle: int, source: str) -> list[str]:
    """Check each actor's path against the scene (ground under it, no static geometry in its box); an
    actor with ``alternatives`` takes the first that passes. Returns one line per actor that could not be
    placed (those are removed from ``actors``); for actors without alternatives (given in a file) a
    problem is an ``InputError`` naming ``source`` and the actor."""
    from rangemcl.errors import InputError
    from simbed.scenes.lanes import blocked, box_rays, headings

    dropped = []
    for a in list(actors):
        hx, hy, hz = ACTOR_KINDS[a.kind]["half"]
        rays = box_rays((-hx, hx), hy, (0.3, 2 * hz), step_m=0.25)
        problem = None
        for path, cumlen in [(a.path, a.cumlen), *a.alternatives]:
            s = np.arange(0.0, cumlen[-1], 1.0)
            idx = np.clip(np.searchsorted(cumlen, s, side="right") - 1, 0, len(path) - 2)
            frac = (s - cumlen[idx]) / np.maximum(cumlen[idx + 1] - cumlen[idx], 1e-9)
            pts = path[idx] + frac[:, None] * (path[idx + 1] - path[idx])
            z = np.asarray(ground(pts[:, 0], pts[:, 1]), np.float64)
            if not np.isfinite(z).all():
                i = int(np.flatnonzero(~np.isfinite(z))[0])
                problem = f"no ground under its path at ({pts[i, 0]:.1f}, {pts[i, 1]:.1f})"
                continue
            steps = np.flatnonzero(np.abs(np.diff(z)) > 0.5)
            if len(steps):
                i = int(steps[0]) + 1
                problem = (
                    f"the ground under its path steps by {z[i] - z[i - 1]:+.1f} m at "
                    f"({pts[i, 0]:.1f}, {pts[i, 1]:.1f})"
                )
                continue
            stuck, where = blocked(pts, headings(pts, False), z, caster, static_handle, rays)
            if stuck.any():
                i = int(np.flatnonzero(stuck)[0])
                problem = f"static geometry at ({where[i, 0]:.1f}, {where[i, 1]:.1f}) in its way"
                continue
            a.path, a.cumlen, problem = path, cumlen, None
            break
        if problem is None:
            continue
        if not a.alternatives:
            raise InputError(f"{source}: {a.name} ({a.kind}): {problem}")
        dropped.append(f"{a.name} ({a.kind}) left out: {problem} on both sides of the route")
        actors.remove(a)
    return dropped
