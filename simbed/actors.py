"""Moving actors: cars, cyclists and pedestrians that travel the town's roads during a drive.

Actors are MuJoCo mocap bodies (kinematic: they follow their paths exactly and are not pushed by the ego
car). They do not collide with anything (so they can never shove the ego car off its route), but the LiDAR
sees them; as they have no physical effect, their poses are set when the LiDAR is about to cast (each
chunk of a sweep), not at every physics step. Each follows a random walk over the road graph at its own
speed: cars in the right-hand lane,
cyclists at the road edge, pedestrians on the sidewalk.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from simbed.routes import RoadGraph, lane_polyline, random_walk

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
