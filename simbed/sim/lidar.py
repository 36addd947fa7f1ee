"""The simulated spinning LiDAR: complete 360° sweeps at the spec's rate, with per-column firing times.

A sweep lasts one rotation period. Column ``c`` fires at ``t_start + c / W · period``. The simulation
advances physics in chunks of the sweep; after each chunk the columns that fired during it are cast from
the sensor poses at their own firing times (interpolated between the physics steps), against the world as
it is at the end of the chunk, so moving actors appear where they were when they were scanned.

Each point is reported in the sensor frame at its own firing time, as a real driver reports it (no
motion compensation), and the scan is stamped with the sweep's end time and pose. So a moving car's scan
is skewed as on a real car: a point fired ``dt`` before the end appears displaced by the motion during
``dt``. With ``skew=False`` every column fires from the sweep-end pose (an instantaneous scan).

Two sensor models: ``ideal`` (every surface returns every ray up to the maximum range, Gaussian range
noise, intensity 0) and ``realistic`` (each hit's material, angle and range decide whether a point is
reported, its noise and its intensity: :mod:`simbed.sim.returns`, :mod:`simbed.sim.materials`; glass
passes most of the beam on to what lies behind it, and the strongest return along the ray is reported).
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
SENSOR_MODELS = ("ideal", "realistic")
GLASS_PASSES = 4  # glass surfaces a ray may cross (a car's cabin: four); the next surface ends it
_GLASS_STEP_M = 1e-3  # the continued ray starts this far beyond the pane


@dataclass
class Sweep:
    """One LiDAR sweep."""

    points: np.ndarray  # (N, 3) float32, each in the sensor frame at its firing time
    ring: np.ndarray  # (N,) uint16 beam index (the spec's laser-id order)
    column: np.ndarray  # (N,) uint16 firing column
    time_s: np.ndarray  # (N,) float32 firing time relative to t_end (<= 0)
    label: np.ndarray  # (N,) uint8 LABEL_STATIC or LABEL_ACTOR
    intensity: np.ndarray  # (N,) float32 (the realistic model's; zeros for the ideal one)
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
        materials, returns: the scene's materials and the sensor's return model (the realistic sensor);
            both None: the ideal sensor.
    """

    def __init__(
        self,
        spec: LidarSpec,
        caster: RayCaster,
        rng: np.random.Generator,
        *,
        skew: bool = True,
        actor_mesh_ids=(),
        materials=None,
        returns=None,
    ):
        if (materials is None) != (returns is None):
            raise ValueError("the realistic sensor needs both the scene's materials and a return model")
        self.materials = materials
        self.returns = returns
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
        self._signal = np.zeros((w, h), np.float64)  # realistic: received signal of the reported return
        self._rho = np.zeros((w, h), np.float32)  # realistic: its apparent reflectivity

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
        if self.returns is not None:
            r, label, signal, rho = self._cast_realistic(origins, dirs)
            shape = (len(w_idx), h)
            self._ranges[cols] = r.reshape(shape)
            self._labels[cols] = label.reshape(shape)
            self._signal[cols] = signal.reshape(shape)
            self._rho[cols] = rho.reshape(shape)
            return
        hits = self.caster.cast(origins, dirs, self.spec.max_range_m)
        r = hits.ranges.reshape(len(w_idx), h)
        self._ranges[cols] = np.where(np.isfinite(r), r, 0.0)
        self._labels[cols] = np.isin(hits.mesh_ids, self._actor_ids).reshape(len(w_idx), h)

    def _cast_realistic(self, origins: np.ndarray, dirs: np.ndarray):
        """Per ray: the strongest return's range (0: none), label, signal and apparent reflectivity (the
        effective reflectivity dimmed by the panes passed, which the sensor cannot tell apart).

        A ray that meets glass records the surface's own glint and goes on, weakened by its two-way
        transmission, across up to :data:`GLASS_PASSES` glass surfaces; the next surface ends it."""
        n = len(dirs)
        table, model = self.materials.table, self.returns
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        best_r = np.zeros(n, np.float32)
        best_s = np.zeros(n, np.float64)
        best_rho = np.zeros(n, np.float32)
        best_label = np.zeros(n, np.uint8)
        travelled = np.zeros(n, np.float64)  # metres from the sensor to the current ray's origin
        passing = np.ones(n, np.float64)  # two-way transmission of the panes passed so far
        live = np.arange(n)
        o = origins.astype(np.float64)
        for step in range(GLASS_PASSES + 1):
            hits = self.caster.cast(
                o[live], unit[live], self.spec.max_range_m - travelled[live], normals=True
            )
            hit = hits.hit
            idx, rr = live[hit], hits.ranges[hit].astype(np.float64)
            points = o[idx] + rr[:, None] * unit[idx]
            mat = self.materials.lookup(hits.mesh_ids[hit], hits.face_ids[hit], points, hits.normals[hit])
            cos = np.abs(np.einsum("ij,ij->i", hits.normals[hit], unit[idx]))
            glass = table.transmission[mat] > 0
            if step == GLASS_PASSES:  # the last pass: whatever it meets returns as an opaque surface
                glass[:] = False
            rho = model.effective_reflectivity(
                table.reflectivity[mat], table.mirror[mat], table.retro[mat], cos
            )
            total = travelled[idx] + rr
            signal = model.signal(rho, total, passing[idx])
            stronger = signal > best_s[idx]
            take = idx[stronger]
            best_r[take] = total[stronger]
            best_s[take] = signal[stronger]
            best_rho[take] = (rho * passing[idx])[stronger]  # as the sensor sees it: dimmed by the panes
            best_label[take] = np.isin(hits.mesh_ids[hit][stronger], self._actor_ids)
            go = glass
            live = idx[go]
            if len(live) == 0:
                break
            passing[live] *= table.transmission[mat[go]].astype(np.float64) ** 2
            o[live] = points[go] + _GLASS_STEP_M * unit[live]
            travelled[live] = total[go] + _GLASS_STEP_M
        return best_r, best_label, best_s, best_rho

    def finish(self, t_start: float, pose_times: np.ndarray, poses: np.ndarray) -> Sweep:
        """Turn the cast columns into a sweep: noise, dropout and range limits, points in the sensor frame
        of their firing time, stamped with the sweep-end time and pose."""
        spec = self.spec
        true_r = self._ranges  # (W, H)
        if self.returns is None:
            noisy = true_r + self.rng.normal(0.0, spec.range_noise_m, true_r.shape).astype(np.float32)
            keep = (true_r > 0) & (noisy >= spec.min_range_m) & (noisy <= spec.max_range_m)
            intensity = np.zeros(true_r.shape, np.float32)
        else:
            sigma = self.returns.noise_sigma(self._signal)
            noisy = (true_r + self.rng.normal(0.0, 1.0, true_r.shape) * sigma).astype(np.float32)
            detected = self.rng.random(true_r.shape) < self.returns.detection_probability(self._signal)
            keep = (true_r > 0) & detected & (noisy >= spec.min_range_m) & (noisy <= spec.max_range_m)
            intensity = self.returns.intensity(self._rho)
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
            intensity=intensity[cols, rows].astype(np.float32),
            ranges=image,
            t_end=t_end,
            T_world_sensor=T_end,
        )
