"""The Monte Carlo localizer's core: particles over ``(x, y, yaw)`` in a mesh map, one :meth:`step` per
LiDAR frame (:class:`MonteCarloLocalizer`).

1. **Predict**: the frame's odometry increment is accumulated; particles move (odometry motion model,
   noise growing with the motion) and are weighted only once the car has moved ``update_distance_m`` or
   turned ``update_angle_deg`` since the last update; between updates the estimate follows the odometry.
2. **Weigh**: a subset of the scan's points (``select_rays``: :mod:`rangemcl.localization.scan_prep`) is
   cast from every particle through the map (:mod:`rangemcl.localization.renderer`) and scored by the
   observation model (:mod:`rangemcl.localization.models`; the paper's Eq. 5 by default).
3. **Search** (global localization: :mod:`rangemcl.localization.search`): particles start uniform over
   the drivable area (:mod:`rangemcl.localization.spread`), a share of them redrawn at the first update
   where the place prior says the scan fits (:mod:`rangemcl.localization.place_prior`); the cloud is kept
   as hypotheses and convergence is declared when one has won (:mod:`rangemcl.localization.hypotheses`),
   or, with ``convergence="tiles"``, the paper's rule (all particles in ``tiles`` tiles); then
   ``converged_count`` particles are kept.
4. **Refine and calibrate** (a converged filter: :mod:`rangemcl.localization.tracking`): the update's
   rays are aligned to the mesh (:mod:`rangemcl.localization.refine`) and the cloud moved by the
   correction when it lies within the cloud's own spread (else refused and counted); the odometry's scale
   and the gyro's bias are estimated from the estimate's motion against the raw odometry's
   (:mod:`rangemcl.localization.calibration`) and applied to every later prediction.
5. **Lost** (:mod:`rangemcl.localization.recovery`): a converged filter watches its evidence and asks the
   place prior for a second opinion (:mod:`rangemcl.localization.lost`); when lost, it spreads again and
   relocalizes.

This module holds what composes them: the constructor, the spread and the start at a pose, the place
priors (loaded or rendered once, read by the search and by the second opinion), the step, the prediction,
the weighing and the estimate. The search and the lost watch are mixins of :class:`MonteCarloLocalizer`
(they rewrite or read its cloud throughout); the tracking, whose state is its own, is a part it composes
(``MonteCarloLocalizer.tracking``).

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
from rangemcl.localization.hypotheses import ConvergenceTest
from rangemcl.localization.lost import LostDetector
from rangemcl.localization.particles import (
    MotionNoise,
    effective_sample_size,
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
from rangemcl.localization.prior_search import PRIOR_SEARCH_WINDOW, PriorSearchMixin
from rangemcl.localization.recovery import RecoveryMixin
from rangemcl.localization.refine import ScanRefiner
from rangemcl.localization.renderer import PLANAR_WITHIN_DEG, PLANAR_WITHIN_M
from rangemcl.localization.scan_prep import ScanRays, lit_returns
from rangemcl.localization.search import SearchMixin
from rangemcl.localization.spread import DrivableArea, uniform_particles
from rangemcl.localization.tracking import Tracking
from rangemcl.se2 import odometry_increment, rotation_roll_pitch, se2_compose, wrap_angle


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
    challenged: int = 0  # places that the search's challenge added to the cloud at this update
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


class MonteCarloLocalizer(SearchMixin, PriorSearchMixin, RecoveryMixin):
    """Particle filter over ``(x, y, yaw)`` in a map (module docstring): the search
    (:class:`~rangemcl.localization.search.SearchMixin`) and the lost watch
    (:class:`~rangemcl.localization.recovery.RecoveryMixin`) are mixed in, the converged tracking is
    composed (:attr:`tracking`: :class:`~rangemcl.localization.tracking.Tracking`).

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
        rendering: str,
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
        prior_profile_returns: int,
        prior_skip_zero_intensity: bool,
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
        challenge_top: int,
        challenge_places: int,
        challenge_updates: int,
    ):
        if convergence not in ("hypotheses", "tiles", "prior"):
            raise InputError(f"convergence {convergence!r}: expected 'hypotheses', 'tiles' or 'prior'")
        if convergence == "prior" and getattr(mesh_map, "budgeted", False):
            # its hypotheses are born where the prior points, whose tiles a budget may not hold yet
            raise InputError(
                "convergence.method 'prior': not yet for a map held within a memory budget (--map-memory); "
                "use 'hypotheses'"
            )
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
        # the converged filter's refinement, odometry calibration and resampling
        self.tracking = Tracking(
            refiner=refiner,
            calibrator=calibrator,
            refine_gate_m=refine_gate_m,
            refine_gate_deg=refine_gate_deg,
            refine_all_heights_updates=refine_all_heights_updates,
            calibration_settle_updates=calibration_settle_updates,
            sensor_height_m=sensor_height_m,
            jitter_xy_m=jitter_xy_m,
            jitter_yaw_deg=jitter_yaw_deg,
        )
        self.map_radius_m = float(map_radius_m)  # a map within a budget: tiles this near the particles
        self._stepped = False  # a map within a budget loads its first tiles before the first frame
        self.sensor_height_m = float(sensor_height_m)
        self.update_distance_m = float(update_distance_m)
        self.update_angle = math.radians(update_angle_deg)
        self.level_with_imu = bool(level_with_imu)
        self.rendering = rendering
        self.global_count = int(global_count)
        self.converged_count = int(converged_count)
        self.tracking_count = int(tracking_count)
        self.tracking_sigma = np.array(
            [tracking_sigma_xy_m, tracking_sigma_xy_m, math.radians(tracking_sigma_yaw_deg)]
        )
        self.resample_neff_ratio = float(resample_neff_ratio)
        self.global_jitter = (float(global_jitter_xy_m), float(global_jitter_yaw_deg))
        self.estimate_best_share = float(estimate_best_share)
        self.uniform_yaw_share = float(uniform_yaw_share)
        self.heading_sigma = math.radians(heading_sigma_deg)
        self.use_prior = bool(place_prior)
        self.prior_params = prior_params or PriorParams()
        self.use_beam_prior = bool(beam_prior)
        self.prior_profile_returns = int(prior_profile_returns)
        self.prior_skip_zero_intensity = bool(prior_skip_zero_intensity)
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
        self.challenge_top = int(challenge_top)
        self.challenge_places = int(challenge_places)
        self.challenge_updates = int(challenge_updates)
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
        # the search's challenge to its leader compares places over the same store's last challenge_updates
        history = lost.history_updates + 1 + lost.max_vetoed_updates if lost is not None else 0
        challenge = self.challenge_updates + 1 if self.challenge_places > 0 and self.challenge_top > 0 else 0
        if convergence == "prior":  # a newborn hypothesis is judged over the recent scans
            challenge = max(challenge, PRIOR_SEARCH_WINDOW + 1)
        self._recent: deque | None = None
        if (lost is not None and lost.history_updates > 0) or challenge > 0:
            self._recent = deque(maxlen=max(history, challenge))
        self._since_spread = 0  # updates since the last spread: the window of the search's challenge
        self._challenges_left = 0  # probation updates left in which the converged pose is challenged
        self.hypotheses: list = []  # the search's clusters at the last update, largest share first
        # the prior search (convergence "prior"): its hypotheses start at the spread's first update, each
        # with an id (the leader's tells the test whether it kept the lead)
        self._prior_search_fresh = False
        self._hyp_ids = np.zeros(0, np.int64)
        self._next_hyp_id = 0
        self._leader_id = -1
        self._prior_slice = 0  # the prior's slice of cells that the prior search matches next
        # the prior search's rivals through the probation after its convergence (PriorSearchMixin)
        self._rivals: dict | None = None

    # --- the tracking's state, as the filter's (read by the run's summary and the tools) ------------------

    @property
    def refiner(self) -> ScanRefiner | None:
        return self.tracking.refiner

    @property
    def calibrator(self) -> OdometryCalibrator | ParticleCalibration | None:
        return self.tracking.calibrator

    @property
    def refinements(self) -> int:
        """Refinements taken ..."""
        return self.tracking.refinements

    @property
    def refused_refinements(self) -> int:
        """... and refused (outside the cloud's spread)."""
        return self.tracking.refused_refinements

    # --- the place priors (the search draws from them, the second opinion asks them) ----------------------

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
            self._adopt_prior("place prior", self.prior)
        return self.prior

    def _adopt_prior(self, what: str, prior: PlacePrior) -> None:
        """A prior just loaded: counted in a map's memory budget (which then keeps it from holding more:
        no spectra kept between matches), and told how many returns a scan's profile bin needs."""
        self._count_in_budget(what, prior.nbytes)
        if self.map.budgeted:
            prior.spectra_max_mb = 0
        prior.scan_returns = self.prior_profile_returns

    def warm_up(self, points: np.ndarray | None = None, roll_pitch=None, intensity=None) -> dict:
        """What the first frames would otherwise do on the way, done before them: for a search, the place
        prior loaded (rendered once and stored, if the map folder has none), the beam prior decided with
        ``points`` (the first scan, as the first update would decide it) and loaded (a tracking filter
        loads them when it is lost). Draws nothing from the generator and leaves the cloud as it is, so a
        run's results do not depend on it. Returns the seconds it took."""
        t0 = time.perf_counter()
        points = self._prior_points(points, intensity)
        if self.use_prior and not self.converged:  # a search's first update needs them (tracking: when lost)
            self.place_prior()
            if points is not None and len(points) and self.use_beam_prior:
                raw = self._scan_raw
                self.prior_for(self._leveller(np.asarray(points, np.float64), roll_pitch)())
                self._scan_raw = raw
        return {"prior_s": time.perf_counter() - t0}

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
            self._adopt_prior("beam place prior", self.beam_prior)
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

    # --- initialisation ---------------------------------------------------------------------------------

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
        self._since_spread = 0
        self._challenges_left = 0
        self.tracking.stop()
        self._prior_search_fresh = self.convergence == "prior"  # its hypotheses start at the first update
        self._prior_pending = self.use_prior and self.convergence != "prior"
        if self._prior_pending:
            self.place_prior()
        self.convergence_test.reset()
        self._preload()

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
        self._converge(search=False, settle=settle)
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
        self._rivals = None
        self.particles = np.asarray(particles, np.float64)
        self.log_w = np.zeros(len(self.particles))
        self.pending = np.zeros(3)
        if self.lost is not None:
            self.lost.reset()
        self._leader = None
        self.tracking.new_interval()
        self.last_estimate = pose_estimate(self.particles, self.weights, self.estimate_best_share)

    def _converge(self, search: bool, settle: bool) -> None:
        """The cloud has converged: a search's decision, or a tracking start when ``search`` is False. The
        tracking starts (``settle``: its first updates refine with every hit); after a search, the lost
        watch's probation."""
        self.converged = True
        self.tracking.start(len(self.particles), self.rng, settle=settle)
        if search:
            self._start_probation()

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
        intensity: np.ndarray | None = None,
    ) -> StepInfo:
        """One LiDAR frame: ``odometry_delta`` ``(dx, dy, dyaw)`` is the car's motion since the previous
        frame in the previous frame's pose, over ``dt_s`` seconds (needed to calibrate the gyro's bias);
        ``points`` the scan ``(M, 3)`` in the sensor frame (None or empty: predict only), ``intensity``
        its returns' ``(M,)`` (for `init.prior_skip_zero_intensity`; None: not known)."""
        if len(self.particles) == 0 and not (self.convergence == "prior" and not self.converged):
            raise InputError("the filter has no particles: call spread() or start_at() first")
        t0 = time.perf_counter()
        delta = np.asarray(odometry_delta, np.float64).reshape(3)
        if not np.isfinite(delta).all():
            raise InputError(f"odometry increment must be finite, got {delta}")
        delta = self.tracking.odometry(delta, dt_s)  # calibrated (the raw increment kept to calibrate)
        self.pending = se2_compose(self.pending, delta)
        info = dict(
            updated=False, resampled=False, skipped_scan=False, best_residual_m=math.nan, recovered=False
        )
        if self._update_due():
            rays = self._select_rays(points, delta, fire_time_s, frame_period_s, roll_pitch)
            self._move()
            self._remember(rays)  # for the second opinion's look at the past and the search's challenge
            self._since_spread += 1
            if rays is None:
                info["skipped_scan"] = True
            else:
                info.update(self._update(rays, self._prior_points(points, intensity), roll_pitch))
        info.update(self.tracking.readings())
        w = self.weights
        return StepInfo(
            estimate=self.estimate(),
            particles=len(self.particles),
            converged=self.converged,
            neff=effective_sample_size(w),
            seconds=time.perf_counter() - t0,
            **info,
        )

    def _update_due(self) -> bool:
        """The car has moved ``update_distance_m`` or turned ``update_angle_deg`` since the last update."""
        return (
            math.hypot(self.pending[0], self.pending[1]) >= self.update_distance_m
            or abs(self.pending[2]) >= self.update_angle
        )

    def _select_rays(self, points, frame_motion, fire_time_s, frame_period_s, roll_pitch) -> ScanRays | None:
        """The scan's rays for this update (None: no scan, or no valid point in it)."""
        if points is None or not len(points):
            return None
        return self.select_rays(
            points,
            self.rng,
            fire_time_s=fire_time_s,
            frame_period_s=frame_period_s,
            frame_motion=frame_motion,
            roll_pitch=roll_pitch,
            sensor_height_m=self.sensor_height_m,
        )

    def _prior_points(self, points: np.ndarray | None, intensity: np.ndarray | None) -> np.ndarray | None:
        """The scan's points that the place prior matches: with `init.prior_skip_zero_intensity`, those
        that report intensity above zero where some do (:func:`lit_returns`)."""
        if not self.prior_skip_zero_intensity or points is None or intensity is None:
            return points
        lit = lit_returns(intensity, len(points))
        return points if lit.all() else np.asarray(points)[lit]

    def _update(self, rays: ScanRays, points: np.ndarray, roll_pitch) -> dict:
        """An update with a scan (the particles have moved): the search's first draw from the place prior,
        the map's tiles near the particles (a map within a budget), the weighing (with the search's update
        or the lost watch), then a converged filter's tracking and the calibration's interval. Returns
        :class:`StepInfo` fields."""
        level = self._leveller(points, roll_pitch)
        levelled = level() if self._needs_prior() else None
        if self._prior_pending and levelled is not None:
            self._draw_initial_prior(levelled)
        self._stepped = True
        info = {}
        if self.map.budgeted:  # a map within a memory budget (rangemcl.maps.view)
            info.update(self.map.update(self.particles[:, :2], self.map_radius_m, wait=not self.converged))
        info.update(self._weigh(rays, levelled, level))
        if (
            self.converged
            and self._rivals is not None
            and not (info["recovered"] or info.get("converged_now"))
        ):
            info.update(self._rivals_update(rays, level))  # the prior search's probation
        if self.converged:
            doubtful = self.lost is not None and self.lost.doubtful
            self.particles, self.last_estimate, refined = self.tracking.update(
                rays,
                self.particles,
                self.weights,
                self.last_estimate,
                self.sensor_z,
                refine=not info["recovered"] and not doubtful,
            )
            info.update(refined)
        self.tracking.calibrate(
            self.converged, bool(info.get("recovered")), bool(info.get("converged_now")), self.last_estimate
        )
        return info

    def _leveller(self, points: np.ndarray, roll_pitch) -> Callable[[], np.ndarray]:
        """``level()``: the scan's points levelled with the IMU's roll and pitch (where that is on), made
        when the place prior is asked (the search's draws, the second opinion)."""

        def level() -> np.ndarray:
            out = np.asarray(points, np.float64).reshape(-1, 3)
            if self.use_beam_prior and self.use_prior:  # the beam prior picks its ring unlevelled
                self._scan_raw = out
            if roll_pitch is not None and self.level_with_imu:
                out = out @ rotation_roll_pitch(*roll_pitch).T
            return out

        return level

    def _move(self) -> None:
        increment = odometry_increment(np.zeros(3), self.pending)
        self._moved_m = float(math.hypot(self.pending[0], self.pending[1]))
        increment = self.tracking.increments(increment, self._moved_m, self.rng)
        self._motion = self.pending.copy()  # this update's odometry, in the previous update's pose
        self.particles = sample_motion(self.particles, increment, self.noise, self.rng)
        self.last_estimate = se2_compose(self.last_estimate, self.pending)
        self.pending = np.zeros(3)

    def _weigh(self, rays: ScanRays, levelled: np.ndarray | None = None, level=None) -> dict:
        """Weigh the cloud with the scan (while searching, its heaviest hypotheses polished first) and
        estimate; then a converged filter's lost watch (lost: spread again, and nothing more), and the
        search's update or the tracking's resampling. Returns :class:`StepInfo` fields."""
        if not self.converged and self.convergence == "prior":
            return self._prior_weigh(rays, levelled)
        z = self.sensor_z(self.particles[:, :2])
        about = self._planar_about()
        if about is None:
            loglik, bad = self.scorer.score(rays, self.particles, z)
        else:
            loglik, bad = self.scorer.score(rays, self.particles, z, about=about)
        self.log_w = self.log_w + loglik
        if not self.converged and self.convergence == "hypotheses" and self.polish_hypotheses > 0:
            loglik, bad = self._polish_hypotheses(rays, loglik, bad)
        best = float(bad.min())
        inl = self.scorer.last_inliers
        inliers = float(inl[np.argmax(loglik)]) if inl is not None and len(inl) else math.nan
        if about is not None:  # the lost watch reads the best particle rendered exactly
            j = int(np.argmax(loglik))
            _ll, exact_bad = self.scorer.score(rays, self.particles[j : j + 1], z[j : j + 1])
            best = float(exact_bad[0])
            if inl is not None and self.scorer.last_inliers is not None:
                inliers = float(self.scorer.last_inliers[0])
            self.scorer.last_inliers = inl
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
            out.update(self._watch(rays, level, best, inliers))
            if out["recovered"]:
                return out
        n = len(self.particles)
        if not self.converged:
            out.update(self._search_update(w, levelled))
        elif effective_sample_size(w) < self.resample_neff_ratio * n:
            self.particles = self.tracking.resample(self.particles, w, self.rng, n)
            self.log_w = np.zeros(n)
            out["resampled"] = True
        if self.converged:
            self.converged_updates += 1
        return out

    def _prior_weigh(self, rays: ScanRays, levelled: np.ndarray | None) -> dict:
        """A searching update of the prior search (:mod:`rangemcl.localization.prior_search`)."""
        if self._prior_search_fresh:  # the spread's cloud gives way to the prior's places
            self._prior_search_reset()
            self._prior_search_fresh = False
        out = dict(
            updated=True,
            resampled=False,
            best_residual_m=math.nan,
            skipped_scan=False,
            recovered=False,
            inliers=math.nan,
        )
        out.update(self._prior_search_update(rays, levelled))
        if self.converged:
            self.converged_updates += 1
        return out

    def _planar_about(self) -> np.ndarray | None:
        """The pose a converged cloud is rendered about (``observation.rendering: planar``):
        ``(x, y, yaw, sensor_z)`` of the estimate, when every particle lies within
        :data:`~rangemcl.localization.renderer.PLANAR_WITHIN_M` and ``PLANAR_WITHIN_DEG`` of it; else None
        (rendered exactly)."""
        if not self.converged or self.rendering != "planar" or not len(self.particles):
            return None
        est = self.last_estimate
        p = self.particles
        if float(np.max(np.hypot(p[:, 0] - est[0], p[:, 1] - est[1]))) > PLANAR_WITHIN_M:
            return None
        if float(np.max(np.abs(wrap_angle(p[:, 2] - est[2])))) > math.radians(PLANAR_WITHIN_DEG):
            return None
        return np.array([est[0], est[1], est[2], float(self.sensor_z(est[None, :2])[0])])

    def sensor_z(self, xy: np.ndarray) -> np.ndarray:
        """The sensor's world z over each ``(x, y)``: the map's ground there plus the mounting height."""
        return self.map.ground.height_at(xy[:, 0], xy[:, 1]) + self.sensor_height_m

    def residuals(self, rays: ScanRays, particles: np.ndarray | None = None) -> np.ndarray:
        """Mean residual ``d`` of Eq. 5 of each particle (default: the filter's) for these rays."""
        p = self.particles if particles is None else np.asarray(particles, np.float64)
        change_top = getattr(self.scorer, "change_top_z", None)
        self.model.set_scan(
            rays.directions,
            rays.ranges,
            structure=rays.structure,
            change_top_z=change_top(rays) if change_top is not None else None,
        )
        return self.model.mean_residuals(p, self.sensor_z(p[:, :2])).astype(np.float64)
