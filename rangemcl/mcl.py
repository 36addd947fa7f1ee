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
from rangemcl.localization.hypotheses import (
    ConvergenceTest,
    cluster_labels,
    kld_sample_size,
    occupied_bins,
    resample_by_cluster,
    summarize,
)
from rangemcl.localization.lost import Opinion, SignalWatch, candidate_particles, second_opinion
from rangemcl.localization.place_prior import PlacePrior, PriorParams, load_or_build
from rangemcl.localization.scan_prep import (
    RAY_SAMPLINGS,
    ScanRays,
    select_rays,
)
from rangemcl.mapping.meshmap import MeshMap
from rangemcl.observation import ObservationModel
from rangemcl.particles import (
    MotionNoise,
    effective_sample_size,
    low_variance_resample,
    normalize_log_weights,
    pose_estimate,
    sample_motion,
)
from rangemcl.raycast import RayCaster
from rangemcl.se2 import (  # noqa: F401 - rotation_roll_pitch, se2_between: re-exported
    odometry_increment,
    rotation_roll_pitch,
    se2_between,
    se2_compose,
    wrap_angle,
)

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
    ray_sampling: str = "structure"  # ... each valid point alike (points), each elevation band alike
    # (elevation: 2-degree bands of the sensor's vertical field, so that a sensor whose beams crowd the
    # road near the car still sends rays to what lies farther and higher), or structure: at most
    # ground_share of the rays from the road (points within 0.5 m of the sensor's ground), the rest from
    # what stands on it, each part evenly over the elevation bands
    ground_share: float = 0.2  # ray_sampling structure: the road's share of the rays
    margin_m: float = 2.0  # rays end at measured range + margin; a miss counts as the margin
    cap_m: float | None = 1.0  # residual cap (the robust variant); None: the paper's plain mean
    cap_beyond_m: float | None = 0.5  # cost of a ray measured more than cap_m longer than the map's
    # surface (it passed where the map holds a removed object: weak evidence against the pose); None: cap_m
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
    method: str = "hypotheses"  # hypotheses (rangemcl.localization.hypotheses) | tiles (the paper's)
    tiles: int = 1  # tiles: converged when all particles lie in this many tiles ...
    max_radius_m: float = 10.0  # ... and 95 % of them within this radius of the estimate;
    compact_radius_m: float = 5.0  # a cloud this compact counts as converged across a tile border; also
    # hypotheses: the winner's 95 % weight radius must be within this
    cluster_m: float = 3.0  # hypotheses: particles in touching cells of this size form one cluster
    margin_nats: float = 6.0  # ... the leader's log weight share must beat the best rival's by this
    separation_m: float = 5.0  # (a rival: a cluster farther than this from the leader) ...
    min_inliers: float = 0.6  # ... and its best particle's inlier share must reach this (it fits at all)
    min_distance_m: float = 8.0  # ... having led over this much driving
    min_cluster_particles: int = 20  # every surviving cluster keeps at least this many particles
    prune_nats: float = 15.0  # clusters this far below the leader are dropped
    max_clusters: int = 150  # at most this many clusters are kept (the largest shares)
    kld_epsilon: float = 0.05  # KLD-sampling bound while searching (Fox 2003) ...
    kld_bin_xy_m: float = 2.0  # ... on bins of this size ...
    kld_bin_yaw_deg: float = 15.0
    min_search_particles: int = 1000  # ... but never fewer than this while searching


@dataclass
class RecoverySettings:
    enabled: bool = True
    signal: str = "inliers"  # inliers: lost when even the best particle's inlier share (rays within
    # 0.3 m of the map among those not measured beyond it) falls below inlier_factor × its running median;
    # residual: when the best mean residual rises (the settings below)
    inlier_factor: float = 0.5
    inlier_residual_factor: float = 0.75  # ... or below this × its median while the best residual is
    inlier_residual_jump: float = 3.0  # ... above this × its own median
    min_residual_m: float | None = None  # lost when the best particle's badness exceeds this (None: the
    # model's floor, 0.3 m for the range model) ...
    factor: float = 2.0  # ... and this many times its median over the recent converged updates ...
    updates: int = 5  # ... for this many updates in a row
    history: int = 50  # converged updates remembered for the median
    second_opinion: bool = True  # a suspicion is lost only when the place prior's best places for the
    # scan (rangemcl.localization.lost) hold one that explains it clearly better; else it is vetoed
    opinion_top: int = 30  # ... those places (at least separation_m from the estimate) ...
    opinion_per_place: int = 16  # ... each with this many particles over its cell
    opinion_inlier_gain: float = 0.15  # better: inlier share higher by this (and a lower residual)
    opinion_badness_ratio: float = 0.7  # ... or, for models without an inlier share, badness below this x
    opinion_min_range_m: float = 5.0  # the opinion compares rays measured at least this far (a van or a
    # bus alongside hides half the scan at 2-4 m and fits any wall: measured on the town_medium suite)
    max_vetoed_updates: int = 30  # a suspicion lasting this many updates is lost all the same
    probation_updates: int = 10  # after each convergence, a second opinion at this many updates ...
    probation_hits: int = 2  # ... lost when it finds a better place this many times in a row


@dataclass
class InitSettings:
    drive_radius_m: float = 6.0  # with a map that keeps its mapping drive: spread within this of it
    heading_sigma_deg: float = 15.0  # ... with yaw along the drive (either way) within this
    uniform_yaw_share: float = 0.25  # share of particles with uniform yaw all the same
    place_prior: bool = True  # draw particles from the place prior (rangemcl.localization.place_prior)
    prior_share: float = 0.7  # share of a global spread drawn from the prior's best places (the rest
    # uniform over the drivable area, so that no place is excluded)
    prior_top: int = 300  # the prior's best (cell, yaw) candidates drawn from (at most 2 % of its cells)
    prior_cell_m: float = 2.0  # the prior's grid
    prior_yaw_sigma_deg: float = 2.0  # yaw spread around a candidate's aligned yaw
    inject_share: float = 0.05  # while searching: fresh prior particles per update (of the cloud), at the
    inject_top: int = 30  # prior's best places for that scan ...
    inject_below_share: float = 1.0  # ... while no hypothesis holds this share of the weight (1: always)


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
            "recovery.opinion_top": r.opinion_top,
            "recovery.opinion_per_place": r.opinion_per_place,
            "recovery.max_vetoed_updates": r.max_vetoed_updates,
            "recovery.probation_hits": r.probation_hits,
            "recovery.opinion_badness_ratio": r.opinion_badness_ratio,
            "recovery.opinion_min_range_m": r.opinion_min_range_m,
            "convergence.cluster_m": c.cluster_m,
            "convergence.min_cluster_particles": c.min_cluster_particles,
            "convergence.max_clusters": c.max_clusters,
            "convergence.kld_epsilon": c.kld_epsilon,
            "convergence.kld_bin_xy_m": c.kld_bin_xy_m,
            "convergence.kld_bin_yaw_deg": c.kld_bin_yaw_deg,
            "convergence.min_search_particles": c.min_search_particles,
            "init.prior_top": self.init.prior_top,
            "init.prior_cell_m": self.init.prior_cell_m,
            "init.inject_top": self.init.inject_top,
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
        if o.cap_beyond_m is not None:
            positive["observation.cap_beyond_m"] = o.cap_beyond_m
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
            "convergence.margin_nats": c.margin_nats,
            "convergence.min_distance_m": c.min_distance_m,
            "convergence.prune_nats": c.prune_nats,
            "convergence.separation_m": c.separation_m,
            "recovery.inlier_factor": r.inlier_factor,
            "recovery.inlier_residual_factor": r.inlier_residual_factor,
            "recovery.inlier_residual_jump": r.inlier_residual_jump,
            "recovery.opinion_inlier_gain": r.opinion_inlier_gain,
            "recovery.probation_updates": r.probation_updates,
            "init.prior_yaw_sigma_deg": self.init.prior_yaw_sigma_deg,
        }
        for key, value in non_negative.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{where}: {key} must be >= 0, got {value}")
        for key in ("prior_share", "inject_share", "inject_below_share"):
            if not 0 <= getattr(self.init, key) <= 1:
                raise InputError(f"{where}: init.{key} must be in [0, 1], got {getattr(self.init, key)}")
        if c.method not in ("hypotheses", "tiles"):
            raise InputError(f"{where}: convergence.method {c.method!r}: expected 'hypotheses' or 'tiles'")
        if r.signal not in ("inliers", "residual"):
            raise InputError(f"{where}: recovery.signal {r.signal!r}: expected 'inliers' or 'residual'")
        if not 0 <= c.min_inliers <= 1:
            raise InputError(f"{where}: convergence.min_inliers must be in [0, 1], got {c.min_inliers}")
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
        if o.ray_sampling not in RAY_SAMPLINGS:
            raise InputError(
                f"{where}: observation.ray_sampling {o.ray_sampling!r}: "
                f"expected one of {', '.join(RAY_SAMPLINGS)}"
            )
        if not 0 <= o.ground_share <= 1:
            raise InputError(f"{where}: observation.ground_share must be in [0, 1], got {o.ground_share}")
        if o.min_range_m >= o.max_range_m:
            raise InputError(f"{where}: observation.min_range_m must be below observation.max_range_m")


# ---------------------------------------------------------------------------------------------- scan rays


def prepare_rays(
    points: np.ndarray,
    settings: ObservationSettings,
    rng: np.random.Generator,
    *,
    fire_time_s: np.ndarray | None = None,
    frame_period_s: float | None = None,
    frame_motion: np.ndarray | None = None,
    roll_pitch: tuple[float, float] | None = None,
    sensor_height_m: float = 1.73,
) -> ScanRays | None:
    """:func:`rangemcl.localization.scan_prep.select_rays` with the observation settings' values."""
    o = settings
    return select_rays(
        points,
        rng,
        rays=o.rays,
        sampling=o.ray_sampling,
        ground_share=o.ground_share,
        min_range_m=o.min_range_m,
        max_range_m=o.max_range_m,
        deskew=o.deskew,
        level_with_imu=o.level_with_imu,
        fire_time_s=fire_time_s,
        frame_period_s=frame_period_s,
        frame_motion=frame_motion,
        roll_pitch=roll_pitch,
        sensor_height_m=sensor_height_m,
    )


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
    hypotheses: int = 0  # clusters while searching (0 once converged or without an update)
    evidence_nats: float = math.nan  # the leader's log weight share over the runner-up's (searching)
    inliers: float = math.nan  # the best particle's inlier share (models that report it)
    converged_now: bool = False  # convergence was declared at this update
    vetoed: bool = False  # a lost suspicion at this update was vetoed by the second opinion


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
        c = self.settings.convergence
        self.convergence_test = ConvergenceTest(
            c.margin_nats, c.min_distance_m, c.compact_radius_m, c.separation_m
        )
        self.prior: PlacePrior | None = None
        self.prior_source = ""
        self.particles = np.zeros((0, 3))
        self.log_w = np.zeros(0)
        self.converged = False
        self.converged_updates = 0
        self.pending = np.zeros(3)  # odometry since the last update, in the pose at that update
        self.last_estimate = np.zeros(3)
        self.recoveries = 0
        r = self.settings.recovery
        self.watch = SignalWatch(
            signal=r.signal,
            inlier_factor=r.inlier_factor,
            inlier_residual_factor=r.inlier_residual_factor,
            inlier_residual_jump=r.inlier_residual_jump,
            residual_factor=r.factor,
            floor=self.scorer.lost_floor if r.min_residual_m is None else r.min_residual_m,
            updates=r.updates,
            history=r.history,
        )
        self.vetoed_alarms = 0  # lost suspicions that the second opinion vetoed (episodes)
        self._probation = 0  # updates left in which each update gets a second opinion
        self._probation_hits = 0
        self._spread_count = self.settings.particles.global_count
        self._prior_pending = False  # a global spread waits for a scan to draw from the prior
        self._leader: np.ndarray | None = None  # per particle: descends from the last leading cluster
        self._moved_m = 0.0
        self.hypotheses: list = []  # the search's clusters at the last update, largest share first

    # --- initialisation ---------------------------------------------------------------------------------

    def place_prior(self) -> PlacePrior:
        """The map's place prior (loaded from the map folder, else rendered once and stored there)."""
        if self.prior is None:
            i = self.settings.init
            area = self.init_cells
            self.prior, self.prior_source = load_or_build(
                self.map, self.caster, area.corners, area.cell_m, PriorParams(cell_m=i.prior_cell_m)
            )
        return self.prior

    def spread(self, n: int | None = None) -> None:
        """Global localization: ``n`` particles uniform over the drivable area; yaw along the mapping
        drive (either way) where the map keeps it, with a share of uniform yaw, else uniform. With the
        place prior on, a share of them is redrawn at the first update from the places that match that
        scan (:mod:`rangemcl.localization.place_prior`)."""
        n = int(n or self.settings.particles.global_count)
        self._spread_count = n
        self._set_particles(self._uniform(n))
        self.converged = False
        self._prior_pending = self.settings.init.place_prior
        if self._prior_pending:
            self.place_prior()
        self.convergence_test.reset()

    def _uniform(self, n: int) -> np.ndarray:
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
        return np.column_stack([xy, yaw])

    def _from_prior(self, n: int, levelled_points: np.ndarray, top: int | None = None) -> np.ndarray | None:
        """``n`` particles around the prior's ``top`` best places for this scan (default ``prior_top``,
        at most 2 % of the map's cells); None when the scan has too few points in the prior's height band
        to compare."""
        i = self.settings.init
        prior = self.place_prior()
        top = min(top or i.prior_top, max(20, len(prior.xy) // 50))
        xy, yaw, _cost, known = prior.candidates(levelled_points, self.sensor_height_m, top)
        if known < max(8, prior.params.bins // 20) or n <= 0:
            return None
        k = self.rng.integers(0, len(xy), n)
        half = 0.5 * prior.params.cell_m
        out = np.empty((n, 3))
        out[:, :2] = xy[k] + self.rng.uniform(-half, half, (n, 2))
        out[:, 2] = wrap_angle(yaw[k] + self.rng.normal(0.0, math.radians(i.prior_yaw_sigma_deg), n))
        return out

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
        self._prior_pending = False
        self.last_estimate = x0.copy()

    def _set_particles(self, particles: np.ndarray) -> None:
        self.particles = np.asarray(particles, np.float64)
        self.log_w = np.zeros(len(self.particles))
        self.pending = np.zeros(3)
        self.watch.reset()
        self._probation = 0
        self._probation_hits = 0
        self._leader = None
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
                    sensor_height_m=self.sensor_height_m,
                )
            self._move()
            if rays is None:
                info["skipped_scan"] = True
            else:

                def level() -> np.ndarray:
                    out = np.asarray(points, np.float64).reshape(-1, 3)
                    if roll_pitch is not None and self.settings.observation.level_with_imu:
                        out = out @ rotation_roll_pitch(*roll_pitch).T
                    return out

                levelled = level() if self._needs_prior() else None
                if self._prior_pending and levelled is not None:
                    self._draw_initial_prior(levelled)
                info.update(self._weigh(rays, levelled, level))
        w = self.weights
        return StepInfo(
            estimate=self.estimate(),
            particles=len(self.particles),
            converged=self.converged,
            neff=effective_sample_size(w),
            seconds=time.perf_counter() - t0,
            **info,
        )

    def _needs_prior(self) -> bool:
        return self.settings.init.place_prior and not self.converged

    def _draw_initial_prior(self, levelled: np.ndarray) -> None:
        n = len(self.particles)
        k = int(round(self.settings.init.prior_share * n))
        drawn = self._from_prior(k, levelled)
        if drawn is None:
            return  # too little in the scan to compare: stay uniform, try again at the next update
        self.particles[self.rng.choice(n, k, replace=False)] = drawn
        self.log_w = np.zeros(n)
        self._prior_pending = False

    def _move(self) -> None:
        increment = odometry_increment(np.zeros(3), self.pending)
        self._moved_m = float(math.hypot(self.pending[0], self.pending[1]))
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

    def _weigh(self, rays: ScanRays, levelled: np.ndarray | None = None, level=None) -> dict:
        loglik, bad = self.scorer.score(rays, self.particles, self.sensor_z(self.particles[:, :2]))
        self.log_w = self.log_w + loglik
        best = float(bad.min())
        inl = self.scorer.last_inliers
        inliers = float(inl[np.argmax(loglik)]) if inl is not None and len(inl) else math.nan
        out = dict(
            updated=True,
            resampled=False,
            best_residual_m=best,
            skipped_scan=False,
            recovered=False,
            inliers=inliers,
        )
        ps = self.settings.particles
        w = self.weights
        self.last_estimate = pose_estimate(self.particles, w, ps.estimate_best_share)
        if self.converged and self._lost(rays, best, inliers, level, out):
            self.recoveries += 1
            self.spread(self._spread_count_for_recovery())
            out["recovered"] = True
            return out
        n = len(self.particles)
        if not self.converged:
            if self.settings.convergence.method == "hypotheses":
                out.update(self._search_update(w, levelled))
            elif self._is_converged():
                self._resample(w, min(ps.converged_count, n))
                self.converged = True
                self._start_probation()
                out.update(resampled=True, converged_now=True)
            elif effective_sample_size(w) < ps.resample_neff_ratio * n:
                self._resample(w, n)
                out["resampled"] = True
        elif effective_sample_size(w) < ps.resample_neff_ratio * n:
            self._resample(w, n)
            out["resampled"] = True
        if self.converged:
            self.converged_updates += 1
        return out

    def _search_update(self, w: np.ndarray, levelled: np.ndarray | None) -> dict:
        """One update of the hypothesis search (:mod:`rangemcl.localization.hypotheses`): cluster,
        test for a winner, else resample cluster by cluster to the KLD size and inject prior particles."""
        c = self.settings.convergence
        ps = self.settings.particles
        labels, count = cluster_labels(self.particles[:, :2], c.cluster_m)
        hyps = summarize(self.particles, w, labels, count)
        self.hypotheses = hyps
        best = hyps[0]
        same = False
        if self._leader is not None and len(self._leader) == len(labels):
            same = bool(self._leader[labels == best.label].mean() >= 0.5)
        won = self.convergence_test.update(hyps, same, self._moved_m)
        inl = self.scorer.last_inliers
        if won and inl is not None and len(inl) == len(labels):
            # the winner must also fit: a place that merely fits less badly than the rest has not won
            won = float(inl[labels == best.label].max()) >= c.min_inliers
        margin = self.convergence_test.margin
        out = dict(resampled=True, hypotheses=len(hyps), evidence_nats=margin)
        self.last_estimate = best.centroid.copy()  # while searching, the leading hypothesis
        if won:
            inside = np.flatnonzero(labels == best.label)
            wi = w[inside] / w[inside].sum()
            self.particles = self.particles[inside]
            self._resample(wi, ps.converged_count)
            self.converged = True
            self._leader = None
            self.last_estimate = pose_estimate(self.particles, self.weights, ps.estimate_best_share)
            self._start_probation()
            out["converged_now"] = True
            return out
        keep = [h for h in hyps if h.log_share >= best.log_share - c.prune_nats][: c.max_clusters]
        provisional = self.particles[low_variance_resample(w, self.rng, len(w))]
        size = kld_sample_size(occupied_bins(provisional, c.kld_bin_xy_m, c.kld_bin_yaw_deg), c.kld_epsilon)
        size = int(np.clip(size, c.min_search_particles, max(self._spread_count, c.min_search_particles)))
        parts, logw, origin = resample_by_cluster(
            self.particles, w, labels, keep, size, c.min_cluster_particles, self.rng
        )
        n = len(parts)
        sxy, syaw = ps.global_jitter_xy_m, math.radians(ps.global_jitter_yaw_deg)
        parts[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
        parts[:, 2] = wrap_angle(parts[:, 2] + self.rng.normal(0.0, syaw, n))
        leader = origin == 0
        i = self.settings.init
        if (
            i.place_prior
            and levelled is not None
            and best.share <= i.inject_below_share
            and i.inject_share > 0
        ):
            k = max(1, int(round(i.inject_share * n)))
            fresh = self._from_prior(k, levelled, i.inject_top)
            if fresh is not None:
                parts = np.vstack([parts, fresh])
                logw = np.concatenate(
                    [logw + math.log(1.0 - i.inject_share), np.full(k, math.log(i.inject_share / k))]
                )
                leader = np.concatenate([leader, np.zeros(k, bool)])
        self.particles, self.log_w, self._leader = parts, logw, leader
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

    def _start_probation(self) -> None:
        self._probation = self.settings.recovery.probation_updates
        self._probation_hits = 0

    def _lost(self, rays: ScanRays, best: float, inliers: float, level, out: dict) -> bool:
        """Lost when the evidence watch (:class:`rangemcl.localization.lost.SignalWatch`) has been bad for
        ``recovery.updates`` updates in a row *and* the second opinion finds a place that explains the scan
        clearly better (else the suspicion is vetoed: the world changed, the place did not), or when a
        suspicion outlasts ``max_vetoed_updates``; or, in the probation after a convergence, when the
        second opinion finds a better place ``probation_hits`` times in a row. Without the place prior
        (or with ``second_opinion`` off), the watch alone decides, as before issue 13's second opinion."""
        r = self.settings.recovery
        if not r.enabled:
            return False
        suspicious = self.watch.update(best, inliers)
        probation = self._probation > 0
        self._probation = max(0, self._probation - 1)
        if not (suspicious or probation):
            self._probation_hits = 0
            return False
        if not (r.second_opinion and self.settings.init.place_prior and level is not None):
            return suspicious
        opinion = self._second_opinion(rays, level())
        if not suspicious:
            self._probation_hits = self._probation_hits + 1 if opinion is not None and opinion.better else 0
            return self._probation_hits >= r.probation_hits
        if opinion is None or opinion.better or self.watch.bad_updates >= r.max_vetoed_updates:
            return True
        if self.watch.bad_updates == r.updates:
            self.vetoed_alarms += 1
        out["vetoed"] = True
        return False

    def _second_opinion(self, rays: ScanRays, levelled: np.ndarray) -> Opinion | None:
        """:func:`rangemcl.localization.lost.second_opinion` on the prior's best places for this scan,
        with the rays measured at least ``opinion_min_range_m`` away (near objects, vehicles alongside
        above all, fit any wall); the filter's own cloud is scored on the same rays. ``None`` when the
        scan has too little in the prior's height band, or too few far rays, to compare."""
        r = self.settings.recovery
        far = rays.ranges >= r.opinion_min_range_m
        if far.sum() < max(20, 0.1 * len(far)):
            return None
        sub = ScanRays(
            rays.directions[far],
            rays.ranges[far],
            rays.valid_points,
            None if rays.structure is None else rays.structure[far],
        )
        prior = self.place_prior()
        xy, yaw, _cost, known = prior.candidates(levelled, self.sensor_height_m, r.opinion_top)
        if known < max(8, prior.params.bins // 20):
            return None
        cand = candidate_particles(
            xy,
            yaw,
            r.opinion_per_place,
            prior.params.cell_m,
            math.radians(self.settings.init.prior_yaw_sigma_deg),
            self.rng,
        )

        def score(p: np.ndarray):
            _loglik, bad = self.scorer.score(sub, p, self.sensor_z(p[:, :2]))
            return bad, self.scorer.last_inliers

        own_bad, own_inl = score(self.particles)
        j = int(np.argmin(own_bad))
        return second_opinion(
            score,
            self.last_estimate,
            float(own_bad[j]),
            float(own_inl[j]) if own_inl is not None else math.nan,
            cand,
            min_distance_m=self.settings.convergence.separation_m,
            inlier_gain=r.opinion_inlier_gain,
            badness_ratio=r.opinion_badness_ratio,
        )


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
