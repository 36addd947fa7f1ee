"""Scan-to-mesh refinement: a known offset of a scan against a synthetic mesh is recovered to a
centimetre; a corridor's axis, which its walls do not constrain, is left alone; through the filter, a
refinement that pulls towards a place outside the particle cloud is refused and counted."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.localization import LocalizerSettings, ObservationSettings, build_localizer, scan_refiner
from rangemcl.localization.settings import RefineSettings
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import se2_compose, se2_inverse
from rangemcl.sensors import load_spec

HEIGHT = 1.73


def _refiner(caster, **kw):
    """The refiner of the settings (``rangemcl.localization.factory.scan_refiner``), by default the plain
    one: every ray takes part (no height floor) and no band of weak directions; ``kw``: settings."""
    return scan_refiner(caster, RefineSettings(**{"min_hit_height_m": None, "weak_information": None, **kw}))


def _world(parts):
    v, f = meshgen.merge(parts)
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="world")
    return caster, v, f


@pytest.fixture(scope="module")
def yard():
    """Ground and irregular blocks at several orientations around the origin."""
    rng = np.random.default_rng(11)
    parts = [meshgen.grid_patch((-50.0, -50.0, 0.0), (100.0, 0, 0), (0, 100.0, 0), 25, 25)]
    for _ in range(14):
        r, a = rng.uniform(8.0, 30.0), rng.uniform(0, 2 * math.pi)
        size = (rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(3, 8))
        v, f = meshgen.box(size, (0.0, 0.0, size[2] / 2), cell_m=2.0)
        yaw = rng.uniform(0, math.pi)
        c, s = math.cos(yaw), math.sin(yaw)
        v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]]) + [r * math.cos(a), r * math.sin(a), 0.0]
        parts.append((v, f))
    return _world(parts)


def _rays(caster, pose, spec="vlp-16", columns=720, count=600, seed=0):
    """Unit directions (sensor frame) and measured ranges of a noiseless scan taken at ``pose``."""
    geo = RangeImageGeometry.for_spec(load_spec(spec).with_columns(columns))
    d = geo.directions.reshape(-1, 3).astype(np.float64)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    hits = caster.cast(np.array([pose[0], pose[1], HEIGHT]), d @ R.T, 40.0)
    ok = np.flatnonzero(hits.hit & (hits.ranges > 2.0))
    pick = np.random.default_rng(seed).choice(ok, min(count, len(ok)), replace=False)
    return d[pick], hits.ranges[pick].astype(np.float64)


@pytest.mark.parametrize("offset", [(0.3, -0.2, 1.5), (-0.15, 0.25, -1.0), (0.0, 0.0, 0.0)])
def test_a_known_offset_is_recovered_to_a_centimetre(yard, offset):
    caster = yard[0]
    truth = np.array([1.0, -2.0, 0.4])
    d, r = _rays(caster, truth)
    start = truth + np.array([offset[0], offset[1], math.radians(offset[2])])
    ref = _refiner(caster).refine(d, r, start, HEIGHT)
    assert ref is not None and ref.constrained == 3
    assert math.hypot(*(ref.pose[:2] - truth[:2])) < 0.01
    assert abs(math.degrees(ref.pose[2] - truth[2])) < 0.05
    assert ref.cost <= ref.start_cost
    assert ref.correction == pytest.approx(ref.pose - start)


def test_a_corridor_axis_is_left_alone():
    caster, _v, _f = _world(
        [
            meshgen.grid_patch((-60.0, -10.0, 0.0), (120.0, 0, 0), (0, 20.0, 0), 30, 5),
            meshgen.box((120.0, 0.5, 4.0), (0.0, -5.0, 2.0), cell_m=4.0),
            meshgen.box((120.0, 0.5, 4.0), (0.0, 5.0, 2.0), cell_m=4.0),
        ]
    )
    d, r = _rays(caster, np.zeros(3))
    ref = _refiner(caster).refine(d, r, np.array([0.4, 0.3, math.radians(1.0)]), HEIGHT)
    assert ref is not None and ref.constrained == 2
    assert ref.pose[0] == pytest.approx(0.4, abs=1e-3)  # along the walls: nothing to go by
    assert abs(ref.pose[1]) < 0.01 and abs(math.degrees(ref.pose[2])) < 0.05


def test_too_few_rays_on_the_map_give_no_refinement(yard):
    caster = yard[0]
    d, r = _rays(caster, np.zeros(3), count=20)
    assert _refiner(caster, min_inliers=30).refine(d, r, np.zeros(3), HEIGHT) is None


def test_the_filter_refuses_a_refinement_outside_its_cloud(yard):
    """A tight cloud 0.5 m off the true pose: the refinement finds the truth but the correction lies far
    outside the cloud's spread, so the filter refuses it (counted) and keeps its own estimate; with a
    cloud as spread as the correction, the same refinement is taken."""
    caster, v, f = yard
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(720))
    truth = np.array([1.0, -2.0, 0.4])
    dirs = geo.directions.reshape(-1, 3)
    c, s = math.cos(truth[2]), math.sin(truth[2])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    hits = caster.cast(np.array([truth[0], truth[1], HEIGHT]), dirs @ R.T, 40.0)
    scan = (dirs[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)
    wrong = truth + np.array([0.0, 0.5, 0.0])
    motion = np.array([0.3, 0.0, 0.0])  # an update is due after 0.2 m
    start = se2_compose(wrong, se2_inverse(motion))  # the filter predicts ``wrong``

    def first_update(sigma_m):
        st = LocalizerSettings()
        st.observation = ObservationSettings(rays=1000, max_range_m=40.0)  # every direction constrained
        st.particles.tracking_sigma_xy_m = sigma_m
        st.particles.tracking_sigma_yaw_deg = 0.1
        st.refine.max_residual_m = 1.0  # reach the truth from 0.5 m
        st.recovery.enabled = False
        loc = build_localizer(m, st, seed=1, caster=caster)
        loc.start_at(start)
        return loc, loc.step(motion, scan)

    loc, info = first_update(0.01)
    assert info.updated and info.refined == -1 and loc.refused_refinements == 1 and loc.refinements == 0
    assert info.refine_shift_m > 0.4
    assert math.hypot(*(info.estimate[:2] - wrong[:2])) < 0.1  # kept its own estimate
    loc, info = first_update(0.5)
    assert info.refined == 1 and loc.refinements == 1


def _street_with_a_low_box(width_m: float, moved_m: float):
    """Map and scan casters of a street between 6 m walls whose only surface across it is a low box (0.5 m
    deep, ``width_m`` wide, 1.4 m tall) 8 m ahead in the map and ``moved_m`` further on in the scan."""
    street = [
        meshgen.grid_patch((-60.0, -10.0, 0.0), (120.0, 0, 0), (0, 20.0, 0), 30, 5),
        meshgen.box((120.0, 0.5, 6.0), (0.0, -5.0, 3.0), cell_m=4.0),
        meshgen.box((120.0, 0.5, 6.0), (0.0, 5.0, 3.0), cell_m=4.0),
    ]
    casters = [
        _world([*street, meshgen.box((0.5, width_m, 1.4), (8.0 + dx, 0.0, 0.7), cell_m=0.5)])[0]
        for dx in (0.0, moved_m)
    ]
    return casters[0], casters[1]


def test_low_hits_can_be_left_out_so_a_moved_parked_car_does_not_pull():
    """In a street of tall walls the only along-street constraint is a low box (a parked car); in the scan
    it stands 0.3 m further on. With every hit taking part the refinement drags the pose along the street;
    with ``min_hit_height_m`` above the box the street's axis is left where it was."""
    map_caster, scan_caster = _street_with_a_low_box(4.0, 0.3)
    d, r = _rays(scan_caster, np.zeros(3), spec="hdl-64e", count=20000)
    pulled = _refiner(map_caster).refine(d, r, np.zeros(3), HEIGHT, ground_z=0.0)
    assert pulled is not None and pulled.constrained == 3 and pulled.pose[0] < -0.1
    held = _refiner(map_caster, min_hit_height_m=2.0).refine(d, r, np.zeros(3), HEIGHT, ground_z=0.0)
    assert held is not None and held.constrained == 2 and abs(held.pose[0]) < 1e-3
    # a threshold above everything the scan hits (an 8-beam sensor looking down): all hits take part again
    low = _refiner(map_caster, min_hit_height_m=10.0).refine(d, r, np.zeros(3), HEIGHT, ground_z=0.0)
    assert low is not None and np.array_equal(low.pose, pulled.pose)


def test_a_few_rays_on_one_low_surface_do_not_move_the_pose_along_the_street():
    """An 8-beam scan (MQ-8, 500 rays) sees nothing above 2 m, so all its hits take part; in a street of
    walls the only surface across the street is a low barrier, which in the scan stands 0.3 m further on
    (as an unmapped vehicle close before a mapped surface can). Its information along the street (16) is
    above the floor (10) but in the weak band (up to 25): the localizer's settings hold the 0.3 m step
    back and the street's axis stays; a refiner without the weak band lets the barrier pull the pose the
    whole 0.3 m."""
    map_caster, scan_caster = _street_with_a_low_box(9.0, 0.3)
    d, r = _rays(scan_caster, np.zeros(3), spec="mq-8", count=500)
    held = scan_refiner(map_caster, LocalizerSettings().refine).refine(
        d, r, np.zeros(3), HEIGHT, ground_z=0.0
    )
    assert held is not None and held.held == 1 and abs(held.pose[0]) < 1e-3 and abs(held.pose[1]) < 0.01
    plain = _refiner(map_caster, min_hit_height_m=2.0)
    pulled = plain.refine(d, r, np.zeros(3), HEIGHT, ground_z=0.0)
    assert pulled is not None and pulled.constrained == 3 and pulled.pose[0] == pytest.approx(-0.3, abs=0.02)


@pytest.mark.parametrize("moved_m", [0.3, 0.05])
def test_a_weak_direction_takes_small_steps_only(moved_m):
    """The street of the test above with ``weak_information`` (the band from the floor 10 up to 25, where
    the barrier's information of 16 lies): the barrier moved 0.3 m is a step beyond ``weak_step_m``
    (0.1 m), held back (the axis stays, the walls' direction still aligned); moved 0.05 m, the step is
    taken as without the band."""
    map_caster, scan_caster = _street_with_a_low_box(9.0, moved_m)
    d, r = _rays(scan_caster, np.zeros(3), spec="mq-8", count=500)
    start = np.array([0.0, 0.2, 0.0])  # 0.2 m across the street: the walls pull it back
    kw = dict(min_hit_height_m=2.0, min_information=10.0)
    free = _refiner(map_caster, **kw).refine(d, r, start, HEIGHT, ground_z=0.0)
    band = _refiner(map_caster, weak_information=25.0, weak_step_m=0.1, **kw)
    ref = band.refine(d, r, start, HEIGHT, ground_z=0.0)
    assert free is not None and ref is not None
    assert free.pose[0] == pytest.approx(-moved_m, abs=0.02) and abs(free.pose[1]) < 0.01
    assert abs(ref.pose[1]) < 0.01  # across the street: strongly constrained, taken
    if moved_m > 0.1:
        assert ref.held == 1 and abs(ref.pose[0]) < 0.01
    else:
        assert ref.held == 0 and np.array_equal(ref.pose, free.pose)


def test_after_a_convergence_the_low_hits_pull_in_an_offset_along_the_street():
    """A cloud that has just converged 0.4 m off along a street of tall walls (as a global search can
    leave it): in the first updates after the convergence the refinement uses the low surfaces too (here
    a low barrier, the same in map and scan, the only thing across the street) and pulls the estimate
    in; a tracking start taken as exact leaves the street's axis to the particles.
    The rays are drawn with ``tall_share: 0`` (all structure alike): with the default, 60 % of the
    structure rays go to the walls and the barrier's few rays leave the along-street direction below the
    refiner's information floor, so the offset is not pulled in (the estimate stays 0.41 m off); a street
    constrained along its axis by low surfaces only is where the default's tall share gives up this pull.
    3000 rays: with 1000 the barrier's information along the street (11) lies in the weak band (10-25),
    where a 0.4 m step is held back."""
    parts = [
        meshgen.grid_patch((-60.0, -10.0, 0.0), (120.0, 0, 0), (0, 20.0, 0), 30, 5),
        meshgen.box((120.0, 0.5, 6.0), (0.0, -5.0, 3.0), cell_m=4.0),
        meshgen.box((120.0, 0.5, 6.0), (0.0, 5.0, 3.0), cell_m=4.0),
        meshgen.box((0.5, 9.0, 1.4), (8.0, 0.0, 0.7), cell_m=0.5),
    ]
    caster, v, f = _world(parts)
    m = MeshMap.from_mesh(v, f, tile_size_m=60.0, meta={"sensor_height_m": HEIGHT})
    geo = RangeImageGeometry.for_spec(load_spec("hdl-64e").with_columns(720))
    dirs = geo.directions.reshape(-1, 3)
    motion = np.array([0.3, 0.0, 0.0])
    truth = np.zeros(3)
    hits = caster.cast(np.array([0.0, 0.0, HEIGHT]), dirs, 40.0)
    scan = (dirs[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)
    wrong = truth + np.array([-0.4, 0.0, 0.0])  # behind the car along the street

    def first_update(settle):
        st = LocalizerSettings()
        st.observation = ObservationSettings(rays=3000, max_range_m=40.0, tall_share=0.0)
        st.particles.tracking_sigma_xy_m = 0.3
        st.particles.tracking_sigma_yaw_deg = 0.1
        st.refine.max_residual_m = 1.0
        st.recovery.enabled = False
        loc = build_localizer(m, st, seed=3, caster=caster)
        loc.start_at(se2_compose(wrong, se2_inverse(motion)), settle=settle)
        return loc.step(motion, scan)

    settled = first_update(True)
    assert settled.refined == 1 and abs(settled.estimate[0] - truth[0]) < 0.03
    exact = first_update(False)
    assert exact.refined == 1 and exact.refine_shift_m < 0.05  # the axis is left to the particles
