"""Hypotheses of the global search: clustering, evidence-preserving resampling, the KLD bound; and, through
the filter, convergence refused while two identical streets are equally good and granted once the drive
tells them apart; a removed object in the map does not make the filter declare itself lost."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.errors import InputError
from rangemcl.localization import LocalizerSettings, ObservationSettings, build_localizer
from rangemcl.localization.hypotheses import (
    ConvergenceTest,
    allocate,
    cluster_labels,
    kld_sample_size,
    occupied_bins,
    resample_by_cluster,
    summarize,
)
from rangemcl.localization.models import ScoringModel
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import se2_between
from rangemcl.sensors import load_spec

HEIGHT = 1.73


def test_clusters_are_connected_groups_of_cells():
    rng = np.random.default_rng(0)
    a = rng.normal([0, 0], 0.5, (50, 2))
    b = rng.normal([30, 5], 0.5, (40, 2))
    chain = np.column_stack([np.arange(100, 130, 1.5), np.full(20, -40.0)])  # touching cells: one cluster
    labels, n = cluster_labels(np.vstack([a, b, chain]), 3.0)
    assert n == 3
    assert len(set(labels[:50])) == 1 and len(set(labels[50:90])) == 1 and len(set(labels[90:])) == 1
    assert len({labels[0], labels[50], labels[90]}) == 3
    assert cluster_labels(np.zeros((0, 2)), 3.0)[1] == 0


def test_resampling_by_cluster_keeps_each_clusters_share_and_a_minimum_of_copies():
    rng = np.random.default_rng(1)
    p = np.vstack([rng.normal([0, 0, 0], 0.3, (300, 3)), rng.normal([50, 0, 1], 0.3, (300, 3))])
    w = np.concatenate([np.full(300, 0.999 / 300), np.full(300, 0.001 / 300)])
    labels, n = cluster_labels(p[:, :2], 3.0)
    hyps = summarize(p, w, labels, n)
    assert [round(h.share, 6) for h in hyps] == [0.999, 0.001]
    parts, logw, origin = resample_by_cluster(p, w, labels, hyps, 200, 25, rng)
    share = np.bincount(origin, weights=np.exp(logw))
    assert share == pytest.approx([0.999, 0.001])  # evidence carried, not sampled away
    assert np.bincount(origin).tolist() == [175, 25]  # the runner-up keeps its minimum
    assert np.all(parts[origin == 1, 0] > 40)


def test_allocation_and_kld_bound():
    assert allocate(np.array([0.7, 0.2, 0.1]), 100, 10).tolist() == [59, 24, 17]  # 10 each + 70 split 49:14:7
    assert allocate(np.array([0.5, 0.5]), 5, 10).tolist() == [10, 10]
    sizes = [kld_sample_size(k) for k in (1, 2, 10, 100, 1000)]
    assert sizes == sorted(sizes) and sizes[0] == 1 and 9000 < sizes[-1] < 13000
    p = np.array([[0.1, 0.1, 0.0], [0.2, 0.3, 0.01], [5.0, 0.0, 0.0], [0.1, 0.1, 3.0]])
    assert occupied_bins(p, 1.0, 10.0) == 3


def test_convergence_test_needs_margin_distance_and_a_compact_leader():
    from rangemcl.localization.hypotheses import Hypothesis

    def h(share, x=0.0, r=1.0):
        return Hypothesis(0, share, math.log(share), 10, np.array([x, 0.0, 0.0]), r)

    t = ConvergenceTest(margin_nats=5.0, min_distance_m=4.0, compact_radius_m=3.0)
    assert not t.update([h(0.5), h(0.5, 50.0)], True, 10.0)  # a tie: never
    t.reset()
    assert not t.update([h(0.999), h(0.001, 50.0)], True, 2.0)  # decisive, but not driven far enough
    assert t.update([h(0.999), h(0.001, 50.0)], True, 2.5)
    assert not t.update([h(0.999), h(0.001, 50.0)], False, 5.0)  # a new leader starts over
    assert not t.update([h(1.0, r=8.0)], True, 10.0)  # alone but spread out


# ---------------------------------------------------------------------------------------------- filter level


def street(x0: float, y0: float, marker: bool, rng_seed: int = 3):
    """A 160 m street along x at ``y0``: the same irregular buildings on both sides every time (the same
    seed), and with ``marker`` a block standing in the road's verge at x0 + 95 m that only this copy has."""
    rng = np.random.default_rng(rng_seed)
    parts = []
    x = x0 - 10.0
    while x < x0 + 150.0:
        for side in (-1.0, 1.0):
            length, depth, height = rng.uniform(6, 14), rng.uniform(6, 10), rng.uniform(4, 12)
            setback = rng.uniform(7.0, 10.0)
            parts.append(
                meshgen.box(
                    (length, depth, height),
                    (x + length / 2, y0 + side * (setback + depth / 2), height / 2 - 0.5),
                    cell_m=3.0,
                )
            )
        x += rng.uniform(14.0, 22.0)
    if marker:
        parts.append(meshgen.box((8.0, 2.5, 4.0), (x0 + 95.0, y0 + 5.5, 1.5), cell_m=2.0))
    return parts


@pytest.fixture(scope="module")
def twin_streets():
    ground = meshgen.grid_patch((-40.0, -40.0, 0.0), (260.0, 0, 0), (0, 200.0, 0), 65, 50)
    parts = [ground, *street(0.0, 0.0, marker=True), *street(0.0, 100.0, marker=False)]
    v, f = meshgen.merge(parts)
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="twins")
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    xs = np.arange(-5.0, 150.0, 1.0)
    m.drive_xy = np.vstack(
        [np.column_stack([xs, np.zeros_like(xs)]), np.column_stack([xs, np.full_like(xs, 100.0)])]
    )
    return caster, m


def twin_settings() -> LocalizerSettings:
    s = LocalizerSettings()
    s.particles.global_count = 2000
    s.particles.converged_count = 60
    s.observation = ObservationSettings(rays=200, max_range_m=40.0)
    s.init.drive_radius_m = 3.0
    return s


def as_shipped_prior_search(s: LocalizerSettings) -> LocalizerSettings:
    """The prior search as `configs/prior.yaml` and `configs/fast.yaml` ship it: without version 0.18's
    additions to the default (the vehicle points, `explain_beyond`, `movable_height_m`, the challenge),
    which it was measured without. (With them, on two identical streets matched a dozen cells at a time,
    it converged before the marker: some of these streets' low facades, under 7 m long and 4 m tall, are
    vehicles to an 8-beam sensor that never sees their tops, and leave the scans.)"""
    s.convergence.method = "prior"
    s.convergence.challenge_top = 0
    s.observation.vehicle_length_m = s.observation.movable_height_m = None
    s.observation.explain_beyond = False
    return s


def scan_at(caster, geo, pose):
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([x, y, HEIGHT]), d @ R.T, 40.0)
    return (d[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)


def test_convergence_is_refused_between_identical_streets_and_granted_once_they_differ(twin_streets):
    caster, m = twin_streets
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(360))
    path = np.column_stack([np.arange(0.0, 120.0, 0.8), np.zeros(150), np.zeros(150)])  # along street A
    loc = build_localizer(m, twin_settings(), seed=4, caster=caster)
    loc.spread()
    converged_at, on_b = None, 0
    for k in range(len(path)):
        delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
        info = loc.step(delta, scan_at(caster, geo, path[k]))
        if not info.converged and info.hypotheses:
            on_b = max(on_b, sum(h.share for h in loc.hypotheses if h.centroid[1] > 50.0))
        if info.converged_now:
            converged_at = k
            break
    assert converged_at is not None
    # refused while both streets were alike: the marker at x = 95 m enters the 40 m range near x = 55 m
    assert path[converged_at, 0] > 50.0, path[converged_at]
    assert on_b > 0.1  # street B really was a contender meanwhile
    assert abs(loc.estimate()[1]) < 1.0 and abs(loc.estimate()[0] - path[converged_at, 0]) < 1.0


@pytest.mark.parametrize("signal", ["inliers", "residual"])
def test_a_removed_object_in_the_map_does_not_make_the_filter_lost(signal):
    """The inlier signal holds; the earlier rule on the best residual (kept as recovery.signal: residual)
    raises a false alarm here, which is why it was replaced."""
    # the map holds a row of parked cars along the street that the drive no longer sees
    parts = [
        meshgen.grid_patch((-20.0, -30.0, 0.0), (160.0, 0, 0), (0, 60.0, 0), 40, 15),
        *street(0.0, 0.0, False),
    ]
    # from x = 40 m on (the first 40 m set the filter's normal level), parked vans line both kerbs
    cars = [meshgen.box((5.0, 2.0, 2.4), (x, -4.5, 1.2), cell_m=1.0) for x in np.arange(40.0, 120.0, 5.5)]
    cars += [meshgen.box((5.0, 2.0, 2.4), (x, 4.5, 1.2), cell_m=1.0) for x in np.arange(42.0, 120.0, 5.5)]
    v_world, f_world = meshgen.merge(parts)
    v_map, f_map = meshgen.merge(parts + cars)
    world = RayCaster(threads=2)
    world.add_mesh(v_world, f_world, name="world")
    m = MeshMap.from_mesh(v_map, f_map, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    geo = RangeImageGeometry.for_spec(load_spec("hdl-64e").with_columns(360))
    path = np.column_stack([np.arange(0.0, 100.0, 0.8), np.zeros(125), np.zeros(125)])
    s = twin_settings()
    s.recovery.signal = signal
    if signal == "residual":
        s.observation.cap_beyond_m = None  # the localizer as it was
    loc = build_localizer(m, s, seed=5)
    loc.start_at(path[0])
    rng = np.random.default_rng(6)
    est, alarms = [], []
    for k in range(len(path)):
        delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
        info = loc.step(delta + rng.normal(0, [0.01, 0.003, 0.002]) * (k > 0), scan_at(world, geo, path[k]))
        est.append(info.estimate)
        if info.recovered:
            alarms.append(k)
            break
    if signal == "residual":
        assert alarms, "the residual rule was expected to raise a false alarm here"
        return
    assert not alarms, f"false alarm at frame {alarms}"
    err = np.hypot(*(np.array(est)[:, :2] - path[:, :2]).T)
    assert err.max() < 0.5
    # the cars really were there to be missed: many rays read longer than the map
    loc.model.set_scan(*_rays(loc, scan_at(world, geo, path[60])))
    beyond = loc.model.scores(path[60][None], loc.sensor_z(path[60][None, :2]))["beyond"][0]
    assert beyond > 0.1


def _rays(loc, points):
    r = np.linalg.norm(points, axis=1)
    ok = (r > 2.0) & (r < 40.0)
    return points[ok] / r[ok, None], r[ok]


def test_a_satellite_of_the_leader_is_no_rival():
    from rangemcl.localization.hypotheses import Hypothesis

    def h(share, x):
        return Hypothesis(0, share, math.log(share), 10, np.array([x, 0.0, 0.0]), 1.0)

    t = ConvergenceTest(margin_nats=5.0, min_distance_m=0.0, compact_radius_m=3.0, separation_m=5.0)
    assert t.update([h(0.7, 0.0), h(0.29, 4.0), h(0.001, 40.0)], True, 1.0)  # 4 m behind: same place
    assert t.margin == pytest.approx(math.log(0.7 / 0.001))
    assert not t.update([h(0.7, 0.0), h(0.29, 6.0), h(0.001, 40.0)], True, 1.0)  # 6 m: a rival


@pytest.mark.parametrize("second_opinion", [True, False])
def test_the_second_opinion_vetoes_alarms_where_no_other_place_fits_better(second_opinion):
    """A lorry row the map never had hides part of the street; with a watch made touchy on purpose it
    raises suspicions, and the second opinion (the prior's best places for the scan, scored alike) finds
    no place that fits better, so the filter stays, and counts the vetoes; without it, the same
    suspicion re-spreads the particles (a false alarm)."""
    parts = [
        meshgen.grid_patch((-20.0, -30.0, 0.0), (160.0, 0, 0), (0, 60.0, 0), 40, 15),
        *street(0.0, 0.0, False),
    ]
    lorries = [meshgen.box((8.0, 2.5, 3.5), (x, 4.5, 1.75), cell_m=1.0) for x in np.arange(40.0, 90.0, 9.0)]
    v_map, f_map = meshgen.merge(parts)
    v_world, f_world = meshgen.merge(parts + lorries)
    world = RayCaster(threads=2)
    world.add_mesh(v_world, f_world, name="world")
    m = MeshMap.from_mesh(v_map, f_map, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    xs = np.arange(-5.0, 140.0, 1.0)
    m.drive_xy = np.column_stack([xs, np.zeros_like(xs)])
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(360))
    path = np.column_stack([np.arange(0.0, 100.0, 0.8), np.zeros(125), np.zeros(125)])
    s = twin_settings()
    s.recovery.second_opinion = second_opinion
    s.recovery.inlier_factor = 0.97  # touchy: any dip of the inlier share is a bad update ...
    s.recovery.updates = 2  # ... and two in a row a suspicion
    s.recovery.max_vetoed_updates = 1000  # (the lorries stay in view for most of the drive)
    loc = build_localizer(m, s, seed=5)
    loc.start_at(path[0])
    rng = np.random.default_rng(6)
    err, recovered, vetoed = [], [], 0
    for k in range(len(path)):
        delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
        info = loc.step(delta + rng.normal(0, [0.01, 0.003, 0.002]) * (k > 0), scan_at(world, geo, path[k]))
        err.append(float(np.hypot(*(info.estimate[:2] - path[k, :2]))))
        vetoed += info.vetoed
        if info.recovered:
            recovered.append(k)
            break
    if not second_opinion:
        assert recovered, "the touchy watch was expected to raise an alarm here"
        return
    assert not recovered, f"false alarm at frame {recovered} after {vetoed} vetoes"
    assert vetoed >= 1 and loc.vetoed_alarms >= 1  # the watch did raise suspicions
    assert max(err) < 0.5


@pytest.mark.parametrize("consult", [True, False])
def test_over_a_map_within_a_budget_the_second_opinion_finds_a_place_whose_tiles_were_not_held(
    tmp_path, monkeypatch, consult
):
    """Two streets 100 m apart (B with a third of A's buildings), the map in 25 m tiles seen through a
    budget of about half the map (``rangemcl.maps.view.MapView``). The filter is put on street B
    while the car drives street A, and its probation asks the second opinion: street A's tiles are not
    held, so the view loads them in the background (``consult``), and once they are in, the opinion
    scores A's places as the whole map would and the filter declares itself lost, a few updates after
    the filter with the map held whole. Without ``consult`` A's places are scored against tiles that are
    not there, and the wrong street stands (for more than three times as
    many updates as with the whole map, if not to the end)."""
    from rangemcl.maps.view import MapView

    ground = meshgen.grid_patch((-40.0, -40.0, 0.0), (260.0, 0, 0), (0, 200.0, 0), 65, 50)
    v, f = meshgen.merge([ground, *street(0.0, 0.0, False, 3), *street(0.0, 100.0, False, 11)[::3]])
    world = RayCaster(threads=2)
    world.add_mesh(v, f, name="world")
    m = MeshMap.from_mesh(v, f, tile_size_m=25.0, meta={"sensor_height_m": HEIGHT})
    xs = np.arange(-5.0, 150.0, 1.0)
    m.drive_xy = np.vstack([np.column_stack([xs, np.zeros_like(xs)]), np.column_stack([xs, xs * 0 + 100])])
    m.save(tmp_path / "map")
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(360))
    path = np.column_stack([np.arange(20.0, 60.0, 0.8), np.zeros(50), np.zeros(50)])  # along street A
    wrong = path[0] + [0.0, 100.0, 0.0]  # the same spot of street B

    def run(mesh_map, caster):
        settings = twin_settings()
        # a narrower second opinion than the default (30 places, 8 looked at again): the default's wider
        # one also finds street B driven the other way 25 m on, which fits the scans better than the
        # filter's pose on B, and declares the filter lost without street A's tiles, so that this test
        # would no longer show what consulting the view does
        settings.recovery.opinion_top = 30
        settings.recovery.polish_places = 8
        loc = build_localizer(mesh_map, settings, seed=7, caster=caster)
        loc.start_at(wrong)
        loc.lost.start_probation()
        for k in range(len(path)):
            delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
            info = loc.step(delta, scan_at(world, geo, path[k]))
            if info.recovered:
                return k
        return None

    whole = run(MeshMap.load(tmp_path / "map"), None)  # (renders the place prior into the map folder)
    assert whole is not None and whole <= 10
    if not consult:
        monkeypatch.delattr(MapView, "consult")
    sizes = [
        62 * e.triangles + 12 * e.vertices for e in MapView(tmp_path / "map", 1e3, RayCaster()).store.entries
    ]
    caster = RayCaster(threads=2)
    view = MapView(tmp_path / "map", 0.5 * sum(sizes) / 1e6 + 1.0, caster)
    try:
        k = run(view, caster)
        if consult:
            assert view.unscored_places > 0  # the true street's tiles were asked for, not held at first
            assert k is not None and k <= 10  # within as many updates as the whole map is allowed
            assert view.cache.peak_bytes <= view.cache.budget_bytes
        else:  # the wrong street stands far longer (lost at update 37 of 50 when this was written)
            assert k is None or k > 3 * whole
    finally:
        view.close()


class _ScriptedStreets(ScoringModel):
    """An observation model with a known answer, so that the search's bookkeeping is what is tested:
    particles at the true pose score 0, those at the same spot of the twin street ``delta`` nats less per
    update (a look-alike that fits each scan a little worse), everything else far less."""

    def __init__(self, delta: float):
        self.delta = delta
        self.truth = np.zeros(3)
        self._truth_of: dict[bytes, np.ndarray] = {}

    def score(self, rays, particles, sensor_z):
        # a scan is scored against the truth of the update that took it (the search's challenge scores
        # the recent updates' scans again): a scan is known by its ranges
        key = np.asarray(rays.ranges).tobytes()
        truth = self._truth_of.setdefault(key, self.truth.copy())

        def err(p0):
            dxy = np.hypot(particles[:, 0] - p0[0], particles[:, 1] - p0[1])
            dyaw = np.abs(np.angle(np.exp(1j * (particles[:, 2] - p0[2]))))
            return dxy**2 + (5.0 * dyaw) ** 2

        twin = truth + np.array([0.0, 100.0, 0.0])
        loglik = np.maximum(np.maximum(-err(truth), -self.delta - err(twin)), -12.0)
        self.last_inliers = np.full(len(particles), 0.9)
        return loglik, 1.0 - np.exp(loglik)


@pytest.mark.parametrize("search", ["always injecting", "default"])
def test_a_look_alike_refreshed_by_the_prior_every_update_caps_the_margin_until_the_injection_stops(
    twin_streets, search
):
    """Two identical streets (the marker aside), a look-alike that fits every scan 0.1 nats worse than
    the true street (a scripted observation; the place prior, the injections, the clusters and the test
    are the filter's own; the prior's 6 best places per scan). Injecting the prior's fresh particles into
    every place it ranks high at 5 % of the weight at every update (``init.inject_below_share: 1``) tops
    the look-alike up every update: it holds about 0.05 / places / (1 - e^-0.1) of the weight, so the
    leader's margin stalls below the test's 6 nats (about 4-4.5 here). The default stops the injection
    while a hypothesis holds 90 % of the weight: the look-alike's share then falls by e^-0.1 per update
    and the test decides, for the true street."""
    caster, m = twin_streets
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(360))
    # 120 m: over seeds 1-10 the default of version 0.17 converges after 52-67 updates, 0.18's after 57-85
    path = np.column_stack([np.arange(0.0, 120.0, 1.0), np.zeros(120), np.zeros(120)])
    s = twin_settings()
    s.init.inject_top = 6
    if search == "always injecting":
        s.init.inject_below_share = 1.0
    loc = build_localizer(m, s, seed=9, caster=caster)
    model = _ScriptedStreets(0.1)
    loc.scorer = model
    loc.spread()
    converged_at, margins = None, []
    for k in range(len(path)):
        model.truth = path[k]
        delta = se2_between(path[k - 1], path[k]) if k else np.zeros(3)
        info = loc.step(delta, scan_at(caster, geo, path[k]))
        if info.converged_now:
            converged_at = k
            break
        margins.append(loc.convergence_test.margin)
    if search == "always injecting":
        assert converged_at is None
        assert 3.0 < max(margins[40:]) < 5.5, margins[40:]
        return
    assert converged_at is not None, margins
    assert np.hypot(*(loc.estimate()[:2] - path[converged_at, :2])) < 1.0


def k_streets(k: int, pitch_m: float = 60.0):
    """``k`` copies of the same street ``pitch_m`` apart, the first with the marker (:func:`street`), and a
    map whose mapping drive runs along each of them."""
    width = pitch_m * k + 40.0
    ground = meshgen.grid_patch((-40.0, -40.0, 0.0), (260.0, 0, 0), (0, width, 0), 65, int(width / 4))
    parts = [ground]
    for i in range(k):
        parts += street(0.0, pitch_m * i, marker=i == 0)
    v, f = meshgen.merge(parts)
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name=f"streets{k}")
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    xs = np.arange(-5.0, 150.0, 1.0)
    m.drive_xy = np.vstack([np.column_stack([xs, np.full_like(xs, pitch_m * i)]) for i in range(k)])
    return caster, m


@pytest.mark.parametrize("k", [2, 4, 8])
def test_a_sparse_sensor_waits_for_the_one_distinct_street_among_k_identical_ones(k):
    """k identical streets, one of which has a marker at x = 95 m; an 8-beam sensor whose beams all point
    below the horizon (the MQ-8) drives along the marked one. Until the marker comes within the 40 m the
    rays reach (x > 55 m), every street explains the scans equally well, so the search must not converge;
    then it must converge on the marked street. The sequential test alone weighs the leader against the
    rivals the cloud holds, and the cloud loses some street's copy of the car's place as it resamples:
    without the challenge (the place prior's places for the scan, judged over the recent scans), this
    converged on a twin street before the marker for k = 4 and 8 when it was written (and, with other
    seeds, for k = 2: before any distinct evidence, on either street)."""
    caster, m = k_streets(k)
    geo = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(360))
    path = np.column_stack([np.arange(0.0, 140.0, 0.8), np.zeros(175), np.zeros(175)])
    s = twin_settings()
    s.convergence.challenge_top = 100  # the default, explicit: the test is about it
    s.particles.global_count = 1000  # (CI time: the search shrinks its cloud to this size anyway)
    s.observation = ObservationSettings(rays=100, max_range_m=40.0)
    loc = build_localizer(m, s, seed=1, caster=caster)
    loc.spread()
    converged_at = None
    for i in range(len(path)):
        delta = se2_between(path[i - 1], path[i]) if i else np.zeros(3)
        if loc.step(delta, scan_at(caster, geo, path[i])).converged_now:
            converged_at = i
            break
    assert converged_at is not None
    assert path[converged_at, 0] > 55.0, path[converged_at]
    est = loc.estimate()
    assert abs(est[1]) < 1.0 and abs(est[0] - path[converged_at, 0]) < 1.0, (est, path[converged_at])


@pytest.mark.parametrize("rendering", ["exact", "planar"])
def test_a_wrong_convergence_planted_in_a_run_is_caught_within_10_frames(rendering):
    """Two identical streets, the car's with the marker; an 8-beam sensor below the horizon. The filter
    tracks the car past the marker's approach, then its cloud is planted on the twin street, at the same
    place along it, as if a search had converged there (the probation starts). The twin explains every
    scan but the marker's rays as well as the true place does, so the signal watch sees little; the
    probation's challenge judges the prior's places over the recent scans, where the marker speaks for
    the true street: the filter must give up the twin within 10 frames; also with the challenge's grids
    and the second opinion rendered planar (`observation.rendering: planar`)."""
    caster, m = k_streets(2)
    geo = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(360))
    path = np.column_stack([np.arange(0.0, 140.0, 0.8), np.zeros(175), np.zeros(175)])
    s = twin_settings()
    s.convergence.challenge_top = 100  # the default, explicit: the test is about it
    s.observation.rendering = rendering
    loc = build_localizer(m, s, seed=2, caster=caster)
    loc.start_at(path[50])
    for i in range(51, 100):  # x = 40 .. 79 m: the marker (x = 95 m) comes into view
        loc.step(se2_between(path[i - 1], path[i]), scan_at(caster, geo, path[i]))
    assert np.hypot(*(loc.estimate()[:2] - path[99, :2])) < 0.5
    loc.particles[:, 1] += 60.0  # the twin street, as a search that converged there would leave it
    loc.last_estimate = loc.last_estimate + np.array([0.0, 60.0, 0.0])
    loc._converge(search=True, settle=True)
    caught = None
    for i in range(100, 111):
        info = loc.step(se2_between(path[i - 1], path[i]), scan_at(caster, geo, path[i]))
        if info.recovered:
            caught = i - 99
            break
    assert caught is not None and caught <= 10, caught
    assert not loc.converged or abs(loc.estimate()[1]) < 1.0  # gave the twin up


@pytest.mark.parametrize("k, cells_per_update", [(2, 12), (8, None)])
def test_the_prior_search_waits_for_the_one_distinct_street_among_k_identical_ones(
    k, cells_per_update, monkeypatch
):
    """The same streets and sensor with the prior search (`convergence.method: prior`): a few dozen
    hypotheses born from the place prior, each searched on local grids rendered planar about it, a newborn
    judged over the recent scans against the leader. Every street explains the scans alike until the
    marker comes within reach (x > 55 m): the search must not converge before, then converge on the marked
    street, with hypotheses on the twin streets until then; also when the prior's cells are matched a
    slice at a time (``cells_per_update``: a dozen, the prior holding some eighty)."""
    from rangemcl.localization import prior_search

    if cells_per_update is not None:
        monkeypatch.setattr(prior_search, "PRIOR_SEARCH_CELLS_PER_UPDATE", cells_per_update)
    caster, m = k_streets(k)
    geo = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(360))
    path = np.column_stack([np.arange(0.0, 140.0, 0.8), np.zeros(175), np.zeros(175)])
    s = twin_settings()
    s.observation = ObservationSettings(rays=100, max_range_m=40.0)
    s = as_shipped_prior_search(s)
    loc = build_localizer(m, s, seed=1, caster=caster)
    loc.spread()
    converged_at, streets = None, set()
    for i in range(len(path)):
        delta = se2_between(path[i - 1], path[i]) if i else np.zeros(3)
        info = loc.step(delta, scan_at(caster, geo, path[i]))
        if info.converged_now:
            converged_at = i
            break
        if path[i, 0] < 50.0 and info.hypotheses:  # the streets the hypotheses stand on
            streets |= {int(round(h.centroid[1] / 60.0)) for h in loc.hypotheses}
    assert converged_at is not None
    assert path[converged_at, 0] > 55.0, path[converged_at]
    est = loc.estimate()
    assert abs(est[1]) < 1.0 and abs(est[0] - path[converged_at, 0]) < 1.0, (est, path[converged_at])
    assert len(streets) >= min(k, 2)  # the twins were held as rivals, not left out
    if cells_per_update is not None:
        prior = loc.beam_prior or loc.prior
        assert len(prior.xy) > 5 * cells_per_update and loc._prior_slice > 5  # sliced, as asked


def test_the_prior_search_refuses_a_map_held_within_a_budget():
    """Its hypotheses are born where the place prior points, whose tiles a budget may not hold: one clear
    error, not scores against missing tiles."""
    caster, m = k_streets(2)
    m.__class__ = type("BudgetedMap", (MeshMap,), {"budgeted": True})
    s = twin_settings()
    s.convergence.method = "prior"
    with pytest.raises(InputError, match="'prior': not yet for a map held within a memory budget"):
        build_localizer(m, s, seed=1, caster=caster)


@pytest.mark.parametrize("shipped", [True, False])
def test_the_prior_search_carries_its_rivals_through_the_probation_and_undoes_a_wrong_convergence(shipped):
    """The prior search's probation (the search goes on beside the tracking instead of second opinions).
    A correct convergence on the marked street of two is left alone through it. Then a convergence is
    planted on the twin street with the marker in reach, the true street left as the rival it beat by a
    nat, as a search that converged on the twin would leave them: the true street's
    evidence overtakes the twin's and the convergence is undone within the probation's 10 updates (the
    search takes up again, no spread), and the search converges again, on the marked street. As shipped
    and with today's defaults, whose challenge of the particle search it leaves alone (its newborns and
    rivals play that part: the challenge reopened a search of particles it does not hold)."""
    caster, m = k_streets(2)
    geo = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(360))
    path = np.column_stack([np.arange(0.0, 140.0, 0.8), np.zeros(175), np.zeros(175)])
    s = twin_settings()
    s.observation = ObservationSettings(rays=100, max_range_m=40.0, rendering="planar")
    s = as_shipped_prior_search(s) if shipped else s
    s.convergence.method = "prior"
    loc = build_localizer(m, s, seed=1, caster=caster)
    loc.spread()
    converged_at = None
    for i in range(len(path)):
        delta = se2_between(path[i - 1], path[i]) if i else np.zeros(3)
        info = loc.step(delta, scan_at(caster, geo, path[i]))
        if converged_at is None and info.converged_now:
            converged_at = i
            assert loc._rivals is not None and loc.lost._probation == 0  # rivals, not opinions
        elif converged_at is not None:
            assert not info.recovered  # the correct convergence stands through its probation
            if i >= converged_at + 12:
                break
    assert converged_at is not None and loc._rivals is None  # the probation is over
    assert abs(loc.estimate()[1]) < 1.0
    # planted: converged on the twin street (y = 60) at x = 79.2 m, the true street a nat behind
    k = 99
    loc = build_localizer(m, s, seed=2, caster=caster)
    loc.start_at(path[k] + np.array([0.0, 60.0, 0.0]))
    lead = loc.particles[int(np.argmax(loc.log_w))]
    loc._keep_rivals(np.vstack([lead, path[k]]), np.array([0.0, -1.0]), np.array([1000, 1001]))
    loc._converge(search=True, settle=True)
    undone, again = None, None
    for i in range(k + 1, len(path)):
        info = loc.step(se2_between(path[i - 1], path[i]), scan_at(caster, geo, path[i]))
        if undone is None and info.recovered:
            undone = i - k
            assert info.particles < s.particles.global_count  # not a spread: the hypotheses go on
        if undone is not None and info.converged_now:
            again = i
            break
    assert undone is not None and undone <= 10, undone
    assert again is not None and abs(loc.estimate()[1]) < 1.0, loc.estimate()
