"""The Monte Carlo localizer's core: particles over ``(x, y, yaw)`` in a mesh map, one :meth:`step` per
LiDAR frame (:class:`MonteCarloLocalizer`).

1. **Predict**: the frame's odometry increment is accumulated; particles move (odometry motion model,
   noise growing with the motion) and are weighted only once the car has moved ``update_distance_m`` or
   turned ``update_angle_deg`` since the last update; between updates the estimate follows the odometry.
2. **Weigh**: a subset of the scan's points (``select_rays``: :mod:`rangemcl.localization.scan_prep`) is
   cast from every particle through the map (:mod:`rangemcl.localization.renderer`) and scored by the
   observation model (:mod:`rangemcl.localization.models`; the paper's Eq. 5 by default).
3. **Search** (global localization): particles start uniform over the drivable area
   (:mod:`rangemcl.localization.spread`), a share of them redrawn at the first update where the place
   prior says the scan fits (:mod:`rangemcl.localization.place_prior`); the cloud is kept as hypotheses
   and convergence is declared when one has won (:mod:`rangemcl.localization.hypotheses`), or, with
   ``convergence="tiles"``, the paper's rule (all particles in ``tiles`` tiles); then ``converged_count``
   particles are kept.
4. **Refine and calibrate** (a converged filter): the update's rays are aligned to the mesh
   (:mod:`rangemcl.localization.refine`) and the cloud moved by the correction when it lies within the
   cloud's own spread (else refused and counted); the odometry's scale and the gyro's bias are estimated
   from the estimate's motion against the raw odometry's (:mod:`rangemcl.localization.calibration`) and
   applied to every later prediction.
5. **Lost**: a converged filter watches its evidence and asks the place prior for a second opinion
   (:mod:`rangemcl.localization.lost`); when lost, it spreads again and relocalizes.

The constructor takes plain values and the parts it composes (observation model, ray selection, drivable
area, lost detector); :func:`rangemcl.localization.factory.build_localizer` makes them from the YAML
settings (:class:`rangemcl.localization.settings.LocalizerSettings`). All
randomness comes from the generator handed in.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError
from rangemcl.localization.calibration import OdometryCalibrator, ParticleCalibration
from rangemcl.localization.hypotheses import (
    ConvergenceTest,
    cluster_labels,
    kld_sample_size,
    occupied_bins,
    resample_by_cluster,
    summarize,
)
from rangemcl.localization.lost import (
    LostDetector,
    Opinion,
    Polish,
    candidate_particles,
    history_fit,
    second_opinion,
)
from rangemcl.localization.particles import (
    MotionNoise,
    effective_sample_size,
    low_variance_resample,
    normalize_log_weights,
    pose_estimate,
    sample_motion,
)
from rangemcl.localization.place_prior import (
    PlacePrior,
    PriorParams,
    beam_params,
    elevations_deg,
    load_or_build,
    scan_profile,
    top_beam_deg,
)
from rangemcl.localization.refine import ScanRefiner
from rangemcl.localization.scan_prep import ScanRays
from rangemcl.localization.spread import DrivableArea, uniform_particles
from rangemcl.se2 import odometry_increment, rotation_roll_pitch, se2_compose, se2_inverse, wrap_angle

# the search's polish of its heaviest hypotheses (MonteCarloLocalizer._polish_hypotheses): a coarse grid
# (half width and step in metres along and across the seed's heading, then in degrees of yaw) and a fine
# one around the coarse grid's best pose
POLISH_COARSE = (2.0, 0.5, 8.0, 2.0)
POLISH_FINE = (0.4, 0.2, 1.5, 0.5)
POLISH_COARSE_RAYS_EVERY = 3  # the coarse grid is scored on every third ray


def _prior_nbytes(area: DrivableArea, params: PriorParams) -> int:
    """What the place prior of ``params`` over ``area`` holds in memory (:attr:`PlacePrior.nbytes`), known
    before it is loaded or rendered."""
    from rangemcl.localization.place_prior import COARSE_FACTOR, TWO_STAGE_MIN_CELLS, grid_cells

    cells = len(grid_cells(area.corners, area.cell_m, params.cell_m))
    profiles = cells * params.rows * params.bins * np.dtype(params.dtype).itemsize
    return 16 * cells + profiles + (profiles // COARSE_FACTOR if cells >= TWO_STAGE_MIN_CELLS else 0)


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
    refined: int = 0  # scan-to-mesh refinement at this update: 1 taken, -1 refused, 0 not tried
    refine_shift_m: float = math.nan  # the refinement's correction (x, y), taken or refused
    odometry_scale: float = math.nan  # the calibration's current translation scale ...
    gyro_bias_deg_s: float = math.nan  # ... and gyro bias
    map_tiles: int = -1  # a map within a memory budget (MapView): tiles held at this update (-1: whole map)
    map_left_out: int = 0  # ... tiles wanted but left out (no room in the budget, or still loading)
    map_coarse: int = 0  # ... tiles held at the coarse level (no room for them at full resolution)
    map_mb: float = math.nan  # ... MB the held tiles take
    map_load_ms: float = math.nan  # ... milliseconds this update waited for tiles to load


class MonteCarloLocalizer:
    """Particle filter over ``(x, y, yaw)`` in a map (module docstring).

    Args:
        mesh_map: the map (its ground grid gives each particle's height; its tiles the paper's rule).
        scorer: the observation model (:func:`rangemcl.localization.models.make_model`), bound to ``caster``.
        caster: the :class:`~rangemcl.raycast.RayCaster` holding the map.
        residual_model: the Eq. 5 kernel :meth:`residuals` reports (the range model's own, or one alike).
        select_rays: ``(points, rng, *, fire_time_s, frame_period_s, frame_motion, roll_pitch,
            sensor_height_m) -> ScanRays | None``: the scan's rays for one update.
        area: where global localization spreads (:func:`rangemcl.localization.spread.drivable_cells`).
        noise: the odometry motion model's noise.
        lost: the lost detector; None: never lost (the paper's filter).
        refiner: scan-to-mesh refinement of a converged filter's pose; None: none (the paper's filter).
        calibrator: the odometry's calibration (applied to every increment; estimated online where it
            is set to); None: the odometry as it comes.
        rng: the run's generator.
        sensor_height_m: the sensor's height above the ground.
        The keyword values: see :class:`rangemcl.localization.settings.LocalizerSettings`, which
            documents each.
    """

    def __init__(
        self,
        mesh_map,
        scorer,
        *,
        caster,
        residual_model,
        select_rays: Callable[..., ScanRays | None],
        area: DrivableArea,
        noise: MotionNoise,
        lost: LostDetector | None,
        rng: np.random.Generator,
        refiner: ScanRefiner | None,
        calibrator: OdometryCalibrator | ParticleCalibration | None,
        refine_gate_m: float,
        refine_gate_deg: float,
        refine_all_heights_updates: int,
        calibration_settle_updates: int,
        map_radius_m: float,
        sensor_height_m: float,
        # motion and scan
        update_distance_m: float,
        update_angle_deg: float,
        level_with_imu: bool,
        # particles
        global_count: int,
        converged_count: int,
        tracking_count: int,
        tracking_sigma_xy_m: float,
        tracking_sigma_yaw_deg: float,
        resample_neff_ratio: float,
        jitter_xy_m: float,
        jitter_yaw_deg: float,
        global_jitter_xy_m: float,
        global_jitter_yaw_deg: float,
        estimate_best_share: float,
        # the spread and the place prior
        uniform_yaw_share: float,
        heading_sigma_deg: float,
        place_prior: bool,
        prior_params: PriorParams | None,
        beam_prior: bool,
        prior_share: float,
        prior_top: int,
        prior_yaw_sigma_deg: float,
        inject_share: float,
        inject_top: int,
        inject_below_share: float,
        # convergence
        convergence: str,
        tiles: int,
        max_radius_m: float,
        compact_radius_m: float,
        cluster_m: float,
        margin_nats: float,
        separation_m: float,
        min_inliers: float,
        min_distance_m: float,
        min_cluster_particles: int,
        prune_nats: float,
        max_clusters: int,
        kld_epsilon: float,
        kld_bin_xy_m: float,
        kld_bin_yaw_deg: float,
        min_search_particles: int,
        polish_hypotheses: int,
        polish_keep: int,
    ):
        if convergence not in ("hypotheses", "tiles"):
            raise InputError(f"convergence {convergence!r}: expected 'hypotheses' or 'tiles'")
        self.map = mesh_map
        self.scorer = scorer
        self.caster = caster
        self.model = residual_model
        self.select_rays = select_rays
        self.init_cells = area
        self._count_in_budget("drivable area", area.corners.nbytes + getattr(area.headings, "nbytes", 0))
        self.noise = noise
        self.lost = lost
        self.rng = rng
        self.refiner = refiner
        self.calibrator = calibrator
        self.refine_gate = (float(refine_gate_m), math.radians(refine_gate_deg))
        self.refine_all_heights_updates = int(refine_all_heights_updates)
        self.map_radius_m = float(map_radius_m)  # a map within a budget: tiles this near the particles
        self._stepped = False  # a map within a budget loads its first tiles before the first frame
        self.calibration_settle_updates = int(calibration_settle_updates)
        self.sensor_height_m = float(sensor_height_m)
        self.update_distance_m = float(update_distance_m)
        self.update_angle = math.radians(update_angle_deg)
        self.level_with_imu = bool(level_with_imu)
        self.global_count = int(global_count)
        self.converged_count = int(converged_count)
        self.tracking_count = int(tracking_count)
        self.tracking_sigma = np.array(
            [tracking_sigma_xy_m, tracking_sigma_xy_m, math.radians(tracking_sigma_yaw_deg)]
        )
        self.resample_neff_ratio = float(resample_neff_ratio)
        self.jitter = (float(jitter_xy_m), float(jitter_yaw_deg))
        self.global_jitter = (float(global_jitter_xy_m), float(global_jitter_yaw_deg))
        self.estimate_best_share = float(estimate_best_share)
        self.uniform_yaw_share = float(uniform_yaw_share)
        self.heading_sigma = math.radians(heading_sigma_deg)
        self.use_prior = bool(place_prior)
        self.prior_params = prior_params or PriorParams()
        self.use_beam_prior = bool(beam_prior)
        self.prior_share = float(prior_share)
        self.prior_top = int(prior_top)
        self.prior_yaw_sigma = math.radians(prior_yaw_sigma_deg)
        self.inject_share = float(inject_share)
        self.inject_top = int(inject_top)
        self.inject_below_share = float(inject_below_share)
        self.convergence = convergence
        self.tiles = int(tiles)
        self.max_radius_m = float(max_radius_m)
        self.compact_radius_m = float(compact_radius_m)
        self.cluster_m = float(cluster_m)
        self.min_inliers = float(min_inliers)
        self.separation_m = float(separation_m)
        self.min_cluster_particles = int(min_cluster_particles)
        self.prune_nats = float(prune_nats)
        self.max_clusters = int(max_clusters)
        self.kld_epsilon = float(kld_epsilon)
        self.kld_bin = (float(kld_bin_xy_m), float(kld_bin_yaw_deg))
        self.min_search_particles = int(min_search_particles)
        self.polish_hypotheses = int(polish_hypotheses)
        self.polish_keep = int(polish_keep)
        self.convergence_test = ConvergenceTest(margin_nats, min_distance_m, compact_radius_m, separation_m)

        self.prior: PlacePrior | None = None
        self.prior_source = ""
        self.beam_prior: PlacePrior | None = None  # the sensor's own top beam (scans with no high band)
        self.beam_prior_source = ""
        self._beam_checked = False  # the top beam was looked for (once per run)
        # a prior not stored in the map folder is rendered at the first search: prior_notify(message) is
        # told so before it starts; prior_fallback_dir holds it when the map folder is not writable
        self.prior_notify = None
        self.prior_fallback_dir = None
        self._scan_raw: np.ndarray | None = None  # the scan being weighed, unlevelled (for the beam prior)
        self.particles = np.zeros((0, 3))
        self.log_w = np.zeros(0)
        self.converged = False
        self.converged_updates = 0
        self.pending = np.zeros(3)  # odometry since the last update, in the pose at that update
        self.last_estimate = np.zeros(3)
        self.recoveries = 0
        self._spread_count = self.global_count
        self._prior_pending = False  # a global spread waits for a scan to draw from the prior
        self._leader: np.ndarray | None = None  # per particle: descends from the last leading cluster
        self._moved_m = 0.0
        self._motion = np.zeros(3)
        # the recent updates' rays (None: no scan) and odometry since the update before, oldest first, for
        # the second opinion's look at the past (LostDetector.history_updates; None when that is off),
        # and before them as many as a suspicion may last (max_vetoed_updates), whose scans it leaves out
        keep = lost is not None and lost.history_updates > 0
        self._recent: deque | None = None
        if keep:
            self._recent = deque(maxlen=lost.history_updates + 1 + lost.max_vetoed_updates)
        self.hypotheses: list = []  # the search's clusters at the last update, largest share first
        self.refinements = 0  # refinements taken ...
        self.refused_refinements = 0  # ... and refused (outside the cloud's spread)
        self._calib_ref: np.ndarray | None = None  # estimate at the last converged update
        self._settled = 0  # updates since the last convergence (or tracking start)
        self._since_search = -1  # updates since the search declared convergence (-1: tracking start)
        self._raw_since_ref = np.zeros(3)  # raw odometry since then (in that pose) ...
        self._dt_since_ref = 0.0  # ... and the time it took (NaN: a frame without a time)
        self._dt_pending = 0.0  # seconds of the odometry not yet applied to the particles

    @property
    def vetoed_alarms(self) -> int:
        """Lost suspicions that the second opinion vetoed (episodes)."""
        return self.lost.vetoed_alarms if self.lost is not None else 0

    # --- initialisation ---------------------------------------------------------------------------------

    def place_prior(self) -> PlacePrior:
        """The map's place prior (loaded from the map folder, else rendered once and stored there)."""
        if self.prior is None:
            area = self.init_cells
            self.prior, self.prior_source = load_or_build(
                self.map,
                self.caster,
                area.corners,
                area.cell_m,
                self.prior_params,
                notify=self.prior_notify,
                fallback_dir=self.prior_fallback_dir,
            )
            self._count_in_budget("place prior", self.prior.nbytes)
        return self.prior

    def prior_for(self, levelled_points: np.ndarray, raw_points: np.ndarray | None = None) -> PlacePrior:
        """The prior a scan is matched with: the band prior, unless the scan has nothing in its high band
        (a sensor that sees nothing above the parked cars: all its beams below the horizon) and
        ``beam_prior`` is on:
        then the prior of the sensor's own top beam (decided at the first scan matched, which also gives
        the beam's elevation, for the rest of the run; loaded from the map folder or rendered there once:
        :func:`rangemcl.localization.place_prior.beam_params`). ``raw_points``: the scan before levelling
        (default: the scan being weighed)."""
        prior = self.place_prior()
        if not self.use_beam_prior:
            return prior
        if self.beam_prior is None:
            if self._beam_checked:  # decided once per run, at the first scan matched
                return prior
            self._beam_checked = True
            p = prior.params
            _prof, known = scan_profile(levelled_points, self.sensor_height_m, p)
            if known[1].sum() >= p.min_known_share * p.bins:
                return prior
            raw = self._scan_raw if raw_points is None else raw_points
            if raw is None or len(raw) != len(levelled_points):
                return prior
            top = top_beam_deg(raw, p.min_range_m)
            if top is None or top >= 0.0:  # a beam at or above the horizon: the bands see what it sees
                return prior
            area = self.init_cells
            params = beam_params(p, top, self.sensor_height_m)
            self.beam_prior, self.beam_prior_source = load_or_build(
                self.map,
                self.caster,
                area.corners,
                area.cell_m,
                params,
                notify=self.prior_notify,
                fallback_dir=self.prior_fallback_dir,
            )
            self._count_in_budget("beam place prior", self.beam_prior.nbytes)
        return self.beam_prior

    def _elevations(self, prior: PlacePrior, levelled_points: np.ndarray) -> np.ndarray | None:
        """For a beam prior, the scan's elevations in the sensor's frame (the points before levelling)."""
        if prior.params.beam_deg is None or self._scan_raw is None:
            return None
        if len(self._scan_raw) != len(levelled_points):
            return None
        return elevations_deg(self._scan_raw)

    def _count_in_budget(self, what: str, nbytes: int) -> None:
        """A map held within a memory budget (``rangemcl.maps.view.MapView``) counts what the filter
        derives from it against that budget; a whole map has no budget."""
        if self.map.budgeted:
            self.map.reserve(what, nbytes)

    def spread(self, n: int | None = None) -> None:
        """Global localization: ``n`` particles uniform over the drivable area; yaw along the mapping
        drive (either way) where the map keeps it, with a share of uniform yaw, else uniform. With the
        place prior on, a share of them is redrawn at the first update from the places that match that
        scan (:mod:`rangemcl.localization.place_prior`)."""
        n = int(n or self.global_count)
        self._check_budget(search=True)  # before the place prior is loaded or rendered
        self._spread_count = n
        self._set_particles(
            uniform_particles(
                self.init_cells,
                n,
                self.rng,
                uniform_yaw_share=self.uniform_yaw_share,
                heading_sigma_rad=self.heading_sigma,
            )
        )
        self.converged = False
        if self._state_calibration():
            self.calibrator.stop()
        self._prior_pending = self.use_prior
        if self._prior_pending:
            self.place_prior()
        self.convergence_test.reset()
        self._preload()

    def _from_prior(self, n: int, levelled_points: np.ndarray, top: int | None = None) -> np.ndarray | None:
        """``n`` particles around the prior's ``top`` best places for this scan (default ``prior_top``,
        at most 2 % of the map's cells); None when the scan has too few points in the prior's height band
        to compare."""
        prior = self.prior_for(levelled_points)
        top = min(top or self.prior_top, max(20, len(prior.xy) // 50))
        xy, yaw, _cost, known = prior.candidates(
            levelled_points, self.sensor_height_m, top, self._elevations(prior, levelled_points)
        )
        if known < max(8, prior.params.bins // 20) or n <= 0:
            return None
        k = self.rng.integers(0, len(xy), n)
        half = 0.5 * prior.params.cell_m
        out = np.empty((n, 3))
        out[:, :2] = xy[k] + self.rng.uniform(-half, half, (n, 2))
        out[:, 2] = wrap_angle(yaw[k] + self.rng.normal(0.0, self.prior_yaw_sigma, n))
        return out

    def start_at(self, pose_xyyaw, n: int | None = None, *, settle: bool = False) -> None:
        """Pose tracking: ``n`` particles around a known start pose. ``settle``: the pose is only
        approximate (a GNSS fix, a hand-placed pose), so the first updates refine with every hit, as after a
        search's convergence (``refine_all_heights_updates``)."""
        n = int(n or self.tracking_count)
        x0 = np.asarray(pose_xyyaw, np.float64).reshape(3)
        if not np.isfinite(x0).all():
            raise InputError(f"initial pose must be finite, got {x0}")
        if self.map.tile_at(x0[0], x0[1]) < 0:
            raise InputError(
                f"initial pose ({x0[0]:.1f}, {x0[1]:.1f}) lies outside the map's tiles "
                f"(extent x {self.map.extent[0]:.0f}..{self.map.extent[3]:.0f}, "
                f"y {self.map.extent[1]:.0f}..{self.map.extent[4]:.0f}): is the map in the sequence's frame?"
            )
        parts = x0 + self.rng.normal(0.0, 1.0, (n, 3)) * self.tracking_sigma
        parts[:, 2] = wrap_angle(parts[:, 2])
        self._set_particles(parts)
        self._converge(search=False)
        self._since_search = 0 if settle else -1
        self._prior_pending = False
        self.last_estimate = x0.copy()
        self._check_budget(search=False)
        self._preload()

    def _check_budget(self, search: bool) -> None:
        """Before the first frame, a map within a memory budget is checked against all the run needs
        (:meth:`rangemcl.maps.view.MapView.check_budget`), the place priors it may load later included:
        the band prior of a search (now, or after the lost detector re-spreads the particles; its second
        opinion reads it too) and the beam prior a scan with nothing in the high band asks for. A budget
        short of it is refused in one line now, not frames later."""
        if not self.map.budgeted or self._stepped:
            return
        expected = {}
        if self.use_prior and (search or self.lost is not None):
            expected["place prior"] = _prior_nbytes(self.init_cells, self.prior_params)
            if self.use_beam_prior:  # (its size does not depend on the beam's elevation)
                beam = beam_params(self.prior_params, -10.0, self.sensor_height_m)
                expected["beam place prior"] = _prior_nbytes(self.init_cells, beam)
        self.map.check_budget(expected)

    def _preload(self) -> None:
        """Before the first frame, a map within a memory budget loads the tiles that the particles need
        (the start-up of the run, as a map held whole is read before it), so that no frame waits for them."""
        if not self._stepped and self.map.budgeted:
            self.map.preload(self.particles[:, :2], self.map_radius_m)

    def _set_particles(self, particles: np.ndarray) -> None:
        self.particles = np.asarray(particles, np.float64)
        self.log_w = np.zeros(len(self.particles))
        self.pending = np.zeros(3)
        if self.lost is not None:
            self.lost.reset()
        self._leader = None
        self._calib_ref = None
        self._raw_since_ref = np.zeros(3)
        self._dt_since_ref = 0.0
        self.last_estimate = pose_estimate(self.particles, self.weights, self.estimate_best_share)

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
        dt_s: float | None = None,
    ) -> StepInfo:
        """One LiDAR frame: ``odometry_delta`` ``(dx, dy, dyaw)`` is the car's motion since the previous
        frame in the previous frame's pose, over ``dt_s`` seconds (needed to calibrate the gyro's bias);
        ``points`` the scan ``(M, 3)`` in the sensor frame (None or empty: predict only)."""
        if len(self.particles) == 0:
            raise InputError("the filter has no particles: call spread() or start_at() first")
        t0 = time.perf_counter()
        delta = np.asarray(odometry_delta, np.float64).reshape(3)
        if not np.isfinite(delta).all():
            raise InputError(f"odometry increment must be finite, got {delta}")
        self._raw_since_ref = se2_compose(self._raw_since_ref, delta)
        self._dt_since_ref += dt_s if dt_s is not None else math.nan
        self._dt_pending += dt_s if dt_s is not None else math.nan
        if self.calibrator is not None:
            delta = self.calibrator.correct(delta, dt_s)
        self.pending = se2_compose(self.pending, delta)
        due = (
            math.hypot(self.pending[0], self.pending[1]) >= self.update_distance_m
            or abs(self.pending[2]) >= self.update_angle
        )
        info = dict(
            updated=False, resampled=False, skipped_scan=False, best_residual_m=math.nan, recovered=False
        )
        if due:
            rays = None
            if points is not None and len(points):
                rays = self.select_rays(
                    points,
                    self.rng,
                    fire_time_s=fire_time_s,
                    frame_period_s=frame_period_s,
                    frame_motion=delta,
                    roll_pitch=roll_pitch,
                    sensor_height_m=self.sensor_height_m,
                )
            self._move()
            if self._recent is not None:
                self._recent.append((rays, self._motion.copy()))
            if rays is None:
                info["skipped_scan"] = True
            else:

                def level() -> np.ndarray:
                    out = np.asarray(points, np.float64).reshape(-1, 3)
                    if self.use_beam_prior and self.use_prior:  # the beam prior picks its ring unlevelled
                        self._scan_raw = out
                    if roll_pitch is not None and self.level_with_imu:
                        out = out @ rotation_roll_pitch(*roll_pitch).T
                    return out

                levelled = level() if self._needs_prior() else None
                if self._prior_pending and levelled is not None:
                    self._draw_initial_prior(levelled)
                self._stepped = True
                if self.map.budgeted:  # a map within a memory budget (rangemcl.maps.view)
                    info.update(
                        self.map.update(self.particles[:, :2], self.map_radius_m, wait=not self.converged)
                    )
                info.update(self._weigh(rays, levelled, level))
                if self.converged and self._state_calibration():
                    self.calibrator.weighted(self.weights)
                if (
                    self.converged
                    and self.refiner is not None
                    and not info["recovered"]
                    and not (self.lost is not None and self.lost.doubtful)
                ):
                    info.update(self._refine(rays))
                if self.converged and self._since_search >= 0:
                    self._since_search += 1
                self._calibrate(info)
        if self.calibrator is not None:
            info.update(
                odometry_scale=self.calibrator.scale,
                gyro_bias_deg_s=math.degrees(self.calibrator.gyro_bias),
            )
        w = self.weights
        return StepInfo(
            estimate=self.estimate(),
            particles=len(self.particles),
            converged=self.converged,
            neff=effective_sample_size(w),
            seconds=time.perf_counter() - t0,
            **info,
        )

    def _refine(self, rays: ScanRays) -> dict:
        """Align the update's rays to the mesh from the estimate (:mod:`rangemcl.localization.refine`);
        take the correction (the whole cloud moves by it) when it lies within the cloud's own spread."""
        est = self.last_estimate
        sensor_z = float(self.sensor_z(est[None, :2])[0])
        # just after a search declared convergence the cloud's place along a street may still be off by
        # decimetres that the facades do not constrain: the lowest metres (kerbs, parked cars) take part
        all_heights = 0 <= self._since_search < self.refine_all_heights_updates
        ref = self.refiner.refine(
            rays.directions,
            rays.ranges,
            est,
            sensor_z,
            ground_z=None if all_heights else sensor_z - self.sensor_height_m,
        )
        if ref is None:
            return {}
        w = self.weights
        spread_xy = math.sqrt(
            float(np.sum(w * ((self.particles[:, 0] - est[0]) ** 2 + (self.particles[:, 1] - est[1]) ** 2)))
        )
        spread_yaw = math.sqrt(float(np.sum(w * wrap_angle(self.particles[:, 2] - est[2]) ** 2)))
        shift = math.hypot(ref.correction[0], ref.correction[1])
        if (
            shift > self.refine_gate[0] + 2.0 * spread_xy
            or abs(ref.correction[2]) > self.refine_gate[1] + 2.0 * spread_yaw
        ):
            self.refused_refinements += 1
            return dict(refined=-1, refine_shift_m=shift)
        self.particles = self.particles + ref.correction
        self.particles[:, 2] = wrap_angle(self.particles[:, 2])
        self.last_estimate = ref.pose.copy()
        self.refinements += 1
        return dict(refined=1, refine_shift_m=shift)

    def _calibrate(self, info: dict) -> None:
        """After a weighted update: the interval since the last converged update feeds the odometry's
        calibration (:mod:`rangemcl.localization.calibration`); a search, a recovery or a convergence
        starts a new interval instead, and the first ``calibration_settle_updates`` after a convergence
        (while the cloud settles on its place) are left out."""
        if self.calibrator is None:
            return
        steady = self.converged and not info.get("recovered") and not info.get("converged_now")
        self._settled = self._settled + 1 if steady else 0
        if steady and self._calib_ref is not None and self._settled > self.calibration_settle_updates:
            dt = self._dt_since_ref if math.isfinite(self._dt_since_ref) else None
            self.calibrator.observe(self._raw_since_ref, dt, self._calib_ref, self.last_estimate)
        self._calib_ref = self.last_estimate.copy() if self.converged and not info.get("recovered") else None
        self._raw_since_ref = np.zeros(3)
        self._dt_since_ref = 0.0

    def _needs_prior(self) -> bool:
        return self.use_prior and not self.converged

    def _draw_initial_prior(self, levelled: np.ndarray) -> None:
        n = len(self.particles)
        k = int(round(self.prior_share * n))
        drawn = self._from_prior(k, levelled)
        if drawn is None:
            return  # too little in the scan to compare: stay uniform, try again at the next update
        self.particles[self.rng.choice(n, k, replace=False)] = drawn
        self.log_w = np.zeros(n)
        self._prior_pending = False

    def _move(self) -> None:
        increment = odometry_increment(np.zeros(3), self.pending)
        self._moved_m = float(math.hypot(self.pending[0], self.pending[1]))
        if self._state_calibration() and self.calibrator.state is not None:
            increment = self.calibrator.increments(increment, self._dt_pending, self._moved_m, self.rng)
        self._dt_pending = 0.0
        self._motion = self.pending.copy()  # this update's odometry, in the previous update's pose
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
        if not self.converged and self.convergence == "hypotheses" and self.polish_hypotheses > 0:
            loglik, bad = self._polish_hypotheses(rays, loglik, bad)
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
        w = self.weights
        self.last_estimate = pose_estimate(self.particles, w, self.estimate_best_share)
        if self.converged and self.lost is not None:
            opinion = (
                (lambda rival, gain: self._second_opinion(rays, level(), rival, gain))
                if self.use_prior and level is not None
                else None
            )
            lost, out["vetoed"] = self.lost.update(best, inliers, opinion, self._motion)
            if lost:
                self.recoveries += 1
                self.spread(max(self._spread_count, self.global_count))
                out["recovered"] = True
                return out
        n = len(self.particles)
        if not self.converged:
            if self.convergence == "hypotheses":
                out.update(self._search_update(w, levelled))
            elif self._tiles_converged():
                self._resample(w, min(self.converged_count, n))
                self._converge(search=True)
                out.update(resampled=True, converged_now=True)
            elif effective_sample_size(w) < self.resample_neff_ratio * n:
                self._resample(w, n)
                out["resampled"] = True
        elif effective_sample_size(w) < self.resample_neff_ratio * n:
            self._resample(w, n)
            out["resampled"] = True
        if self.converged:
            self.converged_updates += 1
        return out

    def _grid_search(self, rays: ScanRays, seeds: np.ndarray, grid: tuple[float, float, float, float]):
        """Each seed ``(x, y, yaw)`` scored over a grid of poses in its own frame (forward, left, yaw):
        ``grid`` = ``(half_m, step_m, half_deg, step_deg)``. Returns the poses ``(K, G, 3)``, their
        log-likelihoods, badness and inlier shares ``(K, G)`` (inliers None for models without them)."""
        half_m, step_m, half_deg, step_deg = grid
        ax = np.arange(-half_m, half_m + 1e-9, step_m)
        ay = np.radians(np.arange(-half_deg, half_deg + 1e-9, step_deg))
        g = np.array(np.meshgrid(ax, ax, ay, indexing="ij")).reshape(3, -1).T
        c, s = np.cos(seeds[:, 2])[:, None], np.sin(seeds[:, 2])[:, None]
        p = np.empty((len(seeds), len(g), 3))
        p[:, :, 0] = seeds[:, None, 0] + c * g[None, :, 0] - s * g[None, :, 1]
        p[:, :, 1] = seeds[:, None, 1] + s * g[None, :, 0] + c * g[None, :, 1]
        p[:, :, 2] = wrap_angle(seeds[:, None, 2] + g[None, :, 2])
        flat = p.reshape(-1, 3)
        ll, bad = self.scorer.score(rays, flat, self.sensor_z(flat[:, :2]))
        inl = self.scorer.last_inliers
        shape = (len(seeds), len(g))
        return p, ll.reshape(shape), bad.reshape(shape), None if inl is None else inl.reshape(shape)

    def _grid_look(self, rays: ScanRays, seeds: np.ndarray):
        """The second opinion's look around its best places: each seed's coarse grid
        (:data:`POLISH_COARSE`, every third ray), then the fine grid (:data:`POLISH_FINE`) around its most
        likely pose; returns the fine grids' poses ``(M, 3)``, badness and inlier shares ``(M,)`` (the
        search's polish, :meth:`_polish_hypotheses`, on the opinion's rays)."""
        seeds = np.asarray(seeds, np.float64).reshape(-1, 3)
        coarse_rays = rays.subset(slice(None, None, POLISH_COARSE_RAYS_EVERY))
        p, ll, _b, _i = self._grid_search(coarse_rays, seeds, POLISH_COARSE)
        best = p[np.arange(len(seeds)), np.argmax(ll, axis=1)]
        p, _ll, bad, inl = self._grid_search(rays, best, POLISH_FINE)
        return p.reshape(-1, 3), bad.reshape(-1), None if inl is None else inl.reshape(-1)

    def _polish_hypotheses(
        self, rays: ScanRays, loglik: np.ndarray, bad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """While searching, the ``polish_hypotheses`` heaviest hypotheses (a cluster's particles within one
        30° sector of yaw) are searched around their best particle on this scan: a coarse grid
        (:data:`POLISH_COARSE`, scored on every third ray) and a fine one around its best pose
        (:data:`POLISH_FINE`, all rays); the fine grid's ``polish_keep`` best poses join the cloud. The range
        likelihood is sharp (a pose 0.2 m to the side, or a degree off, can lose about half a nat per update;
        ``tools/likelihood_peak.py`` measures it on a drive) and a hypothesis holds a few dozen particles over
        metres and degrees, so without this the true place is judged by particles off its peak, which can fit
        worse than a look-alike street's best particles for many updates. The coarse grid on a third of the
        rays keeps the cost of finding the peak's neighbourhood low; the fine grid on all rays places it. The
        seed's weight before this scan is shared among itself and the new poses, each then taking its own
        likelihood. Returns ``loglik`` and ``bad`` extended to the new poses (the clusters are found again by
        the search update: the new poses can join neighbouring ones)."""
        labels, _count = cluster_labels(self.particles[:, :2], self.cluster_m)
        sectors = 12
        sector = np.floor((self.particles[:, 2] + math.pi) / (2 * math.pi) * sectors).astype(np.int64)
        labels = labels * sectors + sector.clip(0, sectors - 1)
        lw = self.log_w
        mass = np.bincount(labels, weights=np.exp(lw - lw.max()))
        top = np.argsort(-mass, kind="stable")[: self.polish_hypotheses]
        top = top[mass[top] > 0]
        if len(top) == 0:
            return loglik, bad
        order = np.lexsort((-lw, labels))  # by hypothesis, its heaviest particle first
        seeds_idx = order[np.searchsorted(labels[order], top)]
        k = len(seeds_idx)
        inl0 = self.scorer.last_inliers
        coarse_rays = rays.subset(slice(None, None, POLISH_COARSE_RAYS_EVERY))  # a third: the cost
        p, ll, _b, _i = self._grid_search(coarse_rays, self.particles[seeds_idx], POLISH_COARSE)
        coarse_best = p[np.arange(k), np.argmax(ll, axis=1)]
        p, ll, b, inl = self._grid_search(rays, coarse_best, POLISH_FINE)
        keep = min(self.polish_keep, ll.shape[1])
        pick = np.argsort(-ll, axis=1, kind="stable")[:, :keep]
        rows = np.arange(k)[:, None]
        new, ll_new, bad_new = (
            p[rows, pick].reshape(-1, 3),
            ll[rows, pick].reshape(-1),
            b[rows, pick].reshape(-1),
        )
        origin = np.repeat(seeds_idx, keep)  # each new pose's seed
        split = math.log(keep + 1)
        lw = lw.copy()
        before = lw[origin] - loglik[origin]
        lw[seeds_idx] -= split
        n0 = len(self.particles)
        self.log_w = np.concatenate([lw, before - split + ll_new])
        self.particles = np.vstack([self.particles, new])
        if self._leader is not None and len(self._leader) == n0:
            self._leader = np.concatenate([self._leader, self._leader[origin]])
        if inl0 is not None and inl is not None:
            self.scorer.last_inliers = np.concatenate([inl0, inl[rows, pick].reshape(-1)])
        else:
            self.scorer.last_inliers = None
        return np.concatenate([loglik, ll_new]), np.concatenate([bad, bad_new])

    def _start_probation(self) -> None:
        if self.lost is not None:
            self.lost.start_probation()

    def _search_update(self, w: np.ndarray, levelled: np.ndarray | None) -> dict:
        """One update of the hypothesis search (:mod:`rangemcl.localization.hypotheses`): cluster,
        test for a winner, else resample cluster by cluster to the KLD size and inject prior particles."""
        labels, count = cluster_labels(self.particles[:, :2], self.cluster_m)
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
            won = float(inl[labels == best.label].max()) >= self.min_inliers
        margin = self.convergence_test.margin
        out = dict(resampled=True, hypotheses=len(hyps), evidence_nats=margin)
        self.last_estimate = best.centroid.copy()  # while searching, the leading hypothesis
        if won:
            inside = np.flatnonzero(labels == best.label)
            wi = w[inside] / w[inside].sum()
            self.particles = self.particles[inside]
            self._resample(wi, self.converged_count)
            self._converge(search=True)
            self._leader = None
            self.last_estimate = pose_estimate(self.particles, self.weights, self.estimate_best_share)
            out["converged_now"] = True
            return out
        keep = [h for h in hyps if h.log_share >= best.log_share - self.prune_nats][: self.max_clusters]
        provisional = self.particles[low_variance_resample(w, self.rng, len(w))]
        size = kld_sample_size(occupied_bins(provisional, *self.kld_bin), self.kld_epsilon)
        size = int(
            np.clip(size, self.min_search_particles, max(self._spread_count, self.min_search_particles))
        )
        parts, logw, origin = resample_by_cluster(
            self.particles, w, labels, keep, size, self.min_cluster_particles, self.rng
        )
        n = len(parts)
        sxy, syaw = self.global_jitter[0], math.radians(self.global_jitter[1])
        parts[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
        parts[:, 2] = wrap_angle(parts[:, 2] + self.rng.normal(0.0, syaw, n))
        leader = origin == 0
        if (
            self.use_prior
            and levelled is not None
            and best.share <= self.inject_below_share
            and self.inject_share > 0
        ):
            k = max(1, int(round(self.inject_share * n)))
            fresh = self._from_prior(k, levelled, self.inject_top)
            if fresh is not None and len(fresh):
                share = min(self.inject_share * len(fresh) / k, 1.0 - 1e-12)
                parts = np.vstack([parts, fresh])
                each = math.log(max(self.inject_share, 1e-300) / k)
                logw = np.concatenate([logw + math.log1p(-share), np.full(len(fresh), each)])
                leader = np.concatenate([leader, np.zeros(len(fresh), bool)])
        self.particles, self.log_w, self._leader = parts, logw, leader
        return out

    def _state_calibration(self) -> bool:
        return isinstance(self.calibrator, ParticleCalibration)

    def _converge(self, search: bool) -> None:
        """The cloud has converged (a search's decision, or a tracking start when ``search`` is False)."""
        self.converged = True
        if search:
            self._since_search = 0
            self._start_probation()
        if self._state_calibration():
            self.calibrator.start(len(self.particles), self.rng)

    def _resample(self, w: np.ndarray, n: int) -> None:
        idx = low_variance_resample(w, self.rng, n)
        if self.converged and self._state_calibration():
            self.calibrator.resampled(idx)
        parts = self.particles[idx].copy()
        sxy, syaw = self.jitter if self.converged else self.global_jitter
        if sxy > 0 or syaw > 0:
            parts[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
            parts[:, 2] = wrap_angle(parts[:, 2] + self.rng.normal(0.0, math.radians(syaw), n))
        self.particles = parts
        self.log_w = np.zeros(n)

    def _tiles_converged(self) -> bool:
        """The paper's rule: all particles in ``tiles`` tiles (and 95 % within ``max_radius_m``), or a
        cloud this compact (``compact_radius_m``) across a tile border."""
        est = self.last_estimate
        dist = np.hypot(self.particles[:, 0] - est[0], self.particles[:, 1] - est[1])
        r95 = float(np.quantile(dist, 0.95))
        if r95 <= self.compact_radius_m:
            return True
        tiles = np.unique(self.map.tile_at(self.particles[:, 0], self.particles[:, 1]))
        return len(tiles) <= self.tiles and r95 <= self.max_radius_m

    def _second_opinion(
        self, rays: ScanRays, levelled: np.ndarray, rival: np.ndarray | None, inlier_gain: float
    ) -> Opinion | None:
        """:func:`rangemcl.localization.lost.second_opinion` on the prior's best places for this scan,
        with the rays measured at least ``opinion_min_range_m`` away (near objects, vehicles alongside
        above all, fit any wall); the filter's own cloud is scored on the same rays. ``None`` when the
        scan has too little in the prior's height band, or too few far rays, to compare. ``rival``: a
        place scored with them (the last better place moved with the odometry, or None); ``inlier_gain``:
        what a better place must gain (:class:`rangemcl.localization.lost.LostDetector`). Over a map
        within a budget (:meth:`rangemcl.maps.view.MapView.consult`) the places whose tiles are not
        held yet are asked for and left out of this opinion."""
        lost = self.lost
        sub = self._far_rays(rays)
        if sub is None:
            return None
        prior = self.prior_for(levelled)
        xy, yaw, _cost, known = prior.candidates(
            levelled, self.sensor_height_m, lost.opinion_top, self._elevations(prior, levelled)
        )
        if known < max(8, prior.params.bins // 20):
            return None
        consult = getattr(self.map, "consult", None)  # a map within a budget: only the places held
        if consult is not None:
            far_away = np.hypot(xy[:, 0] - self.last_estimate[0], xy[:, 1] - self.last_estimate[1])
            keep = far_away > self.separation_m - 0.5 * prior.params.cell_m
            xy, yaw = xy[keep], yaw[keep]
            held = consult(xy)
            xy, yaw = xy[held], yaw[held]
            if len(xy) == 0:  # none scoreable yet (their tiles are loading): no better place found
                return Opinion(False, self.last_estimate.copy(), math.inf, math.nan, 0)
        cand = candidate_particles(
            xy, yaw, lost.opinion_per_place, prior.params.cell_m, self.prior_yaw_sigma, self.rng
        )
        polish = Polish(lost.polish_places, lost.polish_per_place, *lost.polish_sigma, self.rng)
        if rival is not None and polish.places > 0:  # the last better place, moved with the odometry
            cand = np.vstack([cand, rival[None], polish.around(rival[None])])

        def score(p: np.ndarray):
            _loglik, bad = self.scorer.score(sub, p, self.sensor_z(p[:, :2]))
            return bad, self.scorer.last_inliers

        own_bad, own_inl = score(self.particles)
        j = int(np.argmin(own_bad))
        found = second_opinion(
            score,
            self.last_estimate,
            float(own_bad[j]),
            float(own_inl[j]) if own_inl is not None else math.nan,
            cand,
            min_distance_m=self.separation_m,
            inlier_gain=inlier_gain,
            polish=polish,
            badness_ratio=lost.opinion_badness_ratio,
            saturated_ratio=lost.saturated_badness_ratio,
            look=lambda seeds: self._grid_look(sub, seeds),
            rival=rival,
            rival_m=lost.consistent_m,
        )
        if (
            found.better
            and self._recent is not None
            and own_inl is not None
            and float(own_inl[j]) >= lost.history_min_inliers
        ):
            own = self.particles[j].copy()
            rival_fit = history_fit(self._history_inliers, found.pose, polish)
            own_fit = history_fit(self._history_inliers, own, polish)
            if math.isfinite(rival_fit) and rival_fit < own_fit - lost.history_margin:
                found.better = False  # (NaN own_fit: the comparison is False, the place stays better)
        return found

    def _history_inliers(self, poses: np.ndarray) -> np.ndarray:
        """Each pose's ``(M, 3)`` mean inlier share over the far rays of the previous updates' scans (up to
        ``history_updates``), the pose moved back along the odometry to each of them; NaN with fewer than
        half of them to compare (no scan, too few far rays). The watch's current run of bad updates is
        left out: as many scans as it counts (the current update included), those of its updates and the
        one just before them, so the past is the one before the suspicion (a vehicle alongside that hides
        the far rays at the true pose for a while would otherwise let a distant place fit that past nearly
        as well)."""
        p = np.asarray(poses, np.float64).reshape(-1, 3)
        total = np.zeros(len(p))
        count = 0
        entries = list(self._recent)
        skip = self.lost.watch.bad_updates
        for i in range(len(entries) - 1, 0, -1):
            p = se2_compose(p, se2_inverse(entries[i][1]))  # the pose at the update before
            back = len(entries) - 1 - i  # updates before this one
            if back >= skip + self.lost.history_updates:
                break
            if back < skip:
                continue  # a scan of the current suspicion
            sub = None if entries[i - 1][0] is None else self._far_rays(entries[i - 1][0])
            if sub is None:
                continue
            self.scorer.score(sub, p, self.sensor_z(p[:, :2]))
            total += self.scorer.last_inliers  # (asked only of models with an inlier share)
            count += 1
        if count == 0 or count < 0.5 * self.lost.history_updates:
            return np.full(len(p), math.nan)
        return total / count

    def _far_rays(self, rays: ScanRays) -> ScanRays | None:
        """The rays measured at least ``opinion_min_range_m`` away (what the second opinion compares), or
        None when they are too few (under 20, or under a tenth of the rays)."""
        far = rays.ranges >= self.lost.opinion_min_range_m
        if far.sum() < max(20, 0.1 * len(far)):
            return None
        return rays.subset(far)
