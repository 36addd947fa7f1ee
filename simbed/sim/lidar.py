"""The simulated spinning LiDAR: complete 360° sweeps at the spec's rate, with per-column firing times.

A sweep lasts one rotation period. Column ``c`` fires at ``t_start + c / W · period``. The simulation
advances physics in chunks of the sweep; after each chunk the columns that fired during it are cast from
the sensor poses at their own firing times (interpolated between the physics steps), against the world as
it is at the end of the chunk, so moving actors appear where they were when they were scanned.

Each point is reported in the sensor frame at its own firing time, as a real driver reports it (no
motion compensation), and the scan is stamped with the sweep's end time and pose. So a moving car's scan
is skewed as on a real car: a point fired ``dt`` before the end appears displaced by the motion during
``dt``. With ``skew=False`` every column fires from the sweep-end pose (an instantaneous scan).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import interpolate_poses
from rangemcl.sensors import LidarSpec

LABEL_STATIC = 0
LABEL_ACTOR = 1


@dataclass
class Sweep:
    """One LiDAR sweep."""

    points: np.ndarray  # (N, 3) float32, each in the sensor frame at its firing time
    ring: np.ndarray  # (N,) uint16 beam index (the spec's laser-id order)
    column: np.ndarray  # (N,) uint16 firing column
    time_s: np.ndarray  # (N,) float32 firing time relative to t_end (<= 0)
    label: np.ndarray  # (N,) uint8 LABEL_STATIC or LABEL_ACTOR
    ranges: np.ndarray  # (H, W) float32 range image (rows by elevation), 0 = no return
    t_end: float
    T_world_sensor: np.ndarray  # (4, 4) at t_end


class SimLidar:
    """Casts a spec's sweep through the shared Warp core, chunk by chunk.

    Args:
        spec: the sensor.
        caster: the world's ray caster (static world + movable actor meshes; never the ego car).
        rng: the run's seeded generator (range noise, dropout).
        skew: take each column's own sensor pose (True) or the sweep-end pose for all (False).
        actor_mesh_ids: caster mesh handles that belong to moving actors (for point labels).
    """

    def __init__(
        self,
        spec: LidarSpec,
        caster: RayCaster,
        rng: np.random.Generator,
        *,
        skew: bool = True,
        actor_mesh_ids=(),
    ):
        self.spec = spec
        self.caster = caster
        self.rng = rng
        self.skew = skew
        self.geometry = RangeImageGeometry.for_spec(spec)
        h, w = self.geometry.shape
        # column-major (W, H, 3): one column's beams together, columns in firing order
        self._dirs = np.ascontiguousarray(self.geometry.directions.transpose(1, 0, 2))
        self._orig = np.ascontiguousarray(self.geometry.origins.transpose(1, 0, 2))
        self._actor_ids = np.asarray(sorted(actor_mesh_ids), dtype=np.int32)
        self.period_s = spec.sweep_period_s
        self.column_time_s = np.arange(w) / w * self.period_s  # offset of each column from sweep start
        self._ranges = np.zeros((w, h), np.float32)
        self._labels = np.zeros((w, h), np.uint8)

    def cast_columns(self, cols: slice, t_start: float, pose_times: np.ndarray, poses: np.ndarray) -> None:
        """Cast columns ``cols`` of the sweep that started at ``t_start``; ``poses`` ``(S, 4, 4)`` are
        ``T_world_sensor`` sampled at ``pose_times`` (covering those columns' firing times)."""
        w_idx = np.arange(self.geometry.shape[1])[cols]
        if len(w_idx) == 0:
            return
        h = self.geometry.shape[0]
        fire = t_start + self.column_time_s[w_idx]
        T = interpolate_poses(pose_times, poses, fire) if self.skew else np.repeat(poses[-1:], len(w_idx), 0)
        R, t = T[:, :3, :3], T[:, :3, 3]  # (C, 3, 3), (C, 3)
        Rt = R.transpose(0, 2, 1)
        dirs = np.matmul(self._dirs[cols], Rt).reshape(-1, 3)  # (C, H, 3) rotated per column
        origins = (np.matmul(self._orig[cols], Rt) + t[:, None, :]).reshape(-1, 3)
        hits = self.caster.cast(origins, dirs, self.spec.max_range_m)
        r = hits.ranges.reshape(len(w_idx), h)
        self._ranges[cols] = np.where(np.isfinite(r), r, 0.0)
        self._labels[cols] = np.isin(hits.mesh_ids, self._actor_ids).reshape(len(w_idx), h)

    def finish(self, t_start: float, pose_times: np.ndarray, poses: np.ndarray) -> Sweep:
        """Turn the cast columns into a sweep: noise, dropout and range limits, points in the sensor frame
        of their firing time, stamped with the sweep-end time and pose."""
        spec = self.spec
        true_r = self._ranges  # (W, H)
        noisy = true_r + self.rng.normal(0.0, spec.range_noise_m, true_r.shape).astype(np.float32)
        keep = (true_r > 0) & (noisy >= spec.min_range_m) & (noisy <= spec.max_range_m)
        if spec.dropout_prob > 0:
            keep &= self.rng.random(true_r.shape) >= spec.dropout_prob
        cols, rows = np.nonzero(keep)  # column-major order: firing order
        r = noisy[cols, rows].astype(np.float64)
        points = self._orig[cols, rows] + r[:, None] * self._dirs[cols, rows]  # (N, 3) each column's frame
        t_end = t_start + self.period_s
        fire = t_start + self.column_time_s[cols]
        T_end = interpolate_poses(pose_times, poses, np.array([t_end]))[0]
        image = np.zeros(self.geometry.shape, np.float32)
        image[rows, cols] = r
        return Sweep(
            points=points.astype(np.float32),
            ring=self.geometry.row_beam[rows].astype(np.uint16),
            column=cols.astype(np.uint16),
            time_s=(fire - t_end).astype(np.float32),
            label=self._labels[cols, rows].astype(np.uint8),
            ranges=image,
            t_end=t_end,
            T_world_sensor=T_end,
        )
