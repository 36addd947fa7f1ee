"""The Monte Carlo localizer on a tiny synthetic town: global convergence, tracking, recovery after a
teleport, de-skewing and levelling of scans, SE(2) algebra, settings checks, and the results folder of
``localize_sequence`` checked against ground truth."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.common.checkpoint import restore_state, save_state
from rangemcl.config import load_config
from rangemcl.datasets.kitti import SequenceWriter
from rangemcl.errors import InputError
from rangemcl.evaluation.metrics import evaluate_results, localization_metrics
from rangemcl.localization import (
    LocalizerSettings,
    MonteCarloLocalizer,
    ObservationSettings,
    build_localizer,
    drivable_cells,
    prepare_rays,
)
from rangemcl.localization.pipeline import RunOptions, localize_sequence
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import rotation_roll_pitch, se2_between, se2_compose
from rangemcl.sensors import load_spec

HEIGHT = 1.73


@pytest.fixture(scope="module")
def world():
    town = meshgen.town(
        seed=5, size_m=100.0, n_buildings=18, n_poles=25, facade_cell_m=2.0, ground_cell_m=2.0
    )
    v, f = town.merged()
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="town")
    road = float(town.road_xy[0])
    # an L-shaped drive: east along one road, then north along a crossing road
    xs = np.arange(-40.0, float(town.road_xy[1]), 0.6)
    leg1 = np.column_stack([xs, np.full_like(xs, road - 2.0), np.zeros_like(xs)])
    x_turn = float(town.road_xy[1]) + 2.0
    ys = np.arange(road - 2.0, 45.0, 0.6)
    leg2 = np.column_stack([np.full_like(ys, x_turn), ys, np.full_like(ys, np.pi / 2)])
    path = np.vstack([leg1, leg2])
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    m.drive_xy = path[::3, :2]
    geo = RangeImageGeometry.for_spec(load_spec("hdl-32e").with_columns(180))
    return town, caster, m, path, geo


def scan_at(town, caster, geo, pose, roll_pitch=(0.0, 0.0)):
    """Points in the sensor frame of a sensor at ``pose`` (x, y, yaw), tilted by roll and pitch."""
    x, y, yaw = pose
    z = float(town.ground_height(x, y)) + HEIGHT
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ rotation_roll_pitch(*roll_pitch)
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([x, y, z]), d @ R.T, 80.0)
    return (d[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)


def small_settings(**obs) -> LocalizerSettings:
    s = LocalizerSettings()
    s.particles.global_count = 3000
    s.particles.converged_count = 60
    s.observation = ObservationSettings(rays=150, max_range_m=60.0, **obs)
    return s


def run(loc, town, caster, geo, path, odo_noise, rng, truth_at=None, frames=None):
    """Drive the filter along ``path`` (truth ``truth_at(k)``, default the path) with odometry from the
    path plus noise; return estimates and step infos."""
    truth_at = truth_at or (lambda k: path[k])
    est, infos = [], []
    for k in range(frames or len(path)):
        delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
        delta = delta + rng.normal(0, odo_noise, 3) * (k > 0)
        info = loc.step(delta, scan_at(town, caster, geo, truth_at(k)))
        est.append(info.estimate)
        infos.append(info)
    return np.array(est), infos


def errors(est, truth):
    loc = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    yaw = np.degrees(np.abs((est[:, 2] - truth[:, 2] + np.pi) % (2 * np.pi) - np.pi))
    return loc, yaw


def test_global_localization_converges_on_a_tiny_town(world):
    town, caster, m, path, geo = world
    loc = build_localizer(m, small_settings(), seed=1, caster=caster)
    loc.spread()
    assert len(loc.particles) == 3000
    est, infos = run(loc, town, caster, geo, path, [0.01, 0.005, 0.002], np.random.default_rng(2))
    conv = next(k for k, i in enumerate(infos) if i.converged)
    assert infos[-1].particles == 60  # reduced once converged
    assert conv < len(path) - 30
    loc_err, yaw_err = errors(est[conv + 10 :], path[conv + 10 :])
    assert np.sqrt(np.mean(loc_err**2)) < 0.5
    assert np.sqrt(np.mean(yaw_err**2)) < 1.5
    assert loc_err[-10:].max() < 0.35
    assert not any(i.recovered for i in infos)


@pytest.mark.parametrize("rendering", ["exact", "planar"])
def test_tracking_follows_and_recovers_after_a_teleport(world, rendering):
    """Tracking, then a teleport the odometry does not see: caught and relocalized; with the converged
    cloud rendered exactly, and with the planar rendering about its estimate (the lost watch still reads
    the best particle rendered exactly)."""
    town, caster, m, path, geo = world
    jump = 40  # from this frame on the car is elsewhere, but its odometry says it just drove on
    offset = np.array([0.0, 0.0, 0.0])
    other = path[len(path) - 100 :]  # the second leg, 90 degrees turned
    frames = jump + 100

    def truth_at(k):
        return path[k] if k < jump else other[k - jump] + offset

    s = small_settings(rendering=rendering)
    loc = build_localizer(m, s, seed=3, caster=caster)
    loc.start_at(path[0])
    assert loc.converged and len(loc.particles) == s.particles.tracking_count
    rng = np.random.default_rng(4)
    est, infos, planar = [], [], []
    for k in range(frames):
        a, b = (path[k - 1], path[k]) if k < jump else (other[max(k - jump - 1, 0)], other[k - jump])
        delta = (se2_between(a, b) if k else np.zeros(3)) + rng.normal(0, [0.01, 0.005, 0.002]) * (k > 0)
        if k == jump:  # the odometry sees an ordinary step, not the teleport
            delta = se2_between(path[k - 1], path[k])
        planar.append(loc._planar_about() is not None)  # what the step after the motion will see
        info = loc.step(delta, scan_at(town, caster, geo, truth_at(k)))
        est.append(info.estimate)
        infos.append(info)
    est = np.array(est)
    truth = np.array([truth_at(k) for k in range(frames)])
    # the start's spread (0.5 m) is rendered exactly; the tracked cloud, compact, planar (when asked)
    assert not planar[0] and any(planar[5:jump]) == (rendering == "planar")
    loc_err, _ = errors(est, truth)
    assert loc_err[:jump].max() < 0.5  # tracking
    assert loc_err[jump] > 20  # kidnapped
    recovered_at = [k for k, i in enumerate(infos) if i.recovered]
    # a suspicion after 5 bad updates, then the same better place confirmed at two of them
    assert recovered_at and jump <= recovered_at[0] < jump + 20
    assert infos[recovered_at[0]].particles == s.particles.global_count
    assert loc.recoveries >= 1
    assert infos[-1].converged
    assert loc_err[-10:].max() < 0.5  # relocalized


def test_true_pose_scores_above_perturbed_poses_through_the_filter(world):
    town, caster, m, path, geo = world
    s = small_settings()
    loc = build_localizer(m, s, seed=0, caster=caster)
    k = 30
    rays = prepare_rays(scan_at(town, caster, geo, path[k]), s.observation, np.random.default_rng(0))
    offsets = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.05], [2, 1, 0], [0, 0, 0.3]])
    d = loc.residuals(rays, path[k] + offsets)
    assert d[0] < 0.05 and (d[1:] > d[0] + 0.05).all()


def _tracking_with_history(world, updates: int, first: int, last: int, seen=None, **recovery):
    """A filter started at the drive's first true pose with the look at the past over ``updates``
    updates (and the given ``recovery`` settings), stepped along the true odometry over frames ``first``
    to ``last``; ``seen(k)`` is the pose each scan is taken from (default the true one)."""
    _town, caster, m, path, _geo = world
    s = small_settings()
    s.recovery.history_updates = updates
    for key, value in recovery.items():
        setattr(s.recovery, key, value)
    loc = build_localizer(m, s, seed=3, caster=caster)
    loc.start_at(path[0])
    _drive(loc, world, first, last, seen)
    return loc, s


def _drive(loc, world, first: int, last: int, seen=None) -> None:
    town, caster, _m, path, geo = world
    for k in range(first, last + 1):
        pose = path[k] if seen is None else seen(k)
        loc.step(se2_between(path[k - 1], path[k]), scan_at(town, caster, geo, pose))


def test_the_look_at_the_past_moves_poses_back_along_the_odometry(world, tmp_path):
    """recovery.history_updates: the filter keeps the recent updates' rays and odometry; the true pose of
    now, moved back along the odometry, fits each past scan (nearly all far rays inliers), a pose 3 m
    to the side fits them clearly worse, and with too few past scans there is no verdict (NaN)."""
    town, caster, m, path, geo = world
    loc, s = _tracking_with_history(world, 20, 1, 5)
    assert np.isnan(loc._history_inliers(path[5][None])).all()  # 5 past scans of the 20: no verdict
    _drive(loc, world, 6, 39)
    # (kept as long as the look at the past or the search's challenge reaches back, whichever is longer)
    assert len(loc._recent) == 39
    challenge = s.convergence.challenge_updates + 1 if s.convergence.challenge_top > 0 else 0
    assert loc._recent.maxlen == max(21 + s.recovery.max_vetoed_updates, challenge)
    fit = loc._history_inliers(np.array([path[39], path[39] + [0.0, 3.0, 0.0], path[39] + [0.0, 0.0, 0.1]]))
    assert fit[0] > 0.9 and fit[1] < fit[0] - 0.2 and fit[2] < fit[0] - 0.2
    # a checkpoint (rangemcl localize --resume) holds the kept updates: the same verdicts after a restore
    save_state(tmp_path / "state.npz", {"filter": loc})
    again = build_localizer(m, s, seed=3, caster=caster)
    restore_state(tmp_path / "state.npz", {"filter": again})
    assert again._recent.maxlen == loc._recent.maxlen and len(again._recent) == 39
    assert np.array_equal(again._history_inliers(path[39][None]), fit[:1])
    # off, and no challenge either: nothing kept
    s_off = small_settings()
    s_off.recovery.history_updates = 0
    s_off.convergence.challenge_top = 0
    off = build_localizer(m, s_off, seed=3, caster=caster)
    off.start_at(path[0])
    off.step(se2_between(path[0], path[1]), scan_at(town, caster, geo, path[1]))
    assert off._recent is None


def test_the_look_at_the_past_leaves_out_the_scans_of_the_suspicion(world):
    """The scans of the watch's current run of bad updates (here 8 scans taken 3 m to the side of where
    the odometry says, as if hidden or changed) are left out of the look at the past, so the true pose
    fits the past before them; without a suspicion those scans are part of the past and drag its fit
    down."""
    _town, _caster, _m, path, _geo = world

    def seen(k):  # the last 8 scans: not the truth's
        return path[k] + ([0.0, 3.0, 0.0] if k >= 32 else 0.0)

    loc, _s = _tracking_with_history(world, 20, 1, 39, seen)
    loc.lost.watch.bad_updates = 8  # the suspicion's updates (the current one and the 7 before)
    skipped = loc._history_inliers(path[39][None])[0]
    loc.lost.watch.bad_updates = 0  # no suspicion: the 8 scans are the most recent past
    kept = loc._history_inliers(path[39][None])[0]
    assert skipped > 0.9 and kept < skipped - 0.1
    # the same 20 scans whatever the suspicion's length: with a suspicion longer than the depth kept
    # beyond the look, fewer than half of them remain and there is no verdict
    loc.lost.watch.bad_updates = 30
    assert np.isnan(loc._history_inliers(path[39][None])).all()


def test_a_better_place_must_also_explain_the_past_while_the_filter_still_fits(world):
    """A filter converged 12 m down the street from the car, asked for a second opinion, finds the true
    place, and the look at the past (recovery.history_updates) is taken, where the true place, which
    explained the past scans, stays better; while the filter's own place fits fewer far rays than
    recovery.history_min_inliers (a car that jumped rather than a changed street) the look is not
    taken."""
    town, caster, _m, path, geo = world
    # (history_min_inliers 0: the look is asked at any fit of the filter's own place)
    loc, _s = _tracking_with_history(world, 10, 1, 24, history_min_inliers=0.0)
    pts = scan_at(town, caster, geo, path[24])
    rays = loc.select_rays(pts, loc.rng, sensor_height_m=loc.sensor_height_m)
    wrong = path[24] + np.array([12.0, 0.0, 0.0])
    loc._set_particles(wrong + np.random.default_rng(0).normal(0.0, 0.1, (60, 3)) * [1.0, 1.0, 0.02])
    loc.last_estimate = wrong.copy()
    looks = []
    real = loc._history_inliers
    loc._history_inliers = lambda p: (looks.append(len(p)), real(p))[1]

    def ask() -> int:
        looks.clear()
        found = loc._second_opinion(rays, np.asarray(pts, np.float64), None, 0.15)
        assert found.better and np.hypot(*(found.pose[:2] - path[24][:2])) < 4.0  # (not 12 m off)
        return len(looks)

    assert ask() > 0
    loc.lost.history_min_inliers = 1.0  # no place fits every far ray: the look is never taken
    assert ask() == 0


def test_prepare_rays_deskews_with_the_frame_motion():
    """Points fired from a moving sensor, de-skewed, land where a sensor at the stamp pose sees them."""
    rng = np.random.default_rng(0)
    world_pts = np.column_stack(
        [rng.uniform(-30, 30, 500), rng.uniform(-30, 30, 500), rng.uniform(-1, 3, 500)]
    )
    world_pts = world_pts[np.hypot(world_pts[:, 0], world_pts[:, 1]) > 5]
    motion = np.array([1.2, 0.1, 0.15])  # over one 0.1 s frame, in the previous stamp's pose
    prev = np.array([0.0, 0.0, 0.0])
    end = se2_compose(prev, motion)
    t = rng.uniform(-0.1, 0.0, len(world_pts))  # firing times relative to the stamp
    share = 1 + t / 0.1
    pts = []
    for p, a in zip(world_pts, share, strict=True):
        pose = a * motion  # uniform motion, as the de-skew assumes
        rel = se2_between(pose, np.array([p[0], p[1], 0.0]))
        pts.append([rel[0], rel[1], p[2]])
    pts = np.array(pts, np.float32)
    # (every point kept: scattered random points may group into car-sized objects)
    settings = ObservationSettings(rays=10_000, min_range_m=0.1, max_range_m=100.0, vehicle_length_m=None)
    rays = prepare_rays(pts, settings, rng, fire_time_s=t, frame_period_s=0.1, frame_motion=motion)
    got = rays.directions * rays.ranges[:, None]
    want = np.array([[*se2_between(end, np.array([p[0], p[1], 0.0]))[:2], p[2]] for p in world_pts])
    np.testing.assert_allclose(got, want, atol=2e-3)
    raw = prepare_rays(
        pts,
        ObservationSettings(
            rays=10_000, min_range_m=0.1, max_range_m=100.0, deskew=False, vehicle_length_m=None
        ),
        rng,
    )
    assert np.abs(raw.directions * raw.ranges[:, None] - want).max() > 0.5  # the skew was real


def test_prepare_rays_levels_with_roll_and_pitch_and_filters():
    rng = np.random.default_rng(1)
    roll, pitch = 0.05, -0.08
    level = rng.normal(0, 10, (300, 3))
    R = rotation_roll_pitch(roll, pitch)
    tilted = (level @ R).astype(np.float32)  # what a tilted sensor measures: R^T p
    settings = ObservationSettings(rays=10_000, min_range_m=0.0, max_range_m=1e9)
    rays = prepare_rays(tilted, settings, rng, roll_pitch=(roll, pitch))
    np.testing.assert_allclose(rays.directions * rays.ranges[:, None], level, atol=1e-4)
    bad = tilted.copy()
    bad[:50] = np.nan
    bad[50:60] = 0.0
    rays = prepare_rays(bad, ObservationSettings(rays=100, min_range_m=0.5, max_range_m=1e9), rng)
    assert len(rays.ranges) == 100 and rays.valid_points == 240 and np.isfinite(rays.ranges).all()
    assert prepare_rays(np.full((10, 3), np.nan, np.float32), settings, rng) is None
    assert prepare_rays(np.zeros((0, 3), np.float32), settings, rng) is None


def test_ray_sampling_by_elevation_gives_each_band_its_share():
    """A scan whose points crowd one elevation (the road near the car): 'points' picks rays in proportion,
    'elevation' about the same number from each 2-degree band."""
    rng = np.random.default_rng(7)
    elev = np.concatenate([np.full(9000, -20.0), np.repeat(np.arange(-15.0, 5.0, 2.0), 100)])
    elev += rng.uniform(0.1, 1.9, len(elev))  # within each band
    az = rng.uniform(-np.pi, np.pi, len(elev))
    e = np.radians(elev)
    pts = (np.column_stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)]) * 10.0).astype(
        np.float32
    )
    for sampling, crowded in (("points", (0.85, 0.95)), ("elevation", (0.05, 0.15))):
        o = ObservationSettings(rays=550, ray_sampling=sampling, min_range_m=0.0, max_range_m=100.0)
        rays = prepare_rays(pts, o, np.random.default_rng(1))
        band = np.floor(np.degrees(np.arcsin(rays.directions[:, 2])) / 2.0)
        _, counts = np.unique(band, return_counts=True)
        assert len(np.unique(rays.directions, axis=0)) == 550  # 550 distinct points
        share = np.mean(band == -10)  # the crowded band, -20..-18 degrees
        assert crowded[0] < share < crowded[1], (sampling, share)
        if sampling == "elevation":
            assert counts.min() >= 25 and counts.max() <= 75  # 11 bands, 50 each on average
    with pytest.raises(InputError, match="ray_sampling"):
        s = LocalizerSettings()
        s.observation.ray_sampling = "beams"
        s.check()


def test_scan_without_valid_points_only_predicts(world):
    _, caster, m, path, _ = world
    loc = build_localizer(m, small_settings(), seed=0, caster=caster)
    loc.start_at(path[0])
    info = loc.step(np.array([1.0, 0.0, 0.0]), np.full((100, 3), np.nan, np.float32))
    assert info.updated is False and info.skipped_scan is True
    np.testing.assert_allclose(info.estimate[:2], path[0, :2] + [1.0, 0.0], atol=0.3)
    info = loc.step(np.array([0.05, 0.0, 0.0]), None)  # below the update distance: no update due
    assert not info.updated and not info.skipped_scan


@pytest.mark.parametrize("seed", range(5))
def test_se2_compose_and_between_are_inverse(seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform([-50, -50, -np.pi], [50, 50, np.pi], (20, 3))
    b = rng.uniform([-50, -50, -np.pi], [50, 50, np.pi], (20, 3))
    np.testing.assert_allclose(se2_compose(a, se2_between(a, b)), b, atol=1e-9)
    np.testing.assert_allclose(se2_between(a, a), 0, atol=1e-12)


def test_settings_are_checked(world):
    _, caster, m, _, _ = world
    for key, value in [("sigma_m", 0.0), ("rays", 0), ("margin_m", -1.0), ("cap_m", 0.0)]:
        s = LocalizerSettings()
        setattr(s.observation, key, value)
        with pytest.raises(InputError, match=f"observation.{key}"):
            build_localizer(m, s, caster=caster)
    s = LocalizerSettings()
    s.particles.resample_neff_ratio = 1.5
    with pytest.raises(InputError, match="resample_neff_ratio"):
        s.check()
    s = LocalizerSettings()
    s.init.inject_share = 1.5
    with pytest.raises(InputError, match="inject_share"):
        s.check()
    s.init.inject_share = 0.05
    s.convergence.polish_keep = 0  # (convergence.polish_hypotheses: 0 turns the polish off)
    with pytest.raises(InputError, match="polish_keep"):
        s.check()
    s.convergence.polish_keep = 8
    s.check()
    for bad in (0.0, 1.0, float("nan")):
        s.recovery.saturated_badness_ratio = bad
        with pytest.raises(InputError, match="saturated_badness_ratio"):
            s.check()
    s.recovery.saturated_badness_ratio = 0.75
    s.check()
    for bad in (5.0, float("nan")):  # below refine.min_information (10), or not a number
        s.refine.weak_information = bad
        with pytest.raises(InputError, match="weak_information"):
            s.check()
    s.refine.weak_information = None
    s.refine.weak_step_m = -0.1
    with pytest.raises(InputError, match="weak_step_m"):
        s.check()
    loc = build_localizer(m, LocalizerSettings(), caster=caster)
    with pytest.raises(InputError, match="no particles"):
        loc.step(np.zeros(3), None)
    with pytest.raises(InputError, match="outside the map"):
        loc.start_at([5000.0, 0.0, 0.0])


def test_spread_covers_the_drive_with_yaw_along_it(world):
    _, caster, m, _, _ = world
    s = LocalizerSettings()
    area = drivable_cells(m, s.init.drive_radius_m)
    assert area.headings is not None and len(area.corners) > 100
    loc = build_localizer(m, s, seed=0, caster=caster)
    loc.spread(5000)
    p = loc.particles
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(m.drive_xy).query(p[:, :2])
    assert dist.max() < s.init.drive_radius_m + 1.5
    # yaw: most particles point along the road they are on (east-west or north-south here)
    along = np.minimum(np.abs(np.sin(p[:, 2])), np.abs(np.cos(p[:, 2])))
    assert np.mean(along < np.sin(np.radians(45))) > 0.8
    m2 = MeshMap.from_mesh(m.vertices, m.faces, m.is_ground, tile_size_m=50.0)  # no drive: all ground cells
    assert drivable_cells(m2, s.init.drive_radius_m).headings is None
    assert len(drivable_cells(m2, s.init.drive_radius_m).corners) > len(area.corners)


def test_metrics_follow_the_papers_definition():
    truth = np.zeros((350, 3))
    est = np.zeros((350, 3))
    est[:50, 0] = 100.0  # searching
    est[50:, 0] = 0.3
    est[50:, 2] = np.radians(2.0)
    m = localization_metrics(est, truth, 50)
    assert m["success"] and m["checked_frames"] == [50, 150, 250]
    assert m["location_rmse_m"] == pytest.approx(0.3) and m["yaw_rmse_deg"] == pytest.approx(2.0)
    est[250, 0] = 6.0  # a checked frame above 5 m fails the run
    assert not localization_metrics(est, truth, 50)["success"]
    est[250, 0] = 0.3
    est[251, 0] = 6.0  # an unchecked frame does not, but counts in the RMSE
    m2 = localization_metrics(est, truth, 50)
    assert m2["success"] and m2["location_rmse_m"] > m["location_rmse_m"]
    assert localization_metrics(est, truth, None)["success"] is False


def write_sequence(root, town, caster, geo, path, *, odometry=True, nan_frames=(), rng=None):
    rng = rng or np.random.default_rng(0)
    with SequenceWriter(root, meta={"scene": "tiny synthetic town"}) as w:
        odo = np.zeros(3)
        for k, pose in enumerate(path):
            if k:
                odo = se2_compose(odo, se2_between(path[k - 1], pose) + rng.normal(0, [0.01, 0.005, 0.002]))
            pts = scan_at(town, caster, geo, pose)
            if k in nan_frames:
                pts = np.full_like(pts, np.nan)
            T = np.eye(4)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            T[:2, :2] = [[c, -s], [s, c]]
            T[:3, 3] = (pose[0], pose[1], float(town.ground_height(pose[0], pose[1])) + HEIGHT)
            To = np.eye(4)
            c, s = math.cos(odo[2]), math.sin(odo[2])
            To[:2, :2] = [[c, -s], [s, c]]
            To[:2, 3] = odo[:2]
            w.add_frame(pts, pose=T, time_s=0.1 * k, odometry=To if odometry else None)
    return root


def test_localize_sequence_writes_results_checked_against_truth(world, tmp_path):
    town, caster, m, path, geo = world
    seq = write_sequence(tmp_path / "seq", town, caster, geo, path[:60], nan_frames=(20,))
    m.save(tmp_path / "map")
    s = small_settings(sigma_m=0.5, cap_m=1.0)
    out = tmp_path / "res"
    summary = localize_sequence(seq, tmp_path / "map", out, s, RunOptions(mode="tracking", seed=0, threads=2))
    for name in (
        "config.yaml",
        "frames.csv",
        "estimate_kitti.txt",
        "estimate_tum.txt",
        "summary.json",
        "metrics.json",
        "particles.npz",
        "trajectory.png",
        "error.png",
        "particles.png",
    ):
        assert (out / name).is_file(), name
    assert summary["frames"] == 60 and summary["skipped_scans"] == 1 and summary["converged_frame"] == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["success"] and metrics["location_rmse_m"] < 0.3 and metrics["yaw_rmse_deg"] < 1.5
    again = evaluate_results(out, seq / "poses.txt")
    assert again["location_rmse_m"] == pytest.approx(metrics["location_rmse_m"], rel=1e-6)
    assert len((out / "frames.csv").read_text().splitlines()) == 61
    tum = (out / "estimate_tum.txt").read_text().splitlines()
    assert len(tum) == 60 and len(tum[0].split()) == 8


def test_localize_sequence_bad_inputs(world, tmp_path):
    town, caster, m, path, geo = world
    seq = write_sequence(tmp_path / "seq", town, caster, geo, path[:12], odometry=False)
    m.save(tmp_path / "map")
    opts = RunOptions(mode="tracking", threads=2, plots=False)
    with pytest.raises(InputError, match=r"no odometry\.txt.*--odometry-from-poses"):
        localize_sequence(seq, tmp_path / "map", tmp_path / "r1", small_settings(), opts)
    opts.odometry_from_poses = True
    s = localize_sequence(seq, tmp_path / "map", tmp_path / "r2", small_settings(), opts)
    assert s["odometry_source"].startswith("poses.txt")
    far = MeshMap.from_mesh(m.vertices + np.array([5000.0, 0, 0]), m.faces, m.is_ground)
    far.save(tmp_path / "far")
    with pytest.raises(InputError, match="outside the map"):
        localize_sequence(seq, tmp_path / "far", tmp_path / "r3", small_settings(), opts)
    with pytest.raises(InputError, match="map folder does not exist"):
        localize_sequence(seq, tmp_path / "nomap", tmp_path / "r4", small_settings(), opts)


def test_an_interrupted_run_keeps_what_it_computed(world, tmp_path, monkeypatch):
    town, caster, m, path, geo = world
    seq = write_sequence(tmp_path / "seq", town, caster, geo, path[:20])
    m.save(tmp_path / "map")
    real_step = MonteCarloLocalizer.step
    calls = {"n": 0}

    def step(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 13:
            raise KeyboardInterrupt
        return real_step(self, *a, **k)

    monkeypatch.setattr(MonteCarloLocalizer, "step", step)
    out = tmp_path / "res"
    with pytest.raises(KeyboardInterrupt):
        localize_sequence(
            seq, tmp_path / "map", out, small_settings(), RunOptions(mode="tracking", threads=2)
        )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["frames"] == 12
    assert len((out / "estimate_kitti.txt").read_text().splitlines()) == 12
    assert json.loads((out / "metrics.json").read_text())["frames"] == 12
    assert (out / "trajectory.png").is_file()


def test_structure_sampling_caps_the_roads_share_of_the_rays():
    rng = np.random.default_rng(0)
    road = np.column_stack([rng.uniform(3, 20, 9000), rng.uniform(-5, 5, 9000), np.full(9000, -HEIGHT)])
    wall = np.column_stack([np.full(1000, 15.0), rng.uniform(-5, 5, 1000), rng.uniform(-1.0, 3.0, 1000)])
    pts = np.vstack([road, wall])
    share = {}
    for mode in ("points", "elevation", "structure"):
        r = prepare_rays(pts, ObservationSettings(rays=500, ray_sampling=mode), rng, sensor_height_m=HEIGHT)
        share[mode] = float(np.mean(r.directions[:, 2] * r.ranges + HEIGHT < 0.5))
    assert share["points"] > 0.85  # drawn evenly over the points: mostly road
    assert share["structure"] < 0.3 < share["elevation"] < share["points"]
    # a scan of road alone still gives rays
    only_road = prepare_rays(road, ObservationSettings(rays=100, ray_sampling="structure"), rng)
    assert len(only_road.ranges) == 100


def test_structure_sampling_gives_the_tall_structure_its_share():
    """Of the structure rays, tall_share from points at least tall_m above the ground (the
    facades over the parked cars), however many more points the cars near the sensor return."""
    rng = np.random.default_rng(1)

    def band(n, x, z_lo, z_hi):  # points above the sensor's ground (z in the sensor frame: h - HEIGHT)
        z = rng.uniform(z_lo, z_hi, n) - HEIGHT
        return np.column_stack([rng.uniform(*x, n), rng.uniform(-6, 6, n), z])

    road = np.column_stack([rng.uniform(3, 20, 6000), rng.uniform(-5, 5, 6000), np.full(6000, -HEIGHT)])
    # parked cars near the sensor fill most elevation bands (the downward beams of an HDL-64E); the
    # facade above them only the few bands around the horizon
    cars = band(8000, (3.0, 8.0), 0.6, 1.5)
    facade = band(3000, (25.0, 25.0), 2.2, 3.5)
    pts = np.vstack([road, cars, facade])

    def shares(**kw):
        r = prepare_rays(pts, ObservationSettings(rays=500, **kw), rng, sensor_height_m=HEIGHT)
        h = r.directions[:, 2] * r.ranges + HEIGHT
        return len(r.ranges), float(np.mean(h >= 2.0)), float(np.mean(h < 0.5))

    n, tall, road_share = shares(tall_share=0.6)
    assert n == 500 and abs(tall - 0.8 * 0.6) < 0.06 and abs(road_share - 0.2) < 0.05
    _, tall_alike, _ = shares(tall_share=0.0)  # all structure alike, band by band
    assert tall_alike < tall - 0.1
    # no tall points (a sensor whose beams all point down): the low structure keeps the structure share
    # (the draw of tall_share: 0 exactly)
    low_only = np.vstack([road, cars])
    a, b = (
        prepare_rays(
            low_only, ObservationSettings(tall_share=t), np.random.default_rng(5), sensor_height_m=HEIGHT
        )
        for t in (0.6, 0.0)
    )
    assert np.array_equal(a.ranges, b.ranges) and np.array_equal(a.directions, b.directions)
    # all the rays asked of a part with fewer points: the draw is filled from the others
    only_tall = ObservationSettings(rays=500, tall_share=1.0, ground_share=0.0)
    r = prepare_rays(np.vstack([road, cars, facade[:100]]), only_tall, rng, sensor_height_m=HEIGHT)
    h = r.directions[:, 2] * r.ranges + HEIGHT
    assert len(r.ranges) == 500 and int(np.sum(h >= 2.0)) == 100


@pytest.mark.parametrize("beam_prior", [True, False])
def test_a_sensor_below_the_horizon_is_matched_with_its_top_beams_prior(world, beam_prior):
    town, caster, m, path, _geo = world
    mq8 = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(720))
    hdl = RangeImageGeometry.for_spec(load_spec("hdl-32e").with_columns(360))
    s = small_settings()
    s.init.beam_prior = beam_prior
    rp = (0.0, math.radians(0.5))  # pitched 0.5 degrees, levelled by the IMU

    def first_update(geo):
        loc = build_localizer(m, s, seed=3, caster=caster)
        loc.spread()
        for k in range(30, 50):
            if loc.step(
                se2_between(path[k - 1], path[k]), scan_at(town, caster, geo, path[k], rp), roll_pitch=rp
            ).updated:
                return loc, path[k]
        raise AssertionError("no update")

    if beam_prior:  # an HDL-32E sees the high band: the band prior even with the beam prior on
        loc, _ = first_update(hdl)
        assert loc.beam_prior is None
    # the MQ-8: the prior of its -1.57 degree beam
    loc, truth = first_update(mq8)
    if not beam_prior:
        assert loc.beam_prior is None
        return
    assert loc.beam_prior is not None and loc.beam_prior.params.beam_deg == pytest.approx(-1.57)
    # the particles drawn from it include the true pose (within a cell and 5 degrees)
    d = np.hypot(loc.particles[:, 0] - truth[0], loc.particles[:, 1] - truth[1])
    dyaw = np.abs((loc.particles[:, 2] - truth[2] + np.pi) % (2 * np.pi) - np.pi)
    assert ((d < 1.5) & (dyaw < math.radians(5))).sum() >= 5


def test_the_search_polishes_its_hypotheses_onto_the_likelihoods_peak(world):
    """A hypothesis whose particles all lie 1.5 m ahead, 0.8 m aside and 6° off the true pose
    gets poses on the likelihood's peak (within a fine grid step of the truth, fitting better than any of
    its particles); the seed's weight before the scan is shared with them (the hypothesis gains weight
    only by fitting better); without the polish the cloud holds nothing near the truth."""
    town, caster, m, path, geo = world
    truth = path[30]
    pts = scan_at(town, caster, geo, truth)
    c, s_ = math.cos(truth[2]), math.sin(truth[2])
    rng = np.random.default_rng(5)
    off = np.array([1.5 * c - 0.8 * s_, 1.5 * s_ + 0.8 * c, math.radians(6.0)])
    near = truth + off + rng.normal(0.0, 1.0, (40, 3)) * [0.2, 0.2, math.radians(0.5)]
    elsewhere = path[70] + rng.normal(0.0, 1.0, (40, 3)) * [0.2, 0.2, math.radians(0.5)]
    cloud = np.vstack([near, elsewhere])

    def setup(polish: int):
        s = small_settings()
        s.init.place_prior = False
        s.convergence.polish_hypotheses = polish
        loc = build_localizer(m, s, seed=4, caster=caster)
        loc._set_particles(cloud.copy())
        loc.log_w = np.log(np.linspace(1.0, 2.0, len(cloud)))  # unequal weights before the scan
        rays = loc.select_rays(pts, loc.rng, sensor_height_m=loc.sensor_height_m)
        return loc, rays

    def dist(p):
        return np.hypot(p[:, 0] - truth[0], p[:, 1] - truth[1]), np.abs(
            (p[:, 2] - truth[2] + math.pi) % (2 * math.pi) - math.pi
        )

    loc, rays = setup(polish=2)
    before = loc.log_w.copy()
    loglik, bad = loc.scorer.score(rays, loc.particles, loc.sensor_z(loc.particles[:, :2]))
    loc.log_w = loc.log_w + loglik
    ll, bad2 = loc._polish_hypotheses(rays, loglik, bad)
    n0, keep = len(cloud), loc.polish_keep
    assert len(loc.particles) == n0 + 2 * keep and len(ll) == len(bad2) == len(loc.log_w) == n0 + 2 * keep
    new = loc.particles[n0:]
    dxy, dyaw = dist(new)
    assert dxy.min() < 0.2 and dyaw[np.argmin(dxy)] < math.radians(0.6)
    assert bad2[n0:].min() < bad[:n0].min() - 0.05  # fits better than any particle did
    # the weight before the scan is conserved: each seed shares its own with its new poses
    prior = loc.log_w - ll
    assert np.isclose(np.exp(prior).sum(), np.exp(before).sum())
    # the full update with and without the polish: only the polish brings the cloud onto the truth
    for polish, expect in ((2, True), (0, False)):
        loc, rays = setup(polish)
        loc._weigh(rays)
        dxy, dyaw = dist(loc.particles)
        assert bool(((dxy < 0.5) & (dyaw < math.radians(2.0))).any()) is expect


def test_the_second_opinions_grid_look_lands_on_the_likelihoods_peak(world):
    """The second opinion's look around a place (MonteCarloLocalizer._grid_look: the search's
    coarse then fine grid) from a seed 1.5 m ahead, 0.8 m aside and 6° off the true pose returns a pose
    within a fine step of the truth, fitting best, and one fine grid per seed."""
    town, caster, m, path, geo = world
    truth = path[30]
    pts = scan_at(town, caster, geo, truth)
    c, s_ = math.cos(truth[2]), math.sin(truth[2])
    off = np.array([1.5 * c - 0.8 * s_, 1.5 * s_ + 0.8 * c, math.radians(6.0)])
    seeds = np.vstack([truth + off, path[70]])
    loc = build_localizer(m, small_settings(), seed=4, caster=caster)
    rays = loc.select_rays(pts, loc.rng, sensor_height_m=loc.sensor_height_m)
    poses, bad, inl = loc._grid_look(rays, seeds)
    assert len(poses) == len(bad) == len(inl) and len(poses) % 2 == 0
    first = poses[: len(poses) // 2]
    j = int(np.argmin(bad[: len(poses) // 2]))
    assert np.hypot(*(first[j, :2] - truth[:2])) < 0.25
    assert abs((first[j, 2] - truth[2] + math.pi) % (2 * math.pi) - math.pi) < math.radians(0.6)
    assert bad[j] == bad.min() and inl[j] > 0.9
    seed_bad = float(loc.scorer.score(rays, seeds[:1], loc.sensor_z(seeds[:1, :2]))[1][0])
    assert bad[j] < seed_bad - 0.05


@pytest.mark.parametrize(
    "path", sorted((Path(__file__).parents[3] / "configs").glob("*.yaml")), ids=lambda p: p.name
)
def test_the_shipped_configs_load_and_check(path):
    load_config(LocalizerSettings, path).check(str(path))


def _fog_first_draw(world, skip: bool, intensity_of_surfaces: float):
    """The search's first draw (from the place prior) for scans with fog's echoes: every direction's
    returns within 1.5-3 m of the sensor at zero intensity, beside the surfaces' returns (intensity
    ``intensity_of_surfaces``). Returns the particles after the first update and its true pose."""
    town, caster, m, path, geo = world
    s = small_settings()
    s.init.prior_skip_zero_intensity = skip
    loc = build_localizer(m, s, seed=3, caster=caster)
    loc.spread()
    rng = np.random.default_rng(4)
    for k in range(30, 50):
        surface = scan_at(town, caster, geo, path[k])
        d = rng.normal(size=(2 * len(surface), 3))
        fog = d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(1.5, 3.0, (len(d), 1))
        points = np.vstack([surface, fog]).astype(np.float32)
        intensity = np.concatenate([np.full(len(surface), intensity_of_surfaces), np.zeros(len(fog))])
        if loc.step(se2_between(path[k - 1], path[k]), points, intensity=intensity).updated:
            return loc.particles.copy(), path[k]
    raise AssertionError("no update")


def test_returns_of_zero_intensity_are_left_out_of_the_prior_match(world):
    """`init.prior_skip_zero_intensity`: fog's echoes (zero intensity, two for every surface return, in
    every direction near the sensor) make every place of the prior look enclosed, so its first draw
    misses the true place; left out, the draw holds it. A scan whose returns all report zero (the ideal
    sensor) keeps every return: the same particles as without the setting."""

    def near_truth(particles, truth):
        d = np.hypot(particles[:, 0] - truth[0], particles[:, 1] - truth[1])
        dyaw = np.abs((particles[:, 2] - truth[2] + np.pi) % (2 * np.pi) - np.pi)
        return int(((d < 1.5) & (dyaw < math.radians(5))).sum())

    kept, truth = _fog_first_draw(world, skip=False, intensity_of_surfaces=0.3)
    left_out, _ = _fog_first_draw(world, skip=True, intensity_of_surfaces=0.3)
    assert near_truth(left_out, truth) >= 5
    assert near_truth(kept, truth) < near_truth(left_out, truth) / 2
    # all zero: nothing is left out
    ideal_skip, _ = _fog_first_draw(world, skip=True, intensity_of_surfaces=0.0)
    ideal_keep, _ = _fog_first_draw(world, skip=False, intensity_of_surfaces=0.0)
    assert np.array_equal(ideal_skip, ideal_keep)
