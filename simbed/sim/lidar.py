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
noise, intensity 0) and ``realistic``: each pulse's echoes (its footprint at depth edges, glass passed on,
the weather's clutter: :mod:`simbed.sim.echoes`, :mod:`simbed.sim.weather`) and each echo's material,
angle and range decide whether a point is reported, its noise and its intensity
(:mod:`simbed.sim.returns`, :mod:`simbed.sim.materials`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import interpolate_poses
from rangemcl.sensors import LidarSpec
from simbed.sim import SENSOR_MODELS
from simbed.sim.echoes import AXIS_WEIGHT, RETURN_MODES, echoes, edge_pixels, footprint_offsets, trace
from simbed.sim.returns import ReturnModel
from simbed.sim.weather import Weather

LABEL_STATIC = 0
LABEL_ACTOR = 1


def sensor_setup(
    spec: LidarSpec, sensor_model: str, weather: str = "clear", return_mode: str = "strongest"
) -> tuple[ReturnModel | None, Weather]:
    """The realistic sensor's return model (None for the ideal one) and the weather, every bad choice one
    :class:`InputError` line: an unknown model, weather or return mode, a spec without the realistic
    model's figures, weather or return modes asked of the ideal sensor."""
    if sensor_model not in SENSOR_MODELS:
        raise InputError(f"sensor model {sensor_model!r}: expected {', '.join(SENSOR_MODELS)}")
    sky = Weather.parse(weather)
    check_return_mode(spec, return_mode)
    if sensor_model == "ideal":
        if sky.kind != "clear" or return_mode != "strongest":
            raise InputError(
                "weather and return modes need the realistic sensor model (--sensor-model realistic)"
            )
        return None, sky
    return ReturnModel.for_spec(spec, sky), sky


def check_return_mode(spec: LidarSpec, mode: str) -> None:
    """One error line for a return mode the sensor does not have."""
    if mode not in RETURN_MODES:
        raise InputError(f"return mode {mode!r}: expected {', '.join(RETURN_MODES)}")
    if mode != "strongest" and not spec.dual_return:
        raise InputError(
            f"lidar spec {spec.name!r} reports its strongest echo only (no dual_return): not {mode!r}"
        )


@dataclass
class Sweep:
    """One LiDAR sweep."""

    points: np.ndarray  # (N, 3) float32, each in the sensor frame at its firing time
    ring: np.ndarray  # (N,) uint16 beam index (the spec's laser-id order)
    column: np.ndarray  # (N,) uint16 firing column
    time_s: np.ndarray  # (N,) float32 firing time relative to t_end (<= 0)
    label: np.ndarray  # (N,) uint8 LABEL_STATIC or LABEL_ACTOR
    intensity: np.ndarray  # (N,) float32 (the realistic model's; zeros for the ideal one)
    echo: np.ndarray  # (N,) uint8 0: the reported (strongest or last) echo; 1: a dual return's last echo
    snr: np.ndarray  # (N,) float32 the return's signal-to-noise ratio (realistic; zeros for the ideal sensor)
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
        weather: the realistic sensor's weather (:class:`~simbed.sim.weather.Weather`; clear if None).
        return_mode: the realistic sensor's ``strongest``, ``last`` or ``dual`` (the spec must have
            ``dual_return`` for the last two).
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
        weather=None,
        return_mode: str = "strongest",
    ):
        if (materials is None) != (returns is None):
            raise ValueError("the realistic sensor needs both the scene's materials and a return model")
        check_return_mode(spec, return_mode)
        self.materials = materials
        self.returns = returns
        self.weather = weather or Weather()
        self.return_mode = return_mode
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
        # realistic: [range, signal, rho, label] arrays (W, H) of the strongest echo, then of the last
        self._echoes: list[list[np.ndarray]] | None = None
        self._footprint = None
        if returns is not None:
            self._echoes = [
                [np.zeros((w, h)), np.zeros((w, h)), np.zeros((w, h), np.float32), np.zeros((w, h), np.uint8)]
                for _ in range(2)
            ]
            if spec.beam_divergence_mrad:
                fp = footprint_offsets(self.geometry, spec.beam_divergence_mrad * 1e-3)  # (H, W, 4, 3)
                self._footprint = np.ascontiguousarray(fp.transpose(1, 0, 2, 3))  # (W, H, 4, 3)
        self._last_axis: np.ndarray | None = None  # the axis ranges of the column cast last

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
            self._cast_realistic(cols, len(w_idx), origins, dirs, Rt)
            return
        hits = self.caster.cast(origins, dirs, self.spec.max_range_m)
        r = hits.ranges.reshape(len(w_idx), h)
        self._ranges[cols] = np.where(np.isfinite(r), r, 0.0)
        self._labels[cols] = np.isin(hits.mesh_ids, self._actor_ids).reshape(len(w_idx), h)

    def _cast_realistic(self, cols: slice, c: int, origins: np.ndarray, dirs: np.ndarray, Rt) -> None:
        """Trace the pulses of ``c`` columns (:mod:`simbed.sim.echoes`) and keep their strongest and last
        echoes."""
        h = self.geometry.shape[0]
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        args = (self.caster, self.materials, self.returns, self._actor_ids)
        axis = trace(*args, origins, unit, self.spec.max_range_m)
        n, p = axis.range_m.shape
        weight = np.ones(n)
        cand = [axis.range_m, axis.signal, axis.rho, axis.label]
        first = axis.range_m[:, 0].reshape(c, h)
        if self._footprint is not None:
            edge = edge_pixels(first, self._last_axis).reshape(-1)
            sel = np.flatnonzero(edge)
            sub = [np.zeros((n, 4 * p)), np.zeros((n, 4 * p)), np.zeros((n, 4 * p), np.float32)]
            sub.append(np.zeros((n, 4 * p), np.uint8))
            if len(sel):
                fp = np.matmul(self._footprint[cols].reshape(c, h * 4, 3), Rt).reshape(-1, 4, 3)[sel]
                o = np.repeat(origins[sel], 4, axis=0)
                tr = trace(*args, o, fp.reshape(-1, 3), self.spec.max_range_m)
                share = (1.0 - AXIS_WEIGHT) / 4
                sub[0][sel] = tr.range_m.reshape(len(sel), 4 * p)
                sub[1][sel] = tr.signal.reshape(len(sel), 4 * p) * share
                sub[2][sel] = tr.rho.reshape(len(sel), 4 * p) * share
                sub[3][sel] = tr.label.reshape(len(sel), 4 * p)
                weight[sel] = AXIS_WEIGHT
            cand = [
                np.concatenate([a * (weight[:, None] if k in (1, 2) else 1), b], axis=1)
                for k, (a, b) in enumerate(zip(cand, sub, strict=True))
            ]
        if self.weather.kind != "clear":
            hard = np.where(first > 0, first, 0.0).reshape(-1)
            wr, ws = self.weather.clutter(self.rng, hard, self.spec.min_range_m, self.returns)
            cand = [
                np.concatenate([a, b[:, None].astype(a.dtype)], axis=1)
                for a, b in zip(cand, (wr, ws, ws * wr**2, np.zeros(n, np.uint8)), strict=True)
            ]
        self._last_axis = first[-1].copy()
        strong, last = echoes(*cand)
        for store, e in zip(self._echoes, (strong, last), strict=True):
            for arr, value in zip(store, (e.range_m, e.signal, e.rho, e.label), strict=True):
                arr[cols] = value.reshape(c, h)

    def finish(self, t_start: float, pose_times: np.ndarray, poses: np.ndarray) -> Sweep:
        """Turn the cast columns into a sweep: noise, dropout and range limits, points in the sensor frame
        of their firing time, stamped with the sweep-end time and pose."""
        spec = self.spec
        if self.returns is None:
            true_r = self._ranges  # (W, H)
            noisy = true_r + self.rng.normal(0.0, spec.range_noise_m, true_r.shape).astype(np.float32)
            keep = (true_r > 0) & (noisy >= spec.min_range_m) & (noisy <= spec.max_range_m)
            if spec.dropout_prob > 0:
                keep &= self.rng.random(true_r.shape) >= spec.dropout_prob
            zero = np.zeros(true_r.shape, np.float32)
            reported = [(noisy, keep, zero, self._labels, zero)]
        else:
            which = {"strongest": [0], "last": [1], "dual": [0, 1]}[self.return_mode]
            reported = []
            for k in which:
                r, signal, rho, label = self._echoes[k]
                sigma = self.returns.noise_sigma(signal)
                noisy = (r + self.rng.normal(0.0, 1.0, r.shape) * sigma).astype(np.float32)
                detected = self.rng.random(r.shape) < self.returns.detection_probability(signal)
                keep = (r > 0) & detected & (noisy >= spec.min_range_m) & (noisy <= spec.max_range_m)
                if spec.dropout_prob > 0:
                    keep &= self.rng.random(r.shape) >= spec.dropout_prob
                if k == 1 and len(which) == 2:  # dual: the last echo where it is not the strongest
                    keep &= np.abs(r - self._echoes[0][0]) > 1e-9
                snr = self.returns.snr(signal).astype(np.float32)
                reported.append((noisy, keep, self.returns.intensity(rho), label, snr))
        t_end = t_start + self.period_s
        T_end = interpolate_poses(pose_times, poses, np.array([t_end]))[0]
        image = np.zeros(self.geometry.shape, np.float32)
        parts = []
        for e, (noisy, keep, intensity, labels, snr) in enumerate(reported):
            cols, rows = np.nonzero(keep)  # column-major order: firing order
            r = noisy[cols, rows].astype(np.float64)
            if e == 0:
                image[rows, cols] = r
            points = (
                self._orig[cols, rows] + r[:, None] * self._dirs[cols, rows]
            )  # (N, 3) each column's frame
            parts.append(
                (
                    cols,
                    rows,
                    points,
                    intensity[cols, rows],
                    labels[cols, rows],
                    np.full(len(r), e),
                    snr[cols, rows],
                )
            )
        cols, rows, points, intensity, labels, echo, snr = (
            np.concatenate(x) for x in zip(*parts, strict=True)
        )
        if len(parts) > 1:  # firing order: by column, the echoes of one pulse together
            order = np.lexsort((echo, rows, cols))
            cols, rows, points, intensity, labels, echo, snr = (
                a[order] for a in (cols, rows, points, intensity, labels, echo, snr)
            )
        fire = t_start + self.column_time_s[cols]
        return Sweep(
            points=points.astype(np.float32),
            ring=self.geometry.row_beam[rows].astype(np.uint16),
            column=cols.astype(np.uint16),
            time_s=(fire - t_end).astype(np.float32),
            label=labels.astype(np.uint8),
            intensity=intensity.astype(np.float32),
            echo=echo.astype(np.uint8),
            snr=snr.astype(np.float32),
            ranges=image,
            t_end=t_end,
            T_world_sensor=T_end,
        )
