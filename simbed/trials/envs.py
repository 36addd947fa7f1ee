"""Gymnasium environments: a localization trial (``simbed/LocalizationTrial-v0``) and a drivable car
(``simbed/Drive-v0``). Both are registered when :mod:`simbed` is imported.

**LocalizationTrial-v0**: one episode = one trial. The car follows its route in the chosen scene (parked-car
variant, moving actors); each step is one LiDAR frame. The observation is a ``Dict``:

* ``range_image``: ``(beams, columns)`` float32 metres, 0 where there is no return (the sensor's own
  beam/column grid: ``env.unwrapped.geometry`` back-projects it);
* ``odometry``: ``(dx, dy, dyaw)`` float32, the car's own measured motion since the previous frame in the
  previous frame's pose (wheel odometry and gyro, with their drift);
* ``imu``: ``(roll, pitch)`` float32 radians;
* ``intensity_image``: ``(beams, columns)`` float32, each return's intensity on the sensor's scale (0-255
  or 0-1: the spec's ``intensity_scale``), 0 where there is none; all 0 for the ideal sensor.

``sensor_model`` is ``ideal`` (every surface returns every ray) or ``realistic`` (materials decide returns,
noise and intensity: :mod:`simbed.sim.lidar`).

The **action** is the agent's pose estimate ``(x, y, yaw)`` of the sensor in the world. The reward is
``−min(position error, cap) − yaw_weight · min(|yaw error| in degrees, 180)`` of the estimate for the frame
just observed (the first action rates the reset's observation). ``terminated`` when the route ends (or the
car gets stuck), ``truncated`` by ``max_episode_steps``. ``info`` carries the true pose, the errors, the frame
index and whether the car has been kidnapped. ``reset(options=...)`` takes ``start_frame`` (frames driven,
without the LiDAR, before the first observation) and ``kidnap_at`` / ``kidnap_ahead_m`` (at that step the car
is teleported that far ahead along its route; its odometry does not notice).

**Drive-v0**: the action is ``(speed in m/s, steering angle in rad)`` for the car's own speed loop and
steering; the observation is the same ``Dict``; the reward is the distance driven on the road in the step
(minus 1 per step off it); ``terminated`` when the car leaves the roads by more than 5 m.

All randomness (actors, sensor and odometry noise) flows from the seed given to ``reset``.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.se2 import pose2d, se2_between, wrap_angle
from rangemcl.sensors import load_spec
from simbed.scenes.routes import distance_to_roads, make_route
from simbed.sim import DEFAULT_SENSOR_MODEL
from simbed.sim.drive import Drive, Frame
from simbed.sim.world import World

MAX_STEP_M = 10.0  # bound of the odometry observation per frame (a car at 100 m/s)


class _SimEnv(gym.Env):
    """What both environments share: the world, the drive, the sensor and the observation."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scene: str = "town_small",
        sensor: str = "os1-64",
        columns: int | None = None,
        route: str = "test",
        variant: int = 1,
        actors: int = 0,
        device: str = "cpu",
        render_mode: str | None = None,
        sensor_model: str = DEFAULT_SENSOR_MODEL,
    ):
        self.scene = scene
        self.sensor_model = sensor_model
        self.lidar_spec = load_spec(sensor)
        if columns:
            self.lidar_spec = self.lidar_spec.with_columns(int(columns))
        self.geometry = RangeImageGeometry.for_spec(self.lidar_spec)
        self.route_name = route
        self.variant = int(variant)
        self.actors = int(actors)
        self.device = device
        self.render_mode = render_mode
        probe = World(scene, variant=self.variant)  # checks the scene now; gives the bounds
        if probe.town is None:
            raise ValueError(f"{probe.path}: environments need a town with roads (its .yaml sidecar)")
        nodes = np.asarray(probe.town.nodes, np.float64)
        half = float(np.abs(nodes).max()) + 50.0
        self._bounds = half
        h, w = self.geometry.shape
        self.observation_space = spaces.Dict(
            {
                "range_image": spaces.Box(0.0, float(self.lidar_spec.max_range_m), (h, w), np.float32),
                "odometry": spaces.Box(
                    np.array([-MAX_STEP_M, -MAX_STEP_M, -math.pi], np.float32),
                    np.array([MAX_STEP_M, MAX_STEP_M, math.pi], np.float32),
                    dtype=np.float32,
                ),
                "imu": spaces.Box(-math.pi / 2, math.pi / 2, (2,), np.float32),
                "intensity_image": spaces.Box(0.0, 255.0, (h, w), np.float32),
            }
        )
        self.world: World | None = None
        self.drive: Drive | None = None
        self._last_odom = np.zeros(3)
        self._frame: Frame | None = None

    # --- shared machinery ---------------------------------------------------------------------------------

    def _start(self, seed: int | None) -> np.random.Generator:
        gym.Env.reset(self, seed=seed)
        rng = np.random.default_rng(self.np_random.integers(0, 2**63 - 1))
        self.world = World(
            self.scene, variant=self.variant, n_actors=self.actors, rng=rng, device=self.device
        )
        t = self.world.town
        self.route = make_route(self.route_name, self.world.graph, t.lane_width_m, t.road_width_m)
        self.drive = Drive(self.world, self.route, self.lidar_spec, rng, sensor_model=self.sensor_model)
        return rng

    def _observe(self, frame: Frame) -> dict[str, np.ndarray]:
        s = frame.sweep
        rows = np.asarray(self.lidar_spec.row_of_beam)[s.ring.astype(np.int64)]
        image = self.geometry.project(s.points, rows=rows, cols=s.column.astype(np.int64)).ranges
        intensity = np.zeros(self.geometry.shape, np.float32)
        intensity[rows, s.column.astype(np.int64)] = s.intensity
        odom = pose2d(frame.T_odom_sensor)
        delta = se2_between(self._last_odom, odom)
        self._last_odom = odom
        self._frame = frame
        return {
            "range_image": np.clip(image, 0.0, self.lidar_spec.max_range_m).astype(np.float32),
            "odometry": np.clip(delta, -MAX_STEP_M, MAX_STEP_M).astype(np.float32),
            "imu": np.clip(np.asarray(frame.imu_roll_pitch), -math.pi / 2, math.pi / 2).astype(np.float32),
            "intensity_image": intensity,
        }

    def _first_frame(self) -> Frame:
        frame = self.drive.next_frame()
        self._last_odom = pose2d(frame.T_odom_sensor)
        return frame

    def render(self):
        if self.render_mode != "rgb_array" or self.world is None:
            return None
        from simbed.sim.render import render_rgb

        return render_rgb(self.world)

    def close(self) -> None:
        self.world = None
        self.drive = None


class LocalizationTrialEnv(_SimEnv):
    """``simbed/LocalizationTrial-v0`` (see the module docstring)."""

    def __init__(self, *args, error_cap_m: float = 20.0, yaw_weight: float = 0.05, **kwargs):
        super().__init__(*args, **kwargs)
        b = self._bounds
        self.action_space = spaces.Box(
            np.array([-b, -b, -math.pi], np.float32), np.array([b, b, math.pi], np.float32), dtype=np.float32
        )
        self.error_cap_m = float(error_cap_m)
        self.yaw_weight = float(yaw_weight)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        options = dict(options or {})
        unknown = set(options) - {"start_frame", "kidnap_at", "kidnap_ahead_m"}
        if unknown:
            raise ValueError(
                f"unknown reset options {sorted(unknown)} (start_frame, kidnap_at, kidnap_ahead_m)"
            )
        self._start(seed)
        for _ in range(int(options.get("start_frame", 0))):
            self.drive.advance(self.drive.lidar.period_s)
        self.kidnap_at = options.get("kidnap_at")
        self.kidnap_ahead_m = float(options.get("kidnap_ahead_m", 150.0))
        self.kidnapped = False
        self.steps = 0
        frame = self._first_frame()
        obs = self._observe(frame)
        obs["odometry"][:] = 0.0
        return obs, self._info(frame, None)

    def _info(self, frame: Frame, estimate: np.ndarray | None) -> dict[str, Any]:
        truth = pose2d(frame.T_world_sensor)
        info: dict[str, Any] = {
            "true_pose": truth,
            "frame": frame.index,
            "time_s": frame.time_s,
            "kidnapped": self.kidnapped,
        }
        if estimate is not None:
            err = float(np.hypot(*(estimate[:2] - truth[:2])))
            yaw = abs(float(wrap_angle(float(estimate[2]) - truth[2])))
            info.update(position_error_m=err, yaw_error_deg=math.degrees(yaw))
        return info

    def step(self, action):
        estimate = np.asarray(action, np.float64).reshape(3)
        rated = self._frame  # the action estimates the pose of the frame last observed
        info_prev = self._info(rated, estimate)
        reward = -min(info_prev["position_error_m"], self.error_cap_m) - self.yaw_weight * min(
            info_prev["yaw_error_deg"], 180.0
        )
        self.steps += 1
        if self.kidnap_at is not None and self.steps == int(self.kidnap_at) and not self.kidnapped:
            self.drive.teleport_ahead(self.kidnap_ahead_m)
            self.kidnapped = True
        frame = self.drive.next_frame()
        obs = self._observe(frame)
        info = self._info(frame, None)
        info.update(
            estimate_rated=estimate,
            rated_frame=rated.index,
            position_error_m=info_prev["position_error_m"],
            yaw_error_deg=info_prev["yaw_error_deg"],
        )
        terminated = bool(frame.route_done or frame.stuck)
        return obs, float(reward), terminated, False, info


class DriveEnv(_SimEnv):
    """``simbed/Drive-v0`` (see the module docstring)."""

    def __init__(self, *args, max_speed_mps: float = 15.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.max_speed = float(max_speed_mps)
        steer = 0.6  # car.xml's steering range (rad)
        self.action_space = spaces.Box(
            np.array([0.0, -steer], np.float32),
            np.array([self.max_speed, steer], np.float32),
            dtype=np.float32,
        )

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if options:
            raise ValueError(f"Drive-v0 takes no reset options, got {sorted(options)}")
        self._start(seed)
        self.drive.manual = (0.0, 0.0)
        frame = self._first_frame()
        obs = self._observe(frame)
        obs["odometry"][:] = 0.0
        self._pose = pose2d(frame.T_world_sensor)
        return obs, {"true_pose": self._pose, "frame": frame.index}

    def step(self, action):
        a = np.clip(np.asarray(action, np.float64).reshape(2), self.action_space.low, self.action_space.high)
        self.drive.manual = (float(a[0]), float(a[1]))
        frame = self.drive.next_frame()
        obs = self._observe(frame)
        pose = pose2d(frame.T_world_sensor)
        moved = float(np.hypot(*(pose[:2] - self._pose[:2])))
        self._pose = pose
        off = float(distance_to_roads(pose[:2][None], self.world.graph)[0]) - self.world.town.road_width_m / 2
        reward = moved if off <= 0 else -1.0
        terminated = off > 5.0
        info = {
            "true_pose": pose,
            "frame": frame.index,
            "off_road_m": max(off, 0.0),
            "speed_mps": frame.speed_mps,
        }
        return obs, reward, bool(terminated), False, info
