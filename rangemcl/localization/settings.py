"""The localizer's settings: the YAML of ``rangemcl localize --config``, one dataclass per part of the
filter, checked by :meth:`LocalizerSettings.check`. The defaults live here and only here: the filter's
parts are made from these classes by :mod:`rangemcl.localization.factory`, and their constructors take
every setting as a required argument (``tests/rangemcl/localization/test_settings.py`` checks both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rangemcl.errors import InputError
from rangemcl.localization.scan_prep import RAY_SAMPLINGS

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
    global_jitter_xy_m: float = 0.05  # roughening before convergence (lets clusters explore; 0.2 m and
    global_jitter_yaw_deg: float = 0.25  # 2 degrees before revision 14, whose polish explores instead:
    # a copy roughened by 2 degrees falls off the likelihood's peak, tools/likelihood_peak.py)
    estimate_best_share: float = 0.8  # estimate = weighted mean of the best 80 %


@dataclass
class MotionSettings:
    update_distance_m: float = 0.2  # weight only after the car moved this far ...
    update_angle_deg: float = 5.0  # ... or turned this much
    rot_per_rot: float = 0.05  # odometry motion model noise (Thrun et al. alpha1..alpha4)
    rot_per_trans: float = 0.005
    trans_per_trans: float = 0.05
    trans_per_rot: float = 0.05
    odometry_scale: float = 1.0  # the odometry's translation scale as known (the calibration starts here)
    gyro_bias_deg_s: float = 0.0  # the gyro's yaw-rate bias as known (subtracted; the calibration's start)
    calibrate_scale: bool = True  # estimate the scale online (rangemcl.localization.calibration) ...
    calibrate_gyro_bias: bool = True  # ... and the gyro's bias
    calibration_window_m: float = 100.0  # the scale estimate's memory (metres driven)
    calibration_window_s: float = 300.0  # the bias estimate's memory (seconds)
    calibration_prior_m: float = 3.0  # weight of the configured scale, as metres of evidence
    calibration_prior_s: float = 0.3  # weight of the configured bias, as seconds of evidence
    calibration_settle_updates: int = 10  # updates after a convergence left out (the cloud settles)
    calibration_outlier_m: float = 0.25  # an interval whose motion disagrees with the calibrated odometry
    calibration_outlier_deg: float = 2.0  # by more than this is left out (a recovery, a refinement's jump)
    calibration_min_scale: float = 0.8  # the scale estimate (both calibrations) is kept within these
    calibration_max_scale: float = 1.25
    calibration: str = "estimator"  # estimator (a slow estimator on the filter's corrections) | particles
    # (scale and bias as extra particle state; rangemcl.localization.calibration.ParticleCalibration): ...
    calibration_sigma_scale: float = 0.03  # ... each particle's scale drawn this far around the estimate
    calibration_sigma_bias_deg_s: float = 0.5  # ... and its bias, at a convergence
    calibration_walk_scale: float = 0.001  # ... random walk of a particle's scale per sqrt(metre)
    calibration_walk_bias_deg_s: float = 0.005  # ... and of its bias per sqrt(second)


@dataclass
class ObservationSettings:
    model: str = (
        "range"  # range (paper Eq. 5) | overlap | likelihood_field | histogram (rangemcl.localization.models)
    )
    sigma_m: float = 0.25  # σ_d of Eq. 5 (paper 5.0, reference code 2.0; chosen by measurement, README)
    rays: int = 500  # measured points cast per particle (a random subset of the valid ones) ...
    ray_sampling: str = "structure"  # ... each valid point alike (points), each elevation band alike
    # (elevation: 2-degree bands of the sensor's vertical field, so that a sensor whose beams crowd the
    # road near the car still sends rays to what lies farther and higher), or structure: at most
    # ground_share of the rays from the road (points within 0.5 m of the sensor's ground), the rest from
    # what stands on it, each part evenly over the elevation bands
    ground_share: float = 0.2  # ray_sampling structure: the road's share of the rays
    tall_share: float = 0.6  # ... and of the rest (what stands on the road), the share of the points at
    # least tall_m above the ground: facades above the parked cars, which change between drives (0: all
    # structure alike, revision 8's rule)
    tall_m: float = 2.0
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
    polish_hypotheses: int = (
        16  # while searching, the heaviest this many hypotheses (a cluster's particles in
    )
    # one 30 degree sector of yaw) get a dense local search around their best particle on each scan ...
    polish_keep: int = 8  # ... whose best this many poses join the cloud (revision 14; 0: off, as before)


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
    opinion_top: int = 100  # ... those places (at least separation_m from the estimate; 30 before
    # revision 11) ...
    opinion_per_place: int = 16  # ... each with this many particles over its cell
    polish_places: int = 16  # ... then the best this many places get a second look (0: none, revision 9;
    # 8 in revision 10):
    polish_per_place: int = 48  # ... this many particles around each one's best particle ...
    polish_sigma_xy_m: float = 0.6  # ... spread this much (normal; three rounds, each with half the last
    polish_sigma_yaw_deg: float = 3.0  # ... spread) and this much in yaw (revision 10; localization.lost)
    polish_grid: bool = True  # ... or (revision 15) the search's grids instead of those random rounds: a
    # coarse one (+-2 m, +-8 deg) on every third ray, then a fine one around its best pose
    rival_first: bool = True  # the last better place (moved with the odometry) is confirmed when it is
    # still better, even where another place fits a little more (revision 15; docs/results/v15)
    doubt_opinions: bool = True  # a second opinion also at every update whose inlier share is below 0.8 of
    # its running level, not only in a suspicion or the probation (revision 10) ...
    doubt_inlier_gain: float = 0.25  # ... where a better place must gain this much of the inlier share
    opinion_inlier_gain: float = 0.15  # better: inlier share higher by this (and a lower residual)
    opinion_badness_ratio: float = 0.7  # ... or, for models without an inlier share, badness below this x
    # the filter's. Where the filter's inlier share leaves no room for the gain (above 1 - gain; the
    # MQ-8's far rays saturate it at a wrong place as at the true one), a place with as many inliers
    # (within 0.02) and a badness below this x the filter's is better as well (revision 12; None: off,
    # revisions 11 and before; docs/results/v11 and v12)
    saturated_badness_ratio: float | None = 0.75
    # a better place must also explain the recent past: its mean inlier share over the far rays of the
    # previous history_updates updates' scans (moved back along the odometry, polished like the opinion's
    # places) at least the filter's best particle's less history_margin (a street that changed since the
    # mapping drive fits the true pose badly now, not over the last updates; revision 12, 0: off;
    # docs/results/v12)
    history_updates: int = 30
    history_margin: float = 0.05
    history_min_inliers: float = 0.5  # ... asked only while the filter's best particle still fits at least
    # this share of the far rays (below it, a teleport rather than a changed street: its past would hold
    # a true new place back)
    history_in_probation: bool = True  # ... also in the probation after a convergence (revision 13 left it
    # out there: the search chose its place on those same past scans, and the past delayed a wrong
    # convergence's catch by 2 frames on town_large; revision 14 takes it again: its polished search
    # converges earlier, and the MQ-8's first one there, at the true place, was called lost 7 updates
    # later without it; docs/results/v12, v13, v14)
    history_skips_suspicion: bool = True  # ... on the scans before the current suspicion (its bad updates
    # left out; revision 15: a vehicle alongside an MQ-8 hid the far rays at the true pose for 15 updates
    # on town_medium, and over a past that held them a place 171 m off fit within 0.03 of it; v15 results)
    opinion_min_range_m: float = 5.0  # the opinion compares rays measured at least this far (a
    # vehicle alongside hid 63 % of the structure rays at 2.5 m on the town_medium suite, and a far-off
    # place fit those near rays better than the true one)
    max_vetoed_updates: int = 30  # a suspicion lasting this many updates is lost all the same
    probation_updates: int = 10  # after each convergence, a second opinion at this many updates ...
    probation_hits: int = 2  # ... lost when it finds a better place this many times in a row
    opinion_hits: int = 2  # a suspicion is lost when the second opinion finds a better place this many
    # times in a row, each where the last one moved with the odometry (within separation_m)
    opinion_max_misses: int = 2  # ... with at most this many updates without it in between
    doubt_ratio: float = 0.8  # doubt_opinions: an update is in doubt when its inlier share is below this x
    # its running level


@dataclass
class RefineSettings:
    enabled: bool = True  # align each converged update's rays to the mesh (rangemcl.localization.refine)
    iterations: int = 5  # Gauss-Newton steps, each re-casting the rays
    max_residual_m: float = 0.5  # a ray takes part when its range is within this of the map's surface
    huber_m: float = 0.1  # Huber threshold of the point-to-plane residual
    min_inliers: int = 30  # fewer rays taking part: no refinement
    min_information: float = 10.0  # directions the scan constrains less than this are left alone
    lever_m: float = 10.0  # yaw compared with translation at this distance
    min_incidence: float = 0.2  # rays meeting their surface at |cos| below this (grazing) take no part
    min_hit_height_m: float | None = 2.0  # rays hitting the map lower above the ground take no part
    # (parked cars, people: they change between drives), unless too few hit higher; None: every ray
    all_heights_updates: int = 10  # ... except in this many updates after a search declares convergence,
    # when the cloud's place along a street may still be off by decimetres that only low surfaces fix
    gate_m: float = 0.3  # a correction is taken when within this + 2 x the cloud's spread (x, y) ...
    gate_deg: float = 1.0  # ... and this + 2 x the cloud's yaw spread; else refused and counted
    weak_information: float | None = 25.0  # directions with information from min_information up to this
    # move at most weak_step_m per update (a larger step along them is left out); None: no such band
    # (revision 17; an 8-beam scan's few rays on one low surface pulled the pose 0.2 m along a street)
    weak_step_m: float = 0.1


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
    beam_prior: bool = True  # a scan with nothing in the prior's high band (the MQ-8) is matched with a
    # prior of the sensor's own top beam instead of the low band (revision 10; place_prior module)
    inject_share: float = 0.05  # while searching: fresh prior particles per update (of the cloud), at the
    inject_top: int = 30  # prior's best places for that scan ...
    inject_below_share: float = 0.9  # ... while no hypothesis holds this share of the weight (1: always;
    # revision 8: 0.9, so that a look-alike re-injected every update no longer caps the test's margin
    # once one hypothesis dominates: town_medium 24/25 against revision 7's 22/25, README)
    inject_weight: float | None = None  # the injected particles' share of the weight (None: inject_share).
    # It is the prior odds the search gives a place it has not tested yet, and while it is injected it caps
    # the sequential test: a rival re-injected every update at weight w, fitting each scan rho times as
    # well as the leader, holds about w / places / (1 - rho) of the weight (README, issue 13) ...
    inject_held: bool = True  # ... False: fresh particles go only to places the search does not hold yet
    # (no held particle within about convergence.cluster_m and 20 degrees). With 0.001 and False the cap
    # is gone from the start (configs/search_no_cap.yaml), and on town_medium the MQ-8 then converged on
    # wrong streets that its weak evidence favoured for a stretch (README); inject_below_share lifts the
    # cap only once a hypothesis dominates


@dataclass
class LocalizerSettings:
    particles: ParticleSettings = field(default_factory=ParticleSettings)
    motion: MotionSettings = field(default_factory=MotionSettings)
    observation: ObservationSettings = field(default_factory=ObservationSettings)
    convergence: ConvergenceSettings = field(default_factory=ConvergenceSettings)
    recovery: RecoverySettings = field(default_factory=RecoverySettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    init: InitSettings = field(default_factory=InitSettings)
    sensor_height_m: float | None = None  # mounting height; default: the sequence's sensor, else the map's
    # MB of the map the localizer may hold (its tiles near the particles, rangemcl.mapping.view); default:
    # the whole map when it takes under a quarter of the memory available, else that quarter
    map_memory_mb: float | None = None

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
            "recovery.opinion_hits": r.opinion_hits,
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
            "motion.odometry_scale": m.odometry_scale,
            "motion.calibration_window_m": m.calibration_window_m,
            "motion.calibration_window_s": m.calibration_window_s,
            "refine.iterations": self.refine.iterations,
            "refine.max_residual_m": self.refine.max_residual_m,
            "refine.huber_m": self.refine.huber_m,
            "refine.min_inliers": self.refine.min_inliers,
            "refine.lever_m": self.refine.lever_m,
            "motion.calibration_outlier_m": m.calibration_outlier_m,
            "motion.calibration_outlier_deg": m.calibration_outlier_deg,
            "motion.calibration_min_scale": m.calibration_min_scale,
            "recovery.doubt_ratio": r.doubt_ratio,
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
        if self.map_memory_mb is not None:
            positive["map_memory_mb"] = self.map_memory_mb
        if self.refine.min_hit_height_m is not None:
            positive["refine.min_hit_height_m"] = self.refine.min_hit_height_m
        for key, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{where}: {key} must be > 0, got {value}")
        non_negative = {
            "refine.all_heights_updates": self.refine.all_heights_updates,
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
            "convergence.polish_hypotheses": c.polish_hypotheses,
            "convergence.polish_keep": c.polish_keep,
            "convergence.separation_m": c.separation_m,
            "recovery.inlier_factor": r.inlier_factor,
            "recovery.inlier_residual_factor": r.inlier_residual_factor,
            "recovery.inlier_residual_jump": r.inlier_residual_jump,
            "recovery.opinion_inlier_gain": r.opinion_inlier_gain,
            "recovery.doubt_inlier_gain": r.doubt_inlier_gain,
            "recovery.probation_updates": r.probation_updates,
            "recovery.polish_places": r.polish_places,
            "recovery.polish_per_place": r.polish_per_place,
            "recovery.polish_sigma_xy_m": r.polish_sigma_xy_m,
            "recovery.polish_sigma_yaw_deg": r.polish_sigma_yaw_deg,
            "init.prior_yaw_sigma_deg": self.init.prior_yaw_sigma_deg,
            "motion.calibration_prior_m": m.calibration_prior_m,
            "motion.calibration_prior_s": m.calibration_prior_s,
            "motion.calibration_settle_updates": m.calibration_settle_updates,
            "motion.calibration_sigma_scale": m.calibration_sigma_scale,
            "motion.calibration_sigma_bias_deg_s": m.calibration_sigma_bias_deg_s,
            "motion.calibration_walk_scale": m.calibration_walk_scale,
            "motion.calibration_walk_bias_deg_s": m.calibration_walk_bias_deg_s,
            "refine.min_information": self.refine.min_information,
            "refine.gate_m": self.refine.gate_m,
            "refine.gate_deg": self.refine.gate_deg,
            "refine.weak_step_m": self.refine.weak_step_m,
            "refine.min_incidence": self.refine.min_incidence,
            "recovery.opinion_max_misses": r.opinion_max_misses,
        }
        for key, value in non_negative.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{where}: {key} must be >= 0, got {value}")
        if not m.calibration_max_scale >= m.calibration_min_scale:
            raise InputError(
                f"{where}: motion.calibration_max_scale must be >= motion.calibration_min_scale, got "
                f"{m.calibration_max_scale} and {m.calibration_min_scale}"
            )
        if not math.isfinite(m.gyro_bias_deg_s):
            raise InputError(f"{where}: motion.gyro_bias_deg_s must be finite, got {m.gyro_bias_deg_s}")
        if not (isinstance(r.history_updates, int) and r.history_updates >= 0):
            raise InputError(
                f"{where}: recovery.history_updates must be an integer >= 0, got {r.history_updates}"
            )
        for key in ("history_margin", "history_min_inliers"):
            if not (math.isfinite(getattr(r, key)) and 0 <= getattr(r, key) <= 1):
                raise InputError(f"{where}: recovery.{key} must be in [0, 1], got {getattr(r, key)}")
        weak = self.refine.weak_information
        if weak is not None and not (math.isfinite(weak) and weak >= self.refine.min_information):
            raise InputError(
                f"{where}: refine.weak_information must be >= refine.min_information "
                f"({self.refine.min_information}) or null, got {weak}"
            )
        sat = r.saturated_badness_ratio
        if sat is not None and not (math.isfinite(sat) and 0 < sat < 1):
            raise InputError(
                f"{where}: recovery.saturated_badness_ratio must be in (0, 1) or null, got {sat}"
            )
        for key in ("prior_share", "inject_share", "inject_below_share", "inject_weight"):
            if getattr(self.init, key) is not None and not 0 <= getattr(self.init, key) <= 1:
                raise InputError(f"{where}: init.{key} must be in [0, 1], got {getattr(self.init, key)}")
        if m.calibration not in ("estimator", "particles"):
            raise InputError(
                f"{where}: motion.calibration {m.calibration!r}: expected 'estimator' or 'particles'"
            )
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
        from rangemcl.localization.models import MODEL_NAMES

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
        if not 0 <= o.tall_share <= 1:
            raise InputError(f"{where}: observation.tall_share must be in [0, 1], got {o.tall_share}")
        if not o.tall_m > 0:
            raise InputError(f"{where}: observation.tall_m must be > 0, got {o.tall_m}")
        if o.min_range_m >= o.max_range_m:
            raise InputError(f"{where}: observation.min_range_m must be below observation.max_range_m")
