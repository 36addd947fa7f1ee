"""Agents for ``simbed/LocalizationTrial-v0``: rangemcl's Monte Carlo localizer as a policy.

::

    env = gymnasium.make("simbed/LocalizationTrial-v0", actors=10)
    agent = MCLAgent.for_env(env, "out/demo/map")          # a map folder or a MeshMap
    obs, info = env.reset(seed=0)
    agent.reset()                                          # global localization (or agent.reset(pose))
    while True:
        obs, reward, terminated, truncated, info = env.step(agent(obs))
        if terminated or truncated:
            break

The agent back-projects the observed range image with the environment's sensor geometry, levels it with
the observed IMU roll and pitch and feeds the odometry increment to the filter; its action is the
filter's estimate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangemcl.localization import LocalizerSettings, build_localizer
from rangemcl.maps.meshmap import MeshMap
from rangemcl.maps.view import open_map
from rangemcl.rangeimage import RangeImageGeometry


class MCLAgent:
    """rangemcl's localizer as a policy: observation in, pose estimate ``(x, y, yaw)`` out.

    Args:
        mesh_map: a map folder (held whole, or within ``settings.map_memory_mb``: see
            :func:`rangemcl.maps.view.open_map`) or a loaded :class:`MeshMap`.
        geometry: the sensor's range-image geometry (``env.unwrapped.geometry``).
        settings: localizer settings (defaults: rangemcl's).
        sensor_height_m: the sensor's height above the ground.
        seed, device, threads: as for :class:`MonteCarloLocalizer`.
    """

    def __init__(
        self,
        mesh_map: MeshMap | str | Path,
        geometry: RangeImageGeometry,
        *,
        settings: LocalizerSettings | None = None,
        sensor_height_m: float | None = None,
        seed: int = 0,
        device: str = "cpu",
        threads: int | None = None,
    ):
        caster = None
        if isinstance(mesh_map, MeshMap):
            self.map = mesh_map
        else:  # whole, or within settings.map_memory_mb (rangemcl.maps.view)
            memory = settings.map_memory_mb if settings is not None else None
            self.map, caster = open_map(mesh_map, memory, device=device, threads=threads)
        self.geometry = geometry
        self.filter = build_localizer(
            self.map,
            settings,
            seed=seed,
            device=device,
            threads=threads,
            sensor_height_m=sensor_height_m,
            caster=caster,
        )
        self.last_info = None

    @classmethod
    def for_env(cls, env, mesh_map, **kwargs) -> MCLAgent:
        """An agent for a simbed environment: its sensor geometry and mounting height."""
        base = env.unwrapped
        kwargs.setdefault("sensor_height_m", float(base.lidar_spec.T_base_sensor[2, 3]))
        return cls(mesh_map, base.geometry, **kwargs)

    def reset(self, init_pose=None, particles: int | None = None) -> None:
        """Global localization (no prior), or tracking from ``init_pose`` ``(x, y, yaw)``."""
        if init_pose is None:
            self.filter.spread(particles)
        else:
            self.filter.start_at(np.asarray(init_pose, np.float64), particles)
        self.last_info = None

    def __call__(self, obs: dict) -> np.ndarray:
        if len(self.filter.particles) == 0:
            self.reset()
        image = np.asarray(obs["range_image"], np.float32)
        points = self.geometry.back_project(image)[image > 0]
        imu = obs.get("imu")
        self.last_info = self.filter.step(
            np.asarray(obs["odometry"], np.float64),
            points,
            roll_pitch=None if imu is None else (float(imu[0]), float(imu[1])),
        )
        return self.last_info.estimate.astype(np.float32)


def run_episode(
    env,
    agent,
    *,
    seed: int | None = None,
    options: dict | None = None,
    init_pose=None,
    tracking: bool = False,
) -> dict:
    """One trial: reset, step with the agent's estimates until the episode ends; errors per step.

    ``tracking`` starts the agent at the true initial pose (from ``info``), else at ``init_pose`` or with
    global localization."""
    obs, info = env.reset(seed=seed, options=options)
    agent.reset(info["true_pose"] if tracking else init_pose)
    errors, yaw_errors, converged, rewards = [], [], [], []
    while True:
        obs, reward, terminated, truncated, info = env.step(agent(obs))
        errors.append(info["position_error_m"])
        yaw_errors.append(info["yaw_error_deg"])
        converged.append(bool(agent.last_info.converged))
        rewards.append(reward)
        if terminated or truncated:
            break
    return {
        "position_error_m": np.array(errors),
        "yaw_error_deg": np.array(yaw_errors),
        "converged": np.array(converged),
        "reward": float(np.sum(rewards)),
        "steps": len(errors),
        "kidnapped": bool(info.get("kidnapped")),
        "recoveries": agent.filter.recoveries,
    }
