"""One drive: the car follows its route under MuJoCo physics while the LiDAR sweeps and odometry integrates.

:meth:`Drive.next_frame` advances the world by one LiDAR period (physics steps interleaved with the
sweep's chunks) and returns what a real car would record for that frame, with ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rangemcl.errors import InputError
from rangemcl.sensors import LidarSpec
from simbed.scenes.routes import Route
from simbed.sim import DEFAULT_SENSOR_MODEL
from simbed.sim.lidar import SimLidar, Sweep, sensor_setup
from simbed.sim.vehicle import OdometryNoise, RouteFollower, WheelGyroOdometry, wheel_torque
from simbed.sim.world import World


@dataclass
class Frame:
    index: int
    sweep: Sweep
    T_world_sensor: np.ndarray  # (4, 4) ground truth at the sweep's end
    T_odom_sensor: np.ndarray  # (4, 4) the car's own dead-reckoned estimate
    imu_roll_pitch: tuple[float, float]
    time_s: float
    speed_mps: float
    route_done: bool
    stuck: bool = False  # the car made no progress along its route for 10 s


# What of a drive changes as it runs, by part, beside the physics and the random generator: a checkpoint
# holds these, and everything else is rebuilt the same from the drive's arguments (scene, route, sensor,
# seed...). The recording's resume test fails when one is missing here (its bytes differ).
_STATE_ATTRS = {
    "drive": ("frame_index", "t0", "manual"),
    "world": ("time",),
    "controller": ("index", "integral", "done", "stuck", "_time", "_progress_mark"),
    "odometry": ("scale", "bias", "x", "y", "yaw", "_wheels"),
    "lidar": ("_last_axis",),
}


PHYSICS_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # all that mj_step's result depends on


def _encode(value, key: str, arrays: dict):
    """A part's value as JSON (numbers, None, lists for tuples); an array goes into ``arrays``."""
    if isinstance(value, np.ndarray):
        arrays[key] = value
        return {"array": key}
    if isinstance(value, tuple):
        return {"tuple": [_encode(v, f"{key}.{i}", arrays) for i, v in enumerate(value)]}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if value is None:
        return None
    raise TypeError(f"{key}: cannot checkpoint a {type(value).__name__}")


def _decode(value, arrays: dict):
    if isinstance(value, dict) and "array" in value:
        return np.array(arrays[value["array"]])
    if isinstance(value, dict) and "tuple" in value:
        return tuple(_decode(v, arrays) for v in value["tuple"])
    return value


class Drive:
    """A car driving a route in a world, recording LiDAR sweeps.

    Args:
        world: the loaded scene (with its car).
        route: the lane polyline to follow.
        spec: the LiDAR.
        rng: the run's seeded generator (noise of LiDAR and odometry).
        skew: per-column sensor poses (motion skews the scan), on by default.
        chunks_per_sweep: how often, within a sweep, the world is re-posed for casting.
        settle_s: physics time to let the car settle on its wheels before the first sweep.
        sensor_model: ``ideal`` or ``realistic`` (:mod:`simbed.sim.lidar`).
        weather: the realistic sensor's weather (``clear``, ``fog:V``, ``rain:R``: :mod:`simbed.sim.weather`).
        return_mode: the realistic sensor's ``strongest``, ``last`` or ``dual`` echoes.
    """

    def __init__(
        self,
        world: World,
        route: Route,
        spec: LidarSpec,
        rng: np.random.Generator,
        *,
        skew: bool = True,
        chunks_per_sweep: int = 10,
        cruise_mps: float = 8.0,
        settle_s: float = 1.0,
        odometry_noise: OdometryNoise | None = None,
        sensor_model: str = DEFAULT_SENSOR_MODEL,
        weather: str = "clear",
        return_mode: str = "strongest",
    ):
        if world.car is None:
            raise InputError(f"{world.path}: the scene has no car to drive")
        self.world = world
        self.spec = spec
        self.car = world.car
        self.controller = RouteFollower(self.car, route, cruise_mps=cruise_mps)
        self.odometry = WheelGyroOdometry(self.car, rng, odometry_noise)
        returns, sky = sensor_setup(spec, sensor_model, weather, return_mode)
        self.sensor_model = sensor_model
        self.lidar = SimLidar(
            spec,
            world.caster,
            rng,
            skew=skew,
            actor_mesh_ids=world.actor_handles,
            materials=None if returns is None else world.materials,
            returns=returns,
            weather=sky,
            return_mode=return_mode,
        )
        self.chunks = max(1, int(chunks_per_sweep))
        self.dt = float(world.model.opt.timestep)
        self.frame_index = 0
        self.manual: tuple[float, float] | None = None  # (speed m/s, steering rad) instead of the route
        x, y, yaw = route.start_pose()
        ground = float(world.ground_height(x, y))
        self.car.place(world.model, world.data, x, y, ground + 0.02, yaw)
        self._brake_and_settle(settle_s)
        self.odometry.reset(world.data)
        self.t0 = world.time

    def odometry_errors(self) -> dict:
        """What this drive's wheel-and-gyro odometry gets wrong, drawn from the run's seed
        (:class:`~simbed.sim.vehicle.OdometryNoise`: the spreads, 1 sigma) and the values drawn for this
        drive:
        the wheel radius's relative error (distance x ``wheel_scale``) and the gyro's initial bias (it
        then random-walks)."""
        o = self.odometry
        n = o.noise
        return {
            "wheel_scale": round(float(o.scale), 6),
            "gyro_bias_initial_deg_s": round(float(np.degrees(o.bias)), 6),
            "spreads_1sigma": {
                "wheel_scale": n.wheel_scale,
                "wheel_noise_m_per_sqrt_m": n.wheel_noise_m_per_sqrt_m,
                "gyro_bias_deg_s": round(float(np.degrees(n.gyro_bias_rad_s)), 6),
                "gyro_bias_walk_deg_s_per_sqrt_s": round(
                    float(np.degrees(n.gyro_bias_walk_rad_s_per_sqrt_s)), 6
                ),
                "gyro_noise_deg_per_sqrt_s": round(float(np.degrees(n.gyro_noise_rad_per_sqrt_s)), 6),
                "imu_roll_pitch_deg": round(float(np.degrees(n.imu_roll_pitch_rad)), 6),
            },
        }

    def _brake_and_settle(self, seconds: float) -> None:
        d = self.world.data
        for _ in range(int(round(seconds / self.dt))):
            for a in self.car.steer:
                d.ctrl[a] = 0.0
            for a in self.car.drive:
                d.ctrl[a] = -400.0 * self.car.speed(d)
            self.world.step()

    def _control(self) -> None:
        if self.manual is None:
            self.controller.control(self.world.data, self.dt)
            return
        speed_mps, steer = self.manual
        car, d = self.car, self.world.data
        speed = car.speed(d)
        torque = self.controller.kp * (speed_mps - speed)
        for a in car.steer:
            d.ctrl[a] = steer
        for a, dof in zip(car.drive, car.rear_wheel_qvel, strict=True):
            d.ctrl[a] = wheel_torque(torque, float(d.qvel[dof]), speed, car.wheel_radius_m)

    def _physics_step(self) -> None:
        self._control()
        self.world.step()
        self.odometry.step(self.world.data, self.dt)

    def advance(self, seconds: float) -> None:
        """Drive on for ``seconds`` without the LiDAR (physics, controller and odometry only)."""
        end = self.world.time + float(seconds)
        while self.world.time < end - 1e-9:
            self._physics_step()

    def teleport_ahead(self, distance_m: float) -> None:
        """Kidnap the car: put it ``distance_m`` further along its route (at most 20 m before the route's
        end), at rest, heading along the route. The odometry is not told."""
        c = self.controller
        target = min(c.cumlen[c.index] + float(distance_m), max(c.cumlen[-1] - 20.0, 0.0))
        k = int(min(np.searchsorted(c.cumlen, target), len(c.points) - 2))
        d = c.points[min(k + 4, len(c.points) - 1)] - c.points[k]
        x, y = (float(t) for t in c.points[k])
        self.car.place(
            self.world.model,
            self.world.data,
            x,
            y,
            float(self.world.ground_height(x, y)) + 0.02,
            float(np.arctan2(d[1], d[0])),
        )
        c.index = k
        c.integral = 0.0
        c._progress_mark = (c._time, c.progress_m)
        self.odometry.resync(self.world.data)

    def _parts(self) -> dict:
        return {
            "drive": self,
            "world": self.world,
            "controller": self.controller,
            "odometry": self.odometry,
            "lidar": self.lidar,
        }

    def state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """What a checkpoint must hold to go on exactly from here (between frames), as JSON-able values and
        named arrays: MuJoCo's integration state (the kinematics are computed again from it, as the frame's
        last sync left them), the random generator's state and the parts' changing values
        (:data:`_STATE_ATTRS`)."""
        m, d = self.world.model, self.world.data
        physics = np.empty(mujoco.mj_stateSize(m, PHYSICS_STATE))
        mujoco.mj_getState(m, d, physics, PHYSICS_STATE)
        arrays = {"physics": physics}
        values: dict = {}
        parts = self._parts()
        for k, attrs in _STATE_ATTRS.items():
            for a in attrs:
                values[f"{k}.{a}"] = _encode(getattr(parts[k], a), f"{k}.{a}", arrays)
        return {"rng": self.odometry.rng.bit_generator.state, "values": values}, arrays

    def restore(self, doc: dict, arrays: dict[str, np.ndarray]) -> None:
        """Go on from a :meth:`state` taken by a drive set up with the same arguments."""
        m, d = self.world.model, self.world.data
        physics = np.asarray(arrays["physics"], np.float64)
        size = mujoco.mj_stateSize(m, PHYSICS_STATE)
        if physics.shape != (size,):
            raise ValueError(f"a physics state of {physics.size} values where the scene's has {size}")
        mujoco.mj_setState(m, d, physics, PHYSICS_STATE)
        mujoco.mj_kinematics(m, d)
        self.odometry.rng.bit_generator.state = doc["rng"]
        parts = self._parts()
        for k, attrs in _STATE_ATTRS.items():
            for a in attrs:
                setattr(parts[k], a, _decode(doc["values"][f"{k}.{a}"], arrays))

    def sensor_pose(self) -> np.ndarray:
        return self.car.pose(self.world.data) @ self.spec.T_base_sensor

    def next_frame(self) -> Frame:
        """Drive one LiDAR period and return the frame recorded at its end."""
        world, lidar = self.world, self.lidar
        period = lidar.period_s
        t_start = world.time
        times = [t_start]
        poses = [self.sensor_pose()]
        w = lidar.geometry.shape[1]
        # with skew, columns are cast chunk by chunk as they fire; without, all at once from the end pose
        chunks = self.chunks if lidar.skew else 1
        bounds = np.linspace(0, w, chunks + 1).astype(int)
        for k in range(chunks):
            t_chunk_end = t_start + period * (k + 1) / chunks
            while world.time < t_chunk_end - 1e-9:
                self._physics_step()
                times.append(world.time)
                poses.append(self.sensor_pose())
            world.sync_caster()
            lidar.cast_columns(slice(bounds[k], bounds[k + 1]), t_start, np.asarray(times), np.asarray(poses))
        sweep = lidar.finish(t_start, np.asarray(times), np.asarray(poses))
        frame = Frame(
            index=self.frame_index,
            sweep=sweep,
            T_world_sensor=sweep.T_world_sensor,
            T_odom_sensor=self.odometry.pose() @ self.spec.T_base_sensor,
            imu_roll_pitch=self.odometry.imu_roll_pitch(world.data),
            time_s=sweep.t_end - self.t0,
            speed_mps=self.car.speed(world.data),
            route_done=self.controller.done,
            stuck=self.controller.stuck,
        )
        self.frame_index += 1
        if not np.isfinite(world.data.qpos).all():
            raise RuntimeError(f"physics diverged at t = {world.time:.3f} s (frame {frame.index})")
        return frame
