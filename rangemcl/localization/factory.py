"""The filter and its parts made from :class:`~rangemcl.localization.settings.LocalizerSettings`: small
factories that turn settings into the plain constructor arguments of the cores (kiss-icp's ``get_*``), so
that no core sees a settings object and no constructor carries a default of its own.
"""

from __future__ import annotations

import math
from functools import partial

import numpy as np

from rangemcl.localization.calibration import OdometryCalibrator, ParticleCalibration
from rangemcl.localization.filter import MonteCarloLocalizer
from rangemcl.localization.lost import LostDetector, SignalWatch
from rangemcl.localization.particles import MotionNoise
from rangemcl.localization.place_prior import PlacePrior, PriorParams, load_or_build
from rangemcl.localization.refine import ScanRefiner
from rangemcl.localization.renderer import ParticleRenderer
from rangemcl.localization.scan_prep import ScanRays, select_rays
from rangemcl.localization.settings import (
    LocalizerSettings,
    MotionSettings,
    ObservationSettings,
    RecoverySettings,
    RefineSettings,
)
from rangemcl.localization.spread import drivable_cells
from rangemcl.maps.meshmap import MeshMap
from rangemcl.raycast import RayCaster

# ---------------------------------------------------------------------------------------------- scan rays


def ray_selector(settings: ObservationSettings):
    """:func:`rangemcl.localization.scan_prep.select_rays` with the observation settings' values bound:
    ``(points, rng, *, fire_time_s, frame_period_s, frame_motion, roll_pitch, sensor_height_m)``."""
    o = settings
    return partial(
        select_rays,
        rays=o.rays,
        sampling=o.ray_sampling,
        ground_share=o.ground_share,
        tall_share=o.tall_share,
        tall_m=o.tall_m,
        min_range_m=o.min_range_m,
        max_range_m=o.max_range_m,
        deskew=o.deskew,
        level_with_imu=o.level_with_imu,
        vehicle_length_m=o.vehicle_length_m,
        movable_height_m=o.movable_height_m,
    )


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
    """The scan's rays for one update with the observation settings (:func:`ray_selector`)."""
    return ray_selector(settings)(
        points,
        rng,
        fire_time_s=fire_time_s,
        frame_period_s=frame_period_s,
        frame_motion=frame_motion,
        roll_pitch=roll_pitch,
        sensor_height_m=sensor_height_m,
    )


def scan_refiner(caster: RayCaster, f: RefineSettings) -> ScanRefiner:
    """The scan-to-mesh refiner that ``f`` describes (``enabled`` aside), over ``caster``'s map."""
    return ScanRefiner(
        caster,
        iterations=f.iterations,
        max_residual_m=f.max_residual_m,
        huber_m=f.huber_m,
        min_inliers=f.min_inliers,
        min_information=f.min_information,
        lever_m=f.lever_m,
        min_incidence=f.min_incidence,
        min_hit_height_m=f.min_hit_height_m,
        weak_information=f.weak_information,
        weak_step_m=f.weak_step_m,
    )


def motion_noise(m: MotionSettings) -> MotionNoise:
    """The odometry motion model's noise of the motion settings."""
    return MotionNoise(m.rot_per_rot, m.rot_per_trans, m.trans_per_trans, m.trans_per_rot)


def odometry_calibrator(m: MotionSettings) -> OdometryCalibrator | ParticleCalibration:
    """The online odometry calibration that ``m.calibration`` names, from the motion settings."""
    common = dict(
        scale=m.odometry_scale,
        gyro_bias_rad_s=math.radians(m.gyro_bias_deg_s),
        estimate_scale=m.calibrate_scale,
        estimate_bias=m.calibrate_gyro_bias,
        min_scale=m.calibration_min_scale,
        max_scale=m.calibration_max_scale,
    )
    if m.calibration == "particles":
        return ParticleCalibration(
            **common,
            sigma_scale=m.calibration_sigma_scale,
            sigma_bias_rad_s=math.radians(m.calibration_sigma_bias_deg_s),
            walk_scale=m.calibration_walk_scale,
            walk_bias_rad_s=math.radians(m.calibration_walk_bias_deg_s),
        )
    return OdometryCalibrator(
        **common,
        window_m=m.calibration_window_m,
        window_s=m.calibration_window_s,
        prior_m=m.calibration_prior_m,
        prior_s=m.calibration_prior_s,
        outlier_m=m.calibration_outlier_m,
        outlier_deg=m.calibration_outlier_deg,
    )


def signal_watch(r: RecoverySettings, floor: float) -> SignalWatch:
    """The evidence watch of the recovery settings; ``floor``: the observation model's floor of the
    residual signal, unless ``r.min_residual_m`` sets one."""
    return SignalWatch(
        signal=r.signal,
        inlier_factor=r.inlier_factor,
        inlier_residual_factor=r.inlier_residual_factor,
        inlier_residual_jump=r.inlier_residual_jump,
        residual_factor=r.factor,
        floor=floor if r.min_residual_m is None else r.min_residual_m,
        updates=r.updates,
        history=r.history,
    )


def lost_detector(r: RecoverySettings, separation_m: float, floor: float) -> LostDetector:
    """The lost detector (the watch and the second opinion) of the recovery settings; ``separation_m``:
    the convergence test's (a better place must keep moving with the odometry within it)."""
    return LostDetector(
        signal_watch(r, floor),
        second_opinion=r.second_opinion,
        opinion_top=r.opinion_top,
        opinion_per_place=r.opinion_per_place,
        polish_places=r.polish_places,
        polish_per_place=r.polish_per_place,
        polish_sigma_xy_m=r.polish_sigma_xy_m,
        polish_sigma_yaw_deg=r.polish_sigma_yaw_deg,
        opinion_inlier_gain=r.opinion_inlier_gain,
        opinion_badness_ratio=r.opinion_badness_ratio,
        saturated_badness_ratio=r.saturated_badness_ratio,
        history_updates=r.history_updates,
        history_margin=r.history_margin,
        history_min_inliers=r.history_min_inliers,
        opinion_min_range_m=r.opinion_min_range_m,
        max_vetoed_updates=r.max_vetoed_updates,
        probation_updates=r.probation_updates,
        probation_hits=r.probation_hits,
        opinion_hits=r.opinion_hits,
        consistent_m=separation_m,
        max_misses=r.opinion_max_misses,
        doubt_ratio=r.doubt_ratio,
        doubt_inlier_gain=r.doubt_inlier_gain,
    )


def build_localizer(
    mesh_map: MeshMap,
    settings: LocalizerSettings | None = None,
    *,
    rng: np.random.Generator | None = None,
    seed: int | None = None,
    device: str = "cpu",
    threads: int | None = None,
    sensor_height_m: float | None = None,
    caster: RayCaster | None = None,
) -> MonteCarloLocalizer:
    """A :class:`~rangemcl.localization.filter.MonteCarloLocalizer` made from the settings (checked
    first; an InputError names the key).

    Args:
        mesh_map: the map (its ground grid gives each particle's height).
        settings: :class:`LocalizerSettings` (default: the defaults).
        rng: the run's generator (or give ``seed``).
        device: Warp device, ``"cpu"`` or ``"cuda"``.
        threads: CPU threads for the ray casting (None: all cores).
        sensor_height_m: the sensor's height above the ground (default: settings, then the map, then 1.73).
        caster: an existing :class:`RayCaster` holding the map (shared between filters), else one is made.
    """
    from rangemcl.localization.models import RangeModel, make_model

    s = settings or LocalizerSettings()
    s.check()
    p, m, o, c, r, i = s.particles, s.motion, s.observation, s.convergence, s.recovery, s.init
    height = sensor_height_m if sensor_height_m is not None else s.sensor_height_m
    if height is None:
        height = mesh_map.meta.get("sensor_height_m", 1.73)
    if caster is None:
        caster = RayCaster(device, threads)
        caster.add_mesh(mesh_map.vertices, mesh_map.faces, name="map")
    scorer = make_model(o.model, caster, o, mesh_map)
    # Eq. 5 residuals (residuals()): the range model's own kernel, or one of the same settings
    residual_model = (
        scorer.kernel
        if isinstance(scorer, RangeModel)
        else ParticleRenderer(caster, margin_m=o.margin_m, cap_m=np.inf if o.cap_m is None else o.cap_m)
    )
    lost = lost_detector(r, c.separation_m, scorer.lost_floor) if r.enabled else None
    calibrator = odometry_calibrator(m)
    f = s.refine
    refiner = scan_refiner(caster, f) if f.enabled else None
    return MonteCarloLocalizer(
        mesh_map,
        scorer,
        caster=caster,
        refiner=refiner,
        calibrator=calibrator,
        refine_gate_m=f.gate_m,
        refine_gate_deg=f.gate_deg,
        refine_all_heights_updates=f.all_heights_updates,
        map_radius_m=o.max_range_m + o.margin_m + f.max_residual_m + 0.5,
        calibration_settle_updates=m.calibration_settle_updates,
        residual_model=residual_model,
        select_rays=ray_selector(o),
        area=drivable_cells(mesh_map, i.drive_radius_m),
        noise=motion_noise(m),
        lost=lost,
        rng=rng if rng is not None else np.random.default_rng(seed),
        sensor_height_m=float(height),
        update_distance_m=m.update_distance_m,
        update_angle_deg=m.update_angle_deg,
        level_with_imu=o.level_with_imu,
        rendering=o.rendering,
        global_count=p.global_count,
        converged_count=p.converged_count,
        tracking_count=p.tracking_count,
        tracking_sigma_xy_m=p.tracking_sigma_xy_m,
        tracking_sigma_yaw_deg=p.tracking_sigma_yaw_deg,
        resample_neff_ratio=p.resample_neff_ratio,
        jitter_xy_m=p.jitter_xy_m,
        jitter_yaw_deg=p.jitter_yaw_deg,
        global_jitter_xy_m=p.global_jitter_xy_m,
        global_jitter_yaw_deg=p.global_jitter_yaw_deg,
        estimate_best_share=p.estimate_best_share,
        uniform_yaw_share=i.uniform_yaw_share,
        heading_sigma_deg=i.heading_sigma_deg,
        place_prior=i.place_prior,
        prior_params=PriorParams(cell_m=i.prior_cell_m),
        beam_prior=i.beam_prior,
        prior_profile_returns=i.prior_profile_returns,
        prior_skip_zero_intensity=i.prior_skip_zero_intensity,
        prior_share=i.prior_share,
        prior_top=i.prior_top,
        prior_yaw_sigma_deg=i.prior_yaw_sigma_deg,
        inject_share=i.inject_share,
        inject_top=i.inject_top,
        inject_below_share=i.inject_below_share,
        convergence=c.method,
        tiles=c.tiles,
        max_radius_m=c.max_radius_m,
        compact_radius_m=c.compact_radius_m,
        cluster_m=c.cluster_m,
        margin_nats=c.margin_nats,
        separation_m=c.separation_m,
        min_inliers=c.min_inliers,
        min_distance_m=c.min_distance_m,
        min_cluster_particles=c.min_cluster_particles,
        prune_nats=c.prune_nats,
        max_clusters=c.max_clusters,
        kld_epsilon=c.kld_epsilon,
        kld_bin_xy_m=c.kld_bin_xy_m,
        kld_bin_yaw_deg=c.kld_bin_yaw_deg,
        min_search_particles=c.min_search_particles,
        polish_hypotheses=c.polish_hypotheses,
        polish_keep=c.polish_keep,
        challenge_top=c.challenge_top,
        challenge_places=c.challenge_places,
        challenge_updates=c.challenge_updates,
    )


def map_place_prior(
    map_dir,
    settings: LocalizerSettings | None = None,
    *,
    map_memory_mb: float | None = None,
    device: str = "cpu",
    threads: int | None = None,
) -> tuple[PlacePrior, str]:
    """The place prior that a localizer with ``settings`` uses on the map in ``map_dir``: loaded from the
    map folder when one is stored for these settings, else rendered and stored there (what ``rangemcl
    build-map`` and ``import-mesh`` do as their last step, so that the first global localization does not
    pay for it). The map is held as the localizer holds it: within ``map_memory_mb`` (default: the
    settings', else the localizer's default), the prior then rendered tile by tile. Returns ``(prior, how)``
    with how in ``loaded | built | built (not saved: ...)``."""
    from rangemcl.maps.view import open_map

    s = settings or LocalizerSettings()
    s.check()
    memory = map_memory_mb if map_memory_mb is not None else s.map_memory_mb
    mesh_map, caster = open_map(map_dir, memory, device=device, threads=threads)
    try:
        if caster is None:
            caster = RayCaster(device, threads)
            caster.add_mesh(mesh_map.vertices, mesh_map.faces, name="map")
        area = drivable_cells(mesh_map, s.init.drive_radius_m)
        return load_or_build(
            mesh_map,
            caster,
            area.corners,
            area.cell_m,
            PriorParams(cell_m=s.init.prior_cell_m),
            replace_damaged=True,  # rendering the prior is what this is for: a damaged one is replaced
        )
    finally:
        if mesh_map.budgeted:
            mesh_map.close()
