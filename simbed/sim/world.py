"""A MuJoCo scene as the LiDAR sees it: the model, its moving actors, and its triangles in the shared
Warp ray caster (static geometry in one BVH, each moving body as a movable mesh, the ego car left out)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import mujoco
import numpy as np

from rangemcl.errors import InputError
from rangemcl.raycast import RayCaster
from simbed.scenes.routes import RoadGraph
from simbed.scenes.scene_ground import SceneGround
from simbed.scenes.towngen import TownInfo, load_town_info
from simbed.sim.actors import Actor, add_actor_bodies, bind_actors, place_actors, plan_actors
from simbed.sim.geometry import body_pose, split_static_dynamic
from simbed.sim.materials import SceneMaterials
from simbed.sim.vehicle import CarHandles

# bodies that belong to one variant of a scene: parked_v{k}_* (generated towns' parked cars) and
# variant_{k}_* (anything: moved furniture, a construction fence, a door left open)
VARIANT = re.compile(r"^(?:parked_v|variant_)(\d+)_")
CAR_XML = Path(__file__).resolve().parents[2] / "scenes" / "car.xml"
EGO_PREFIX = "ego_"  # the names of the car simbed adds to a scene that has none
COLLISION_ONLY_GROUP = 4  # geoms in this MuJoCo group are felt by the car but not seen by the LiDAR


def scenes_dir() -> Path:
    """The folder of shipped scenes (``$SIMBED_SCENES`` overrides)."""
    return Path(os.environ.get("SIMBED_SCENES", Path(__file__).resolve().parents[2] / "scenes"))


def resolve_scene(scene: str | os.PathLike) -> Path:
    """A scene name (``town_small``) or a path to an MJCF file."""
    p = Path(scene)
    if p.suffix.lower() != ".xml":
        p = scenes_dir() / f"{scene}.xml"
    if not p.is_file():
        shipped = sorted(q.stem for q in scenes_dir().glob("town*.xml"))
        raise InputError(f"{p}: no such scene file (shipped scenes: {', '.join(shipped) or 'none'})")
    return p


def load_model_spec(path: Path) -> mujoco.MjSpec:
    try:
        return mujoco.MjSpec.from_file(str(path))
    except Exception as err:  # MuJoCo raises ValueError with a multi-line message
        # the message spans lines ("XML parse error 6:" then the detail): keep all of it on one line
        detail = " ".join(part.strip() for part in str(err).strip().splitlines() if part.strip())
        raise InputError(f"{path}: malformed MJCF scene: {detail or type(err).__name__}") from None


class World:
    """A loaded scene, ready to step and to be ray-cast.

    Args:
        scene: scene name or MJCF path. A town's sidecar YAML (same stem) gives roads and terrain.
        variant: which variant of the scene is present: bodies named ``parked_v{k}_*`` (generated towns'
            parked cars) or ``variant_{k}_*`` (anything) of other k are removed, with their child bodies,
            from the LiDAR's world and from collisions, and made invisible; variant 0 of a scene that has
            no bodies of variant 0 is its world without any variant bodies.
        n_actors: moving actors on the town's roads (needs a town with roads).
        rng: the run's seeded generator (actor paths).
        device, threads: for the ray caster.
        add_car: add simbed's car (``scenes/car.xml``, names prefixed ``ego_``) if the scene has none.
        actors: actors planned by the caller (:func:`simbed.sim.actors.read_actor_paths`,
            :func:`simbed.sim.actors.actors_along_route`) instead of ``n_actors`` on the town's roads.
    """

    def __init__(
        self,
        scene: str | os.PathLike,
        *,
        variant: int = 0,
        n_actors: int = 0,
        rng: np.random.Generator | None = None,
        device: str = "cpu",
        threads: int | None = None,
        segments: int = 24,
        add_car: bool = False,
        actors: list[Actor] | None = None,
    ):
        rng = rng or np.random.default_rng(0)
        self.path = resolve_scene(scene)
        sidecar = self.path.with_suffix(".yaml")
        self.town: TownInfo | None = load_town_info(sidecar) if sidecar.is_file() else None
        spec = load_model_spec(self.path)
        self.scene_ground: SceneGround | None = None  # set once the static world is in the caster
        self.car_prefix = ""
        if add_car and spec.body("car") is None:
            add_car_body(spec)
            self.car_prefix = EGO_PREFIX
        self.actors: list[Actor] = []
        if actors is not None:  # planned by the caller (a paths file, or along a route)
            self.actors = list(actors)
            add_actor_bodies(spec, self.actors)
        elif n_actors and self.town is None:
            raise InputError(
                f"{self.path}: actors on their own need a town with roads ({sidecar} is missing); "
                "give them paths (--actor-paths) or a waypoint route to travel beside"
            )
        elif n_actors:
            t = self.town
            self.actors = plan_actors(
                n_actors, self.graph, t.lane_width_m, t.road_width_m, rng, keep_clear_xy=t.spawn[:2]
            )
            add_actor_bodies(spec, self.actors)
        try:
            self.model = spec.compile()
        except Exception as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise InputError(f"{self.path}: the scene does not compile: {first}") from None
        self.data = mujoco.MjData(self.model)
        bind_actors(self.model, self.actors)
        self.variant = variant
        self.hidden_geoms = self._hide_other_variants(variant)
        car_name = self.car_prefix + "car"
        has_car = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, car_name) >= 0
        self.car = CarHandles.find(self.model, self.data, self.car_prefix) if has_car else None
        self.time = 0.0
        place_actors(self.data, self.actors, 0.0, self.ground_height)
        mujoco.mj_forward(self.model, self.data)

        # what the LiDAR does not see: other variants' bodies and collision-only geoms (an imported
        # world's height field, which stands in for its mesh under the car's wheels)
        hidden = set(self.hidden_geoms.tolist())
        hidden |= set(np.flatnonzero(self.model.geom_group == COLLISION_ONLY_GROUP).tolist())
        parts = split_static_dynamic(
            self.model,
            self.data,
            exclude_bodies=[self.car.body] if self.car else [],
            include_geom=lambda g: g not in hidden,
            segments=segments,
        )
        self.caster = RayCaster(device=device, threads=threads)
        v, f, static_geoms = parts.static
        self.static_handle = self.caster.add_mesh(v, f, name="static")
        self.static_triangles = (v, f)
        self.dynamic_handles: dict[int, int] = {}
        self._face_geoms = {self.static_handle: static_geoms}  # handle -> geom id of each face given
        for bm in parts.dynamic:
            h = self.caster.add_mesh(
                bm.vertices, bm.faces, name=bm.name, movable=True, pose=body_pose(self.data, bm.body_id)
            )
            self.dynamic_handles[bm.body_id] = h
            self._face_geoms[h] = bm.geom_ids_per_face
        self._materials: SceneMaterials | None = None
        actor_bodies = {a.body_id for a in self.actors}
        self.actor_handles = [h for b, h in self.dynamic_handles.items() if b in actor_bodies]
        # scenes without a terrain sidecar: the ground is found in their own static geometry
        self.scene_ground = (
            SceneGround.from_triangles(self.caster, self.static_handle, v) if self.town is None else None
        )

    @property
    def materials(self) -> SceneMaterials:
        """What every surface is made of (:mod:`simbed.sim.materials`), built on first use (the realistic
        sensor needs it; the ideal one does not)."""
        if self._materials is None:
            mats = SceneMaterials(self.model, self.data, self.path, self.town)
            infos = self.caster.meshes
            for handle, geoms in self._face_geoms.items():
                mats.add_mesh(handle, geoms, infos[handle].face_map)
            self._materials = mats
        return self._materials

    @property
    def graph(self) -> RoadGraph:
        if self.town is None:
            raise InputError(
                f"{self.path}: this scene has no road network ({self.path.with_suffix('.yaml')})"
            )
        return RoadGraph(np.asarray(self.town.nodes, float), np.asarray(self.town.edges, int))

    def ground_height(self, x, y):
        """Ground height under (x, y): from the town's terrain, or for other scenes the lowest static
        surface a car can stand on (:mod:`simbed.scenes.scene_ground`; 0 where there is none)."""
        if self.town is not None:
            return self.town.ground_height(x, y)
        if self.scene_ground is None:  # during construction (actors are placed before the caster exists)
            return np.zeros_like(np.asarray(x, dtype=float))
        h = self.scene_ground.height(x, y)
        return np.where(np.isfinite(h), h, 0.0)

    def _hide_other_variants(self, variant: int) -> np.ndarray:
        """Remove the bodies of other variants (``parked_v{k}_*``, ``variant_{k}_*``, with their child
        bodies): no collisions, invisible, not seen by the LiDAR; returns their geom ids."""
        m = self.model
        variants = set()
        hidden = []
        for b in range(m.nbody):
            match = VARIANT.match(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or "")
            if not match:
                continue
            variants.add(int(match.group(1)))
            if int(match.group(1)) != variant:
                hidden.extend(np.flatnonzero(_in_subtree(m, b)[m.geom_bodyid]).tolist())
        if variants and variant not in variants and variant != 0:  # 0: the world without its variants
            raise InputError(f"{self.path}: no variant {variant} (it has {sorted(variants)})")
        if not variants and variant != 0:
            raise InputError(
                f"{self.path}: no variant {variant}: the scene has no bodies named parked_v{{k}}_* or "
                "variant_{k}_*"
            )
        hidden = np.asarray(hidden, dtype=int)
        if len(hidden):
            m.geom_contype[hidden] = 0
            m.geom_conaffinity[hidden] = 0
            m.geom_rgba[hidden, 3] = 0.0
        return hidden

    def sync_caster(self) -> None:
        """Move actors to where they are now, and each dynamic mesh to its body's pose (before casting)."""
        place_actors(self.data, self.actors, self.time, self.ground_height)
        mujoco.mj_kinematics(self.model, self.data)
        if self.dynamic_handles:
            bodies = list(self.dynamic_handles)
            self.caster.set_poses(self.dynamic_handles.values(), [body_pose(self.data, b) for b in bodies])

    def step(self, n: int = 1) -> None:
        """Advance physics ``n`` steps (actors have no physical effect: they move in :meth:`sync_caster`)."""
        for _ in range(n):
            mujoco.mj_step(self.model, self.data)
            self.time += self.model.opt.timestep


def _in_subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    """(nbody,) bool: the body ``root`` and its descendants."""
    inside = np.zeros(model.nbody, bool)
    inside[root] = True
    for b in range(root + 1, model.nbody):  # parents come before their children
        inside[b] = inside[model.body_parentid[b]]
    return inside


def add_car_body(spec: mujoco.MjSpec) -> None:
    """Attach the car of ``scenes/car.xml`` to a scene that has none, at the world origin (the drive
    places it at its route's start), its names prefixed with ``ego_``."""
    car = mujoco.MjSpec.from_file(str(CAR_XML))
    spec.worldbody.add_frame().attach_body(car.body("car"), EGO_PREFIX, "")
