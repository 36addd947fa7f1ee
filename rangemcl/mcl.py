"""Monte Carlo localization over ``(x, y, yaw)`` in a mesh map, weighted by the range-image observation
model (paper Eq. 5): :class:`MonteCarloLocalizer`.

One step per LiDAR frame (:meth:`MonteCarloLocalizer.step`):

1. The frame's odometry increment is accumulated. Particles move (odometry motion model, noise growing
   with the motion) and are weighted only once the car has moved ``update_distance_m`` or turned
   ``update_angle_deg`` since the last update; between updates the estimate follows the odometry.
2. Update: a subset of the scan's valid points is de-skewed with the frame's odometry (each point from
   the pose at its own firing time), levelled with the IMU's roll and pitch, and cast from every particle
   (sensor at the map's ground height under the particle plus the mounting height). Log-weights add
   ``−½ d² / σ_d²``; low-variance resampling when ``N_eff < 0.75 N``, weights reset after it.
3. Global localization starts from particles spread uniformly over the mapped drivable area with uniform
   yaw. Convergence is decided by tiles (all particles in ``N_conv`` tiles, as in the paper), guarded by
   the cloud's size; then the particle count drops (10,000 → 100 by default).
4. Recovery: when even the best particle disagrees with the scan for several updates in a row (its mean
   residual far above what it was while tracking), the particles are spread again and the filter
   relocalizes; the reference code, whose particle reduction cannot be undone, stays lost.

All randomness comes from the generator handed in (or made from ``seed``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from rangemcl.errors import InputError
from rangemcl.mapping.meshmap import MeshMap
from rangemcl.observation import ObservationModel
from rangemcl.particles import (
    MotionNoise,
    effective_sample_size,
    low_variance_resample,
    normalize_log_weights,
    odometry_increment,
    pose_estimate,
    sample_motion,
    wrap_angle,
)
from rangemcl.raycast import RayCaster

# ---------------------------------------------------------------------------------------------- settings


@dataclass
class ParticleSettings:
    global_count: int = 10000  # particles spread for global localization (and after a recovery)
    converged_count: int = 100  # particles kept once converged
    tracking_count: int = 100  # particles around the initial pose in tracking mode
    tracking_sigma_xy_m: float = 0.5  # spread of the tracking-mode start
    tracking_sigma_yaw_deg: float = 3.0
    resample_neff_ratio: float = 0.75  # resample when N_eff < ratio · N
    jitter_xy_m: float = 0.05  # roughening after each resampling once converged (keeps copies apart)
    jitter_yaw_deg: float = 0.5
    global_jitter_xy_m: float = 0.2  # roughening before convergence (lets clusters explore)
    global_jitter_yaw_deg: float = 2.0
    estimate_best_share: float = 0.8  # estimate = weighted mean of the best 80 %


@dataclass
class MotionSettings:
    update_distance_m: float = 0.2  # weight only after the car moved this far ...
    update_angle_deg: float = 5.0  # ... or turned this much
    rot_per_rot: float = 0.05  # odometry motion model noise (Thrun et al. alpha1..alpha4)
    rot_per_trans: float = 0.005
    trans_per_trans: float = 0.05
    trans_per_rot: float = 0.05


@dataclass
class ObservationSettings:
    model: str = "range"  # range (paper Eq. 5) | overlap | likelihood_field | histogram (rangemcl.models)
    sigma_m: float = 0.25  # σ_d of Eq. 5 (paper 5.0, reference code 2.0; chosen by measurement, README)
    rays: int = 500  # measured points cast per particle (a random subset of the valid ones) ...
    ray_sampling: str = "points"  # ... each valid point alike (points) or each elevation band alike
    # (elevation: 2-degree bands of the sensor's vertical field, so that a sensor whose beams crowd the
    # road near the car still sends rays to what lies farther and higher)
    margin_m: float = 2.0  # rays end at measured range + margin; a miss counts as the margin
    cap_m: float | None = 1.0  # residual cap (the robust variant); None: the paper's plain mean
    min_range_m: float = 2.0  # ignore returns this close (the car itself)
    max_range_m: float = 40.0  # as far as the map builder meshes (its scans.max_range_m)
    deskew: bool = True  # with per-point firing times and odometry
    level_with_imu: bool = True  # rotate the scan by the IMU's roll and pitch
    overlap_tau_m: float = 0.3  # overlap model: a ray agrees within this
    overlap_sigma: float = 0.1
    histogram_bins: int = 50  # histogram model: bins over [0, max_range_m)
    histogram_sigma: float = 0.05
    field_voxel_m: float = 0.1  # likelihood field: voxel map resolution
    field_sigma_m: float = 0.2
    field_weight: float = 20.0  # log-likelihood = weight · mean per-ray log-likelihood


@dataclass
class ConvergenceSettings:
    tiles: int = 1  # N_conv: converged when all particles lie in this many tiles ...
    max_radius_m: float = 10.0  # ... and 95 % of them within this radius of the estimate;
    compact_radius_m: float = 5.0  # a cloud this compact counts as converged across a tile border


@dataclass
class RecoverySettings:
    enabled: bool = True
    min_residual_m: float | None = None  # lost when the best particle's badness exceeds this (None: the
    # model's floor, 0.3 m for the range model) ...
    factor: float = 2.0  # ... and this many times its median over the recent converged updates ...
    updates: int = 5  # ... for this many updates in a row
    history: int = 50  # converged updates remembered for the median


@dataclass
class InitSettings:
    drive_radius_m: float = 6.0  # with a map that keeps its mapping drive: spread within this of it
    heading_sigma_deg: float = 15.0  # ... with yaw along the drive (either way) within this
    uniform_yaw_share: float = 0.25  # share of particles with uniform yaw all the same


@dataclass
class LocalizerSettings:
    particles: ParticleSettings = field(default_factory=ParticleSettings)
    motion: MotionSettings = field(default_factory=MotionSettings)
    observation: ObservationSettings = field(default_factory=ObservationSettings)
    convergence: ConvergenceSettings = field(default_factory=ConvergenceSettings)
    recovery: RecoverySettings = field(default_factory=RecoverySettings)
    init: InitSettings = field(default_factory=InitSettings)
    sensor_height_m: float | None = None  # mounting height; default: the sequence's sensor, else the map's

    def check(self, where: str = "settings") -> None:
        """Range checks that the types alone do not give; an InputError names the key."""
        p, m, o, c, r = self.particles, self.motion, self.observation, self.convergence, self.recovery
        positive = {
            "particles.global_count": p.global_count,
            "particles.converged_count": p.converged_count,
            "particles.tracking_count": p.tracking_count,
            "observation.sigma_m": o.sigma_m,
            "observation.rays": o.rays,
            "observation.margin_m": o.margin_m,
            "observation.max_range_m": o.max_range_m,
            "convergence.tiles": c.tiles,
            "recovery.updates": r.updates,
            "recovery.history": r.history,
        }
        for key in (
            "overlap_tau_m",
            "overlap_sigma",
            "histogram_bins",
            "histogram_sigma",
            "field_voxel_m",
            "field_sigma_m",
            "field_weight",
        ):
            positive[f"observation.{key}"] = getattr(o, key)
        if o.cap_m is not None:
            positive["observation.cap_m"] = o.cap_m
        if r.min_residual_m is not None:
            positive["recovery.min_residual_m"] = r.min_residual_m
        if self.sensor_height_m is not None:
            positive["sensor_height_m"] = self.sensor_height_m
        for key, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{where}: {key} must be > 0, got {value}")
        non_negative = {
            "particles.tracking_sigma_xy_m": p.tracking_sigma_xy_m,
            "particles.tracking_sigma_yaw_deg": p.tracking_sigma_yaw_deg,
            "particles.jitter_xy_m": p.jitter_xy_m,
            "particles.jitter_yaw_deg": p.jitter_yaw_deg,
            "motion.update_distance_m": m.update_distance_m,
            "motion.update_angle_deg": m.update_angle_deg,
            "motion.rot_per_rot": m.rot_per_rot,
            "motion.rot_per_trans": m.rot_per_trans,
            "motion.trans_per_trans": m.trans_per_trans,
            "motion.trans_per_rot": m.trans_per_rot,
            "observation.min_range_m": o.min_range_m,
            "convergence.max_radius_m": c.max_radius_m,
            "convergence.compact_radius_m": c.compact_radius_m,
            "recovery.factor": r.factor,
            "init.drive_radius_m": self.init.drive_radius_m,
            "init.heading_sigma_deg": self.init.heading_sigma_deg,
            "particles.global_jitter_xy_m": p.global_jitter_xy_m,
            "particles.global_jitter_yaw_deg": p.global_jitter_yaw_deg,
        }
        for key, value in non_negative.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{where}: {key} must be >= 0, got {value}")
        if not 0 <= self.init.uniform_yaw_share <= 1:
            raise InputError(
                f"{where}: init.uniform_yaw_share must be in [0, 1], got {self.init.uniform_yaw_share}"
            )
        if not 0 < p.resample_neff_ratio <= 1:
            raise InputError(
                f"{where}: particles.resample_neff_ratio must be in (0, 1], got {p.resample_neff_ratio}"
            )
        if not 0 < p.estimate_best_share <= 1:
            raise InputError(
                f"{where}: particles.estimate_best_share must be in (0, 1], got {p.estimate_best_share}"
            )
        from rangemcl.models import MODEL_NAMES

        if o.model not in MODEL_NAMES:
            raise InputError(
                f"{where}: observation.model {o.model!r}: expected one of {', '.join(MODEL_NAMES)}"
            )
        if o.ray_sampling not in ("points", "elevation"):
            raise InputError(
                f"{where}: observation.ray_sampling {o.ray_sampling!r}: expected 'points' or 'elevation'"
            )
        if o.min_range_m >= o.max_range_m:
            raise InputError(f"{where}: observation.min_range_m must be below observation.max_range_m")


# ---------------------------------------------------------------------------------------------- SE(2) helpers


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ⊕ b``: pose ``b`` (given in the frame of ``a``) in the frame ``a`` is given in; ``(..., 3)``."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ⊕ b``: pose ``b`` expressed in the frame of pose ``a``."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def rotation_roll_pitch(roll: float, pitch: float) -> np.ndarray:
    """``Ry(pitch) · Rx(roll)``: the sensor's attitude without its yaw (``R = Rz Ry Rx``)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return ry @ rx


# ---------------------------------------------------------------------------------------------- scan rays


@dataclass
class ScanRays:
    """The measured rays used to weight the particles: unit directions in the levelled sensor frame at
    the scan's stamp, and ranges."""

    directions: np.ndarray  # (R, 3) float64
    ranges: np.ndarray  # (R,) float64
    valid_points: int  # valid points in the scan before subsampling


ELEVATION_BAND_DEG = 2.0  # observation.ray_sampling "elevation": the bands sampled alike


def prepare_rays(
    points: np.ndarray,
    settings: ObservationSettings,
    rng: np.random.Generator,
    *,
    fire_time_s: np.ndarray | None = None,
    frame_period_s: float | None = None,
    frame_motion: np.ndarray | None = None,
    roll_pitch: tuple[float, float] | None = None,
) -> ScanRays | None:
    """Pick, de-skew and level the rays of one scan; ``None`` when it has no valid point.

    ``fire_time_s`` are the points' firing times relative to the scan's stamp (<= 0), ``frame_motion`` the
    odometry motion ``(dx, dy, dyaw)`` over the frame period that ends at the stamp (in the previous
    frame's pose), assumed uniform: a point fired at time ``t`` is moved by the part of that motion that
    happened after ``t``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    r = np.linalg.norm(p, axis=1)
    ok = np.isfinite(r) & (r >= settings.min_range_m) & (r <= settings.max_range_m)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    if len(idx) > settings.rays:
        weight = None
        if settings.ray_sampling == "elevation":
            band = np.floor(np.degrees(np.arcsin(p[idx, 2] / r[idx])) / ELEVATION_BAND_DEG).astype(np.int64)
            _, inverse, counts = np.unique(band, return_inverse=True, return_counts=True)
            weight = 1.0 / counts[inverse]
            weight /= weight.sum()
        # sorted: the rays keep sweep order, which keeps them coherent in memory
        idx = np.sort(rng.choice(idx, settings.rays, replace=False, p=weight))
    q = p[idx]
    if (
        settings.deskew
        and fire_time_s is not None
        and frame_motion is not None
        and frame_period_s is not None
        and frame_period_s > 0
    ):
        t = np.asarray(fire_time_s, np.float64).reshape(-1)[idx]
        # pose at firing time relative to the stamp's pose: the remaining share of the frame's motion, undone
        share = np.clip(-t / frame_period_s, 0.0, 1.0)  # 0 at the stamp, 1 a whole period before it
        end = np.asarray(frame_motion, np.float64)  # stamp pose in the previous frame's pose
        at = np.stack([(1 - share) * end[0], (1 - share) * end[1], (1 - share) * end[2]], axis=1)
        rel = se2_between(np.broadcast_to(end, at.shape), at)  # firing pose in the stamp's frame
        c, s = np.cos(rel[:, 2]), np.sin(rel[:, 2])
        q = np.stack(
            [c * q[:, 0] - s * q[:, 1] + rel[:, 0], s * q[:, 0] + c * q[:, 1] + rel[:, 1], q[:, 2]], axis=1
        )
    if settings.level_with_imu and roll_pitch is not None:
        q = q @ rotation_roll_pitch(*roll_pitch).T
    rng_ = np.linalg.norm(q, axis=1)
    return ScanRays(q / rng_[:, None], rng_, int(ok.sum()))


# ---------------------------------------------------------------------------------------------- the filter


@dataclass
class StepInfo:
    """What one :meth:`MonteCarloLocalizer.step` did."""

    estimate: np.ndarray  # (3,) x, y, yaw
    particles: int
    converged: bool
    updated: bool  # particles were moved and weighted this frame
    resampled: bool
    skipped_scan: bool  # the scan had no valid point (prediction only)
    best_residual_m: float  # best particle's mean residual at this update (NaN without an update)
    neff: float
    recovered: bool  # the filter declared itself lost and spread the particles again
    seconds: float


class MonteCarloLocalizer:
    """Particle filter over ``(x, y, yaw)`` in a :class:`MeshMap` (see the module docstring).

    Args:
        mesh_map: the map (its ground grid gives each particle's height).
        settings: :class:`LocalizerSettings`.
        rng: the run's generator (or give ``seed``).
        device: Warp device, ``"cpu"`` or ``"cuda"``.
        threads: CPU threads for the ray casting (None: all cores).
        sensor_height_m: the sensor's height above the ground (default: settings, then the map, then 1.73).
        caster: an existing :class:`RayCaster` holding the map (shared between filters), else one is made.
    """

    def __init__(
        self,
        mesh_map: MeshMap,
        settings: LocalizerSettings | None = None,
        *,
        rng: np.random.Generator | None = None,
        seed: int | None = None,
        device: str = "cpu",
        threads: int | None = None,
        sensor_height_m: float | None = None,
        caster: RayCaster | None = None,
    ):
        self.settings = settings or LocalizerSettings()
        self.settings.check()
        self.map = mesh_map
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        height = sensor_height_m if sensor_height_m is not None else self.settings.sensor_height_m
        if height is None:
            height = mesh_map.meta.get("sensor_height_m", 1.73)
        self.sensor_height_m = float(height)
        if caster is None:
            caster = RayCaster(device, threads)
            caster.add_mesh(mesh_map.vertices, mesh_map.faces, name="map")
        self.caster = caster
        o = self.settings.observation
        from rangemcl.models import RangeModel, make_model

        self.scorer = make_model(o.model, caster, o, mesh_map)
        # Eq. 5 residuals (residuals()): the range model's own kernel, or one of the same settings
        self.model = (
            self.scorer.kernel
            if isinstance(self.scorer, RangeModel)
            else ObservationModel(
                caster, sigma_m=o.sigma_m, margin_m=o.margin_m, cap_m=np.inf if o.cap_m is None else o.cap_m
            )
        )
        m = self.settings.motion
        self.noise = MotionNoise(m.rot_per_rot, m.rot_per_trans, m.trans_per_trans, m.trans_per_rot)
        self.init_cells = drivable_cells(mesh_map, self.settings.init)
        self.particles = np.zeros((0, 3))
        self.log_w = np.zeros(0)
        self.converged = False
        self.converged_updates = 0
        self.pending = np.zeros(3)  # odometry since the last update, in the pose at that update
        self.last_estimate = np.zeros(3)
        self.recoveries = 0
        self._best_history: list[float] = []
        self._bad_updates = 0
        self._spread_count = self.settings.particles.global_count

    # --- initialisation ---------------------------------------------------------------------------------

    def spread(self, n: int | None = None) -> None:
        """Global localization: ``n`` particles uniform over the drivable area; yaw along the mapping
        drive (either way) where the map keeps it, with a share of uniform yaw, else uniform."""
        n = int(n or self.settings.particles.global_count)
        self._spread_count = n
        area = self.init_cells
        k = self.rng.integers(0, len(area.corners), n)
        xy = area.corners[k] + self.rng.uniform(0.0, area.cell_m, (n, 2))
        yaw = self.rng.uniform(-np.pi, np.pi, n)
        if area.headings is not None:
            init = self.settings.init
            along = self.rng.uniform(0.0, 1.0, n) >= init.uniform_yaw_share
            m = int(along.sum())
            yaw[along] = wrap_angle(
                area.headings[k[along]]
                + np.pi * self.rng.integers(0, 2, m)
                + self.rng.normal(0.0, math.radians(init.heading_sigma_deg), m)
            )
        self._set_particles(np.column_stack([xy, yaw]))
        self.converged = False

    def start_at(self, pose_xyyaw, n: int | None = None) -> None:
        """Pose tracking: ``n`` particles around a known start pose."""
        p = self.settings.particles
        n = int(n or p.tracking_count)
        x0 = np.asarray(pose_xyyaw, np.float64).reshape(3)
        if not np.isfinite(x0).all():
            raise InputError(f"initial pose must be finite, got {x0}")
        if self.map.tile_at(x0[0], x0[1]) < 0:
            raise InputError(
                f"initial pose ({x0[0]:.1f}, {x0[1]:.1f}) lies outside the map's tiles "
                f"(extent x {self.map.extent[0]:.0f}..{self.map.extent[3]:.0f}, "
                f"y {self.map.extent[1]:.0f}..{self.map.extent[4]:.0f}): is the map in the sequence's frame?"
            )
        s = np.array([p.tracking_sigma_xy_m, p.tracking_sigma_xy_m, math.radians(p.tracking_sigma_yaw_deg)])
        parts = x0 + self.rng.normal(0.0, 1.0, (n, 3)) * s
        parts[:, 2] = wrap_angle(parts[:, 2])
        self._set_particles(parts)
        self.converged = True
        self.last_estimate = x0.copy()

    def _set_particles(self, particles: np.ndarray) -> None:
        self.particles = np.asarray(particles, np.float64)
        self.log_w = np.zeros(len(self.particles))
        self.pending = np.zeros(3)
        self._best_history.clear()
        self._bad_updates = 0
        self.last_estimate = pose_estimate(
            self.particles, self.weights, self.settings.particles.estimate_best_share
        )

    @property
    def weights(self) -> np.ndarray:
        return normalize_log_weights(self.log_w) if len(self.log_w) else self.log_w

    def estimate(self) -> np.ndarray:
        """Current pose estimate ``(x, y, yaw)``: the last update's estimate moved by the odometry since."""
        return se2_compose(self.last_estimate, self.pending)

    # --- one frame ---------------------------------------------------------------------------------------

    def step(
        self,
        odometry_delta,
        points: np.ndarray | None,
        *,
        fire_time_s: np.ndarray | None = None,
        frame_period_s: float | None = None,
        roll_pitch: tuple[float, float] | None = None,
    ) -> StepInfo:
        """One LiDAR frame: ``odometry_delta`` ``(dx, dy, dyaw)`` is the car's motion since the previous
        frame in the previous frame's pose; ``points`` the scan ``(M, 3)`` in the sensor frame (None or
        empty: predict only)."""
        if len(self.particles) == 0:
            raise InputError("the filter has no particles: call spread() or start_at() first")
        t0 = time.perf_counter()
        delta = np.asarray(odometry_delta, np.float64).reshape(3)
        if not np.isfinite(delta).all():
            raise InputError(f"odometry increment must be finite, got {delta}")
        self.pending = se2_compose(self.pending, delta)
        m = self.settings.motion
        due = math.hypot(self.pending[0], self.pending[1]) >= m.update_distance_m or abs(
            self.pending[2]
        ) >= math.radians(m.update_angle_deg)
        info = dict(
            updated=False, resampled=False, skipped_scan=False, best_residual_m=math.nan, recovered=False
        )
        if due:
            rays = None
            if points is not None and len(points):
                rays = prepare_rays(
                    points,
                    self.settings.observation,
                    self.rng,
                    fire_time_s=fire_time_s,
                    frame_period_s=frame_period_s,
                    frame_motion=delta,
                    roll_pitch=roll_pitch,
                )
            self._move()
            if rays is None:
                info["skipped_scan"] = True
            else:
                info.update(self._weigh(rays))
        w = self.weights
        return StepInfo(
            estimate=self.estimate(),
            particles=len(self.particles),
            converged=self.converged,
            neff=effective_sample_size(w),
            seconds=time.perf_counter() - t0,
            **info,
        )

    def _move(self) -> None:
        increment = odometry_increment(np.zeros(3), self.pending)
        self.particles = sample_motion(self.particles, increment, self.noise, self.rng)
        self.last_estimate = se2_compose(self.last_estimate, self.pending)
        self.pending = np.zeros(3)

    def sensor_z(self, xy: np.ndarray) -> np.ndarray:
        """The sensor's world z over each ``(x, y)``: the map's ground there plus the mounting height."""
        return self.map.ground.height_at(xy[:, 0], xy[:, 1]) + self.sensor_height_m

    def residuals(self, rays: ScanRays, particles: np.ndarray | None = None) -> np.ndarray:
        """Mean residual ``d`` of Eq. 5 of each particle (default: the filter's) for these rays."""
        p = self.particles if particles is None else np.asarray(particles, np.float64)
        self.model.set_scan(rays.directions, rays.ranges)
        return self.model.mean_residuals(p, self.sensor_z(p[:, :2])).astype(np.float64)

    def _weigh(self, rays: ScanRays) -> dict:
        loglik, bad = self.scorer.score(rays, self.particles, self.sensor_z(self.particles[:, :2]))
        self.log_w = self.log_w + loglik
        best = float(bad.min())
        out = dict(updated=True, resampled=False, best_residual_m=best, skipped_scan=False, recovered=False)
        ps = self.settings.particles
        w = self.weights
        self.last_estimate = pose_estimate(self.particles, w, ps.estimate_best_share)
        if self.converged and self._lost(best):
            self.recoveries += 1
            self.spread(self._spread_count_for_recovery())
            out["recovered"] = True
            return out
        n = len(self.particles)
        if not self.converged and self._is_converged():
            self._resample(w, min(ps.converged_count, n))
            self.converged = True
            out["resampled"] = True
        elif effective_sample_size(w) < ps.resample_neff_ratio * n:
            self._resample(w, n)
            out["resampled"] = True
        if self.converged:
            self.converged_updates += 1
        return out

    def _spread_count_for_recovery(self) -> int:
        return max(self._spread_count, self.settings.particles.global_count)

    def _resample(self, w: np.ndarray, n: int) -> None:
        ps = self.settings.particles
        idx = low_variance_resample(w, self.rng, n)
        parts = self.particles[idx].copy()
        sxy, syaw = (
            (ps.jitter_xy_m, ps.jitter_yaw_deg)
            if self.converged
            else (ps.global_jitter_xy_m, ps.global_jitter_yaw_deg)
        )
        if sxy > 0 or syaw > 0:
            parts[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
            parts[:, 2] = wrap_angle(parts[:, 2] + self.rng.normal(0.0, math.radians(syaw), n))
        self.particles = parts
        self.log_w = np.zeros(n)

    def _is_converged(self) -> bool:
        c = self.settings.convergence
        est = self.last_estimate
        dist = np.hypot(self.particles[:, 0] - est[0], self.particles[:, 1] - est[1])
        r95 = float(np.quantile(dist, 0.95))
        if r95 <= c.compact_radius_m:
            return True
        tiles = np.unique(self.map.tile_at(self.particles[:, 0], self.particles[:, 1]))
        return len(tiles) <= c.tiles and r95 <= c.max_radius_m

    def _lost(self, best: float) -> bool:
        r = self.settings.recovery
        if not r.enabled:
            return False
        hist = self._best_history
        floor = self.scorer.lost_floor if r.min_residual_m is None else r.min_residual_m
        if len(hist) >= min(5, r.history):
            limit = max(floor, r.factor * float(np.median(hist)))
        else:  # just converged: no history yet, so judge against the floor (with some room)
            limit = 1.5 * floor
        if best > limit:
            self._bad_updates += 1
        else:
            self._bad_updates = 0
            hist.append(best)
            del hist[: -r.history]
        return self._bad_updates >= r.updates


# ---------------------------------------------------------------------------------------------- drivable area


@dataclass
class DrivableArea:
    """Where global localization spreads particles: lower-left corners ``(K, 2)`` of square cells of
    ``cell_m``, and the mapping drive's heading near each cell (None without a drive)."""

    corners: np.ndarray
    cell_m: float
    headings: np.ndarray | None


def drivable_cells(mesh_map: MeshMap, settings: InitSettings) -> DrivableArea:
    """The map's measured ground cells, and of those only the ones within ``drive_radius_m`` of the
    mapping drive when the map keeps its drive (``drive_xy``), with the drive's heading there."""
    g = mesh_map.ground
    j, i = np.nonzero(g.measured)
    if len(i) == 0:
        raise InputError("map: no ground cell was measured, so there is no area to spread particles over")
    corners = g.origin_xy + np.column_stack([i, j]) * g.cell_m
    drive = mesh_map.drive_xy
    if drive is None or len(drive) < 2 or settings.drive_radius_m <= 0:
        return DrivableArea(corners, float(g.cell_m), None)
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(drive).query(corners + 0.5 * g.cell_m)
    near = dist <= settings.drive_radius_m
    if not near.any():
        return DrivableArea(corners, float(g.cell_m), None)
    step = np.diff(drive, axis=0)
    seg_heading = np.arctan2(step[:, 1], step[:, 0])
    heading = seg_heading[np.minimum(nearest[near], len(seg_heading) - 1)]
    return DrivableArea(corners[near], float(g.cell_m), heading)
