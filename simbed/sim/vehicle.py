"""The ego car: handles into its MJCF (``scenes/car.xml``), a route-following controller on its steering
and drive torque, and what it measures of itself (wheel odometry, a drifting yaw-rate gyro, IMU roll/pitch).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rangemcl.errors import InputError
from rangemcl.se2 import pose2d, pose_matrix, wrap_angle
from simbed.scenes.routes import Route

STEER_ACTUATORS = ("steer_fl", "steer_fr")
DRIVE_ACTUATORS = ("drive_rl", "drive_rr")
REAR_WHEEL_JOINTS = ("wheel_rl", "wheel_rr")


def roll_pitch_of(R: np.ndarray) -> tuple[float, float]:
    """Roll and pitch (radians) of a rotation ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    return float(np.arctan2(R[2, 1], R[2, 2])), float(-np.arcsin(np.clip(R[2, 0], -1.0, 1.0)))


@dataclass
class CarHandles:
    """Indices of the car's parts in a compiled model, and its geometry read from the model."""

    body: int
    qpos_adr: int  # free joint: qpos[adr:adr+3] position, [adr+3:adr+7] quaternion (w, x, y, z)
    qvel_adr: int  # free joint: qvel[adr:adr+3] linear (world), [adr+3:adr+6] angular (body frame)
    steer: tuple[int, int]
    drive: tuple[int, int]
    rear_wheel_qpos: tuple[int, int]
    rear_wheel_qvel: tuple[int, int]
    wheelbase_m: float
    wheel_radius_m: float
    max_steer_rad: float
    max_torque_nm: float

    @classmethod
    def find(cls, model: mujoco.MjModel, data: mujoco.MjData, prefix: str = "") -> CarHandles:
        """The car of ``scenes/car.xml`` in ``model``, its names starting with ``prefix`` (``ego_`` when
        simbed added it to a scene without a car)."""

        def ident(kind, name):
            name = prefix + name
            i = mujoco.mj_name2id(model, kind, name)
            if i < 0:
                raise InputError(
                    f"the scene has no car: {kind.name.split('_')[-1].lower()} {name!r} is missing"
                )
            return i

        body = ident(mujoco.mjtObj.mjOBJ_BODY, "car")
        root = ident(mujoco.mjtObj.mjOBJ_JOINT, "car_root")
        steer = tuple(ident(mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in STEER_ACTUATORS)
        drive = tuple(ident(mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in DRIVE_ACTUATORS)
        wheels = [ident(mujoco.mjtObj.mjOBJ_JOINT, n) for n in REAR_WHEEL_JOINTS]
        mujoco.mj_forward(model, data)
        R, p = data.xmat[body].reshape(3, 3), data.xpos[body]
        front = ident(mujoco.mjtObj.mjOBJ_JOINT, "steer_fl")
        wheelbase = float((R.T @ (data.xanchor[front] - p))[0] - (R.T @ (data.xanchor[wheels[0]] - p))[0])
        wheel_body = model.jnt_bodyid[wheels[0]]
        geoms = np.flatnonzero(model.geom_bodyid == wheel_body)
        radius = float(model.geom_size[geoms[0], 0]) if len(geoms) else 0.33
        return cls(
            body=body,
            qpos_adr=int(model.jnt_qposadr[root]),
            qvel_adr=int(model.jnt_dofadr[root]),
            steer=steer,
            drive=drive,
            rear_wheel_qpos=tuple(int(model.jnt_qposadr[j]) for j in wheels),
            rear_wheel_qvel=tuple(int(model.jnt_dofadr[j]) for j in wheels),
            wheelbase_m=abs(wheelbase),
            wheel_radius_m=radius,
            max_steer_rad=float(model.actuator_ctrlrange[steer[0], 1]),
            max_torque_nm=float(model.actuator_ctrlrange[drive[0], 1]),
        )

    def pose(self, data: mujoco.MjData) -> np.ndarray:
        """``T_world_base`` (4×4), from the free joint's state (current even right after ``mj_step``)."""
        a = self.qpos_adr
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, data.qpos[a + 3 : a + 7])
        T = np.eye(4)
        T[:3, :3] = R.reshape(3, 3)
        T[:3, 3] = data.qpos[a : a + 3]
        return T

    def speed(self, data: mujoco.MjData) -> float:
        """Forward speed (m/s) along the car's x axis."""
        v = data.qvel[self.qvel_adr : self.qvel_adr + 3]
        return float(self.pose(data)[:3, 0] @ v)

    def place(
        self, model: mujoco.MjModel, data: mujoco.MjData, x: float, y: float, z: float, yaw: float
    ) -> None:
        """Put the car at rest at (x, y, z) heading ``yaw``."""
        a = self.qpos_adr
        data.qpos[a : a + 3] = (x, y, z)
        data.qpos[a + 3 : a + 7] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)


class RouteFollower:
    """Pure-pursuit steering and a PI speed loop on the drive torque, along a route's lane polyline.

    Speed is the cruise speed, lowered ahead of curves so that lateral acceleration stays below
    ``max_lateral_acc`` and brought down to a stop at the route's end.
    """

    def __init__(
        self,
        car: CarHandles,
        route: Route,
        *,
        cruise_mps: float = 8.0,
        max_lateral_acc: float = 2.0,
        kp: float = 900.0,
        ki: float = 250.0,
    ):
        self.car = car
        self.route = route
        self.cruise_mps = cruise_mps
        self.max_lateral_acc = max_lateral_acc
        self.kp, self.ki = kp, ki
        self.points = route.points
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cumlen = np.concatenate([[0.0], np.cumsum(seg)])
        self.curvature = _polyline_curvature(self.points)
        speeds = getattr(route, "speeds", None)
        self.speeds = None if speeds is None or not np.isfinite(speeds).any() else np.asarray(speeds, float)
        self.index = 0
        self.integral = 0.0
        self.done = False
        self.stuck = False  # no progress along the route for `stuck_after_s` of driving
        self.stuck_after_s = 10.0
        self._time = 0.0
        self._progress_mark = (0.0, 0.0)  # (time, progress) when progress last grew by a metre

    @property
    def progress_m(self) -> float:
        return float(self.cumlen[self.index])

    def _advance(self, xy: np.ndarray) -> None:
        """Move the progress index forward to the nearest point within the next 30 m of route."""
        end = np.searchsorted(self.cumlen, self.cumlen[self.index] + 30.0)
        window = self.points[self.index : max(end, self.index + 2)]
        self.index += int(np.argmin(np.linalg.norm(window - xy, axis=1)))

    def target_speed(self, speed: float) -> float:
        ahead = np.searchsorted(self.cumlen, self.cumlen[self.index] + max(15.0, 2.0 * speed))
        kappa = float(np.abs(self.curvature[self.index : max(ahead, self.index + 1)]).max())
        v = min(self.cruise_mps, np.sqrt(self.max_lateral_acc / max(kappa, 1e-6)))
        if self.speeds is not None:  # the route's own limits over the same stretch ahead
            limits = self.speeds[self.index : max(ahead, self.index + 1)]
            if np.isfinite(limits).any():
                v = min(v, float(np.nanmin(limits)))
        remaining = self.cumlen[-1] - self.cumlen[self.index]
        return float(min(v, np.sqrt(max(0.0, 2.0 * 1.5 * (remaining - 2.0)))))

    def control(self, data: mujoco.MjData, dt: float) -> None:
        """Set the car's actuator controls for the next physics step."""
        T = self.car.pose(data)
        xy, yaw = T[:2, 3], float(pose2d(T)[2])
        self._advance(xy)
        self._time += dt
        if self.progress_m > self._progress_mark[1] + 1.0:
            self._progress_mark = (self._time, self.progress_m)
        elif not self.done and self._time - self._progress_mark[0] > self.stuck_after_s:
            self.stuck = True
        speed = self.car.speed(data)
        if self.cumlen[-1] - self.cumlen[self.index] < 3.0:
            self.done = True
        look = max(5.0, 0.9 * abs(speed))
        k = min(int(np.searchsorted(self.cumlen, self.cumlen[self.index] + look)), len(self.points) - 1)
        d = self.points[k] - xy
        alpha = wrap_angle(np.arctan2(d[1], d[0]) - yaw)
        dist = max(float(np.linalg.norm(d)), 1e-3)
        steer = np.arctan2(2.0 * self.car.wheelbase_m * np.sin(alpha), dist)
        steer = float(np.clip(steer, -self.car.max_steer_rad, self.car.max_steer_rad))
        v_ref = 0.0 if self.done else self.target_speed(speed)
        err = v_ref - speed
        if abs(err) < 1.0:  # integrate near the target only, so accelerating does not wind it up
            self.integral = float(np.clip(self.integral + err * dt, -2.0, 2.0))
        torque = np.clip(
            self.kp * err + self.ki * self.integral, -self.car.max_torque_nm, self.car.max_torque_nm
        )
        for a in self.car.steer:
            data.ctrl[a] = steer
        for a, dof in zip(self.car.drive, self.car.rear_wheel_qvel, strict=True):
            data.ctrl[a] = wheel_torque(torque, float(data.qvel[dof]), speed, self.car.wheel_radius_m)


BRAKE_NM_PER_RAD_S = 300.0  # braking torque allowed per rad/s of forward wheel spin
MAX_WHEEL_NM = 600.0  # drive and brake torque per wheel: half the torque at which a rear wheel slips
SLIP_MARGIN_MPS = 0.3  # traction control: cut the drive when the wheel's rim outruns the car by more


def wheel_torque(torque: float, wheel_rate_rad_s: float, car_speed_mps: float, radius_m: float) -> float:
    """A rear wheel's torque as a car's brakes, anti-lock and traction control would let it through:
    at most ``MAX_WHEEL_NM`` either way; braking only slows a wheel that turns forward (in proportion to
    its spin, so it never drives the wheel backwards); drive torque is cut while the wheel spins faster
    than the car moves. Keeps wheel slip, and so the wheel odometry's error, small."""
    torque = float(np.clip(torque, -MAX_WHEEL_NM, MAX_WHEEL_NM))
    if torque >= 0.0:
        if wheel_rate_rad_s * radius_m > 1.1 * max(car_speed_mps, 0.0) + SLIP_MARGIN_MPS:
            return 0.0
        return torque
    return float(-min(-torque, BRAKE_NM_PER_RAD_S * max(wheel_rate_rad_s, 0.0)))


def _polyline_curvature(p: np.ndarray) -> np.ndarray:
    """Unsigned curvature (1/m) at each point of a polyline, from its neighbours."""
    if len(p) < 3:
        return np.zeros(len(p))
    a, b, c = p[:-2], p[1:-1], p[2:]
    ab, bc, ca = (np.linalg.norm(x, axis=1) for x in (b - a, c - b, a - c))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    k = 2.0 * cross / np.maximum(ab * bc * ca, 1e-12)
    return np.concatenate([[k[0]], k, [k[-1]]])


@dataclass
class OdometryNoise:
    """What the car's own sensors get wrong (1σ unless said otherwise)."""

    wheel_scale: float = 0.01  # constant relative error of the wheel radius, drawn once per run
    wheel_noise_m_per_sqrt_m: float = 0.005  # random distance error growing with the square root of distance
    gyro_bias_rad_s: float = 0.0005  # initial yaw-rate bias
    gyro_bias_walk_rad_s_per_sqrt_s: float = 0.0001  # bias random walk
    gyro_noise_rad_per_sqrt_s: float = 0.0005  # angle random walk
    imu_roll_pitch_rad: float = 0.002  # white noise on IMU roll and pitch


class WheelGyroOdometry:
    """Dead reckoning from the rear wheels' rotation and a yaw-rate gyro; it drifts as a real one does.

    The pose is kept in the odometry frame, which starts at the car's first pose flattened to (x, y, yaw).
    """

    def __init__(self, car: CarHandles, rng: np.random.Generator, noise: OdometryNoise | None = None):
        self.car = car
        self.rng = rng
        self.noise = noise or OdometryNoise()
        self.scale = 1.0 + rng.normal(0.0, self.noise.wheel_scale)
        self.bias = rng.normal(0.0, self.noise.gyro_bias_rad_s)
        self.x = self.y = self.yaw = 0.0
        self._wheels: np.ndarray | None = None

    def reset(self, data: mujoco.MjData) -> None:
        self._wheels = np.array([data.qpos[a] for a in self.car.rear_wheel_qpos])
        self.x = self.y = self.yaw = 0.0

    def resync(self, data: mujoco.MjData) -> None:
        """Take the wheels' current angles as the reference without moving the odometry pose (after the
        car was placed somewhere else: its odometry does not see the jump)."""
        self._wheels = np.array([data.qpos[a] for a in self.car.rear_wheel_qpos])

    def step(self, data: mujoco.MjData, dt: float) -> None:
        """Integrate one physics step."""
        wheels = np.array([data.qpos[a] for a in self.car.rear_wheel_qpos])
        if self._wheels is None:
            self._wheels = wheels
        ds = float(np.mean(wheels - self._wheels)) * self.car.wheel_radius_m * self.scale
        self._wheels = wheels
        n = self.noise
        ds += self.rng.normal(0.0, n.wheel_noise_m_per_sqrt_m * np.sqrt(abs(ds)))
        omega = float(data.qvel[self.car.qvel_adr + 5])  # body-frame yaw rate
        self.bias += self.rng.normal(0.0, n.gyro_bias_walk_rad_s_per_sqrt_s * np.sqrt(dt))
        dyaw = (omega + self.bias) * dt + self.rng.normal(0.0, n.gyro_noise_rad_per_sqrt_s * np.sqrt(dt))
        mid = self.yaw + dyaw / 2
        self.x += ds * np.cos(mid)
        self.y += ds * np.sin(mid)
        self.yaw = float(wrap_angle(self.yaw + dyaw))

    def pose(self) -> np.ndarray:
        """``T_odom_base`` (4×4, planar)."""
        return pose_matrix(self.x, self.y, self.yaw)

    def imu_roll_pitch(self, data: mujoco.MjData) -> tuple[float, float]:
        roll, pitch = roll_pitch_of(self.car.pose(data)[:3, :3])
        sigma = self.noise.imu_roll_pitch_rad
        return roll + self.rng.normal(0.0, sigma), pitch + self.rng.normal(0.0, sigma)
