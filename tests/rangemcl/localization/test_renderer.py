"""The particle renderer (the residuals of paper Eq. 5 in one kernel) against a reference built from plain
ray casts, its ranking of the true pose, and Eq. 5 as the range model's likelihood."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.errors import InputError
from rangemcl.localization.models import RangeModel
from rangemcl.localization.renderer import (
    PLANAR_WITHIN_DEG,
    PLANAR_WITHIN_M,
    ParticleRenderer,
    planar_references,
)
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.sensors import load_spec


@pytest.fixture(scope="module")
def scene():
    town = meshgen.town(seed=2, size_m=100.0, n_buildings=15, n_poles=20, facade_cell_m=2.0)
    caster = RayCaster(threads=2)
    caster.add_mesh(*town.merged(), name="town")
    x, y, yaw = float(town.road_xy[0]) + 3.0, float(town.road_xy[1]), 0.4
    z = float(meshgen.town_ground_height(x, y)) + 1.73
    geo = RangeImageGeometry.for_spec(load_spec("hdl-32e").with_columns(90))
    dirs = geo.directions.reshape(-1, 3)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    hits = caster.cast(np.array([x, y, z]), dirs @ R.T, 100.0)
    keep = hits.hit
    return caster, np.array([x, y, yaw]), z, dirs[keep], hits.ranges[keep]


def reference_residuals(
    caster, particles, z, dirs, measured, margin, cap, beyond=None, short=None, top=np.inf, explain=False
):
    """d of Eq. 5 by casting each particle's rays with RayCaster.cast and reducing in numpy: each ray's
    |measured - rendered| (``margin`` where the map has nothing within it) at most ``cap``; at most
    ``beyond`` where measured more than ``cap`` beyond the map's surface, at most ``short`` where measured
    more than ``cap`` short of it or where the map has nothing (None: ``cap``); ``beyond`` only where the
    map's surface, ``short`` only where the measured point, lies below the sensor-frame height ``top``;
    with ``explain``, ``beyond`` only where the map has a surface within ``cap`` of the measured point."""
    beyond = cap if beyond is None else beyond
    short = cap if short is None else short
    out = []
    for (x, y, yaw), zi in zip(particles, z, strict=True):
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        t = caster.cast(np.array([x, y, zi]), dirs @ R.T, measured + margin).ranges
        hit = np.isfinite(t)
        e = np.where(hit, measured - t, -margin)
        gone = dirs[:, 2] * np.where(hit, t, 0.0) < top
        if explain:  # cast from cap short of each measured point, 2 cap long
            ahead = (dirs @ R.T) * (measured - cap)[:, None]
            gone &= np.isfinite(caster.cast(np.array([x, y, zi]) + ahead, dirs @ R.T, 2.0 * cap).ranges)
        low = dirs[:, 2] * measured < top
        limit = np.where((e > cap) & gone, beyond, np.where((e < -cap) & low, short, cap))
        out.append(np.minimum(np.abs(e), limit).mean())
    return np.array(out)


@pytest.mark.parametrize(
    "cap, beyond, short, top, explain",
    [
        (np.inf, None, None, None, False),
        (1.0, None, None, None, False),
        (1.0, 0.5, None, None, False),
        (1.0, 0.5, 0.3, None, False),
        (1.0, 0.5, 0.3, 0.5, False),  # changes only up to 0.5 m above the sensor (2.2 m above the ground)
        (1.0, 0.5, 0.3, -1.0, False),
        (1.0, 0.5, 0.3, None, True),
        (1.0, 0.5, 0.3, 0.5, True),
    ],
)
def test_kernel_matches_plain_ray_casts(scene, cap, beyond, short, top, explain):
    caster, true, z, dirs, measured = scene
    rng = np.random.default_rng(0)
    particles = true + rng.normal(0, [1.0, 1.0, 0.1], size=(40, 3))
    zs = np.full(40, z)
    model = ParticleRenderer(
        caster, margin_m=2.0, cap_m=cap, cap_beyond_m=beyond, cap_short_m=short, explain_beyond=explain
    )
    model.set_scan(dirs, measured, change_top_z=top)
    got = model.mean_residuals(particles, zs)
    ref = reference_residuals(
        caster,
        particles,
        zs,
        dirs,
        measured,
        2.0,
        cap,
        beyond,
        short,
        np.inf if top is None else top,
        explain,
    )
    # the kernel's costs in numpy (what the tools use), ray by ray, average to the same d
    for (x, y, yaw), zi, d in zip(particles[:5], zs, got, strict=False):
        c, s = np.cos(yaw), np.sin(yaw)
        world = dirs @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])
        t = caster.cast(np.array([x, y, zi]), world, measured + 2.0).ranges
        e = np.where(np.isfinite(t), measured - t, -np.inf)
        heights = (dirs[:, 2] * measured, dirs[:, 2] * np.nan_to_num(t, posinf=0.0))
        ahead = np.array([x, y, zi]) + world * (measured - min(cap, 1e9))[:, None]
        behind = np.isfinite(caster.cast(ahead, world, 2.0 * min(cap, 1e9)).ranges) if explain else None
        assert model.ray_costs(e, *heights, behind).mean() == pytest.approx(d, rel=1e-4, abs=1e-4)
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)


def test_true_pose_scores_best(scene):
    caster, true, z, dirs, measured = scene
    offsets = [
        (dx, dy, dyaw) for dx in (-1, -0.3, 0, 0.3, 1) for dy in (-1, 0, 1) for dyaw in (-0.05, 0, 0.05)
    ]
    particles = true + np.array(offsets)
    model = ParticleRenderer(caster)
    model.set_scan(dirs, measured)
    d = model.mean_residuals(particles, z)
    k_true = offsets.index((0, 0, 0))
    assert d[k_true] < 1e-3
    assert np.argmin(d) == k_true and np.sort(d)[1] > 0.02
    ll = RangeModel(model, sigma_m=2.0).log_likelihood(d)
    assert np.argmax(ll) == k_true and ll[k_true] == pytest.approx(-0.5 * d[k_true] ** 2 / 4.0)


def test_bad_input(scene):
    caster, true, z, dirs, measured = scene
    model = ParticleRenderer(caster)
    with pytest.raises(InputError, match="no scan"):
        model.mean_residuals(true[None], z)
    with pytest.raises(InputError, match="ranges"):
        model.set_scan(dirs, -measured)
    model.set_scan(dirs, measured)
    with pytest.raises(InputError, match="particles"):
        model.mean_residuals(np.array([[np.nan, 0, 0]]), z)
    with pytest.raises(InputError, match="sigma"):
        RangeModel(model, sigma_m=0)
    with pytest.raises(InputError, match="margin"):
        ParticleRenderer(caster, margin_m=0)
    assert model.mean_residuals(np.zeros((0, 3)), z).shape == (0,)


def test_particles_far_apart_cast_in_groups_with_the_same_scores():
    """A map held as many tiles and particles spread over all of it (a global search within a memory
    budget): the particles are scored in groups of nearby ones, each group's rays cast into the tiles near
    it only, and every score (histogram included) is what one launch over all tiles gives."""
    rng = np.random.default_rng(3)
    caster = RayCaster("cpu", threads=2)
    for i in range(6):
        for j in range(6):
            v, f = meshgen.box(np.array([8.0, 8.0, 5.0]), np.array([40.0 * i, 40.0 * j, 2.5]), cell_m=2.0)
            caster.add_mesh(v, f)
    renderer = ParticleRenderer(caster, margin_m=2.0, cap_m=1.0)
    dirs = rng.normal(size=(60, 3)) * [1.0, 1.0, 0.15]
    renderer.set_scan(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), rng.uniform(2.0, 12.0, 60))
    particles = np.column_stack(
        [rng.uniform(-10, 210, 400), rng.uniform(-10, 210, 400), rng.uniform(-3, 3, 400)]
    )
    z = np.full(400, 1.7)
    groups = renderer._groups(particles)
    assert len(groups) > 10 and sorted(np.concatenate(groups)) == list(range(400))
    got = renderer.scores(particles, z, hist_bins=8, hist_top_m=20.0)
    renderer._groups = lambda p: [np.arange(len(p))]  # one launch over every tile
    ref = renderer.scores(particles, z, hist_bins=8, hist_top_m=20.0)
    for k in ("mean", "agree", "beyond", "structure", "hist"):
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
    assert (ref["agree"] > 0).sum() > 20  # some particles do see a box


def _buildings(y0: float, seed: int) -> list:
    """Irregular blocks on both sides of a street along x at ``y0`` (``seed``: which blocks)."""
    rng = np.random.default_rng(seed)
    parts, x = [], -30.0
    while x < 60.0:
        for side in (-1.0, 1.0):
            length, depth, height = rng.uniform(6, 14), rng.uniform(6, 10), rng.uniform(4, 12)
            setback = rng.uniform(7.0, 10.0)
            centre = (x + length / 2, y0 + side * (setback + depth / 2), height / 2 - 0.5)
            parts.append(meshgen.box((length, depth, height), centre, cell_m=3.0))
        x += rng.uniform(14.0, 22.0)
    return parts


def _parked_cars(y0: float) -> list:
    """A row of parked cars on the street's verge, one every 9 m."""
    return [
        meshgen.box((4.4, 1.8, 1.5), (x, y0 + 5.0, 0.75), cell_m=1.0) for x in np.arange(-20.0, 40.0, 9.0)
    ]


def test_a_street_whose_parked_cars_are_new_beats_another_whose_mapped_cars_line_up_with_them():
    """An 8-beam sensor pointing down (the MQ-8) on street A, where cars have parked since the mapping
    drive; the map's other street B has its own buildings and, from the mapping drive, cars parked just
    where A's are now. At A the cars' rays end short of the map's surface (an object the map lacks); at B
    they agree, while B's buildings contradict the scan (rays pass through mapped facades, or end short of
    them). With every short ray costing the full cap, B explains the scan better than the car's own street
    (the wrong place that a sparse sensor's search converged on in a generated town); with rays
    measured more than the cap short costing the agreement distance (``cap_short_m``) the true street is
    the better one."""
    ground = meshgen.grid_patch((-40.0, -30.0, 0.0), (120.0, 0, 0), (0, 120.0, 0), 30, 30)
    world = RayCaster(threads=2)
    world.add_mesh(*meshgen.merge([ground, *_buildings(0.0, 3), *_parked_cars(0.0)]))
    mapped = RayCaster(threads=2)
    mapped.add_mesh(*meshgen.merge([ground, *_buildings(0.0, 3), *_buildings(60.0, 4), *_parked_cars(60.0)]))
    geo = RangeImageGeometry.for_spec(load_spec("mq-8").with_columns(720))
    dirs = geo.directions.reshape(-1, 3)
    hits = world.cast(np.array([0.0, 0.0, 1.73]), dirs, 40.0)
    a_and_b = np.array([[0.0, 0.0, 0.0], [0.0, 60.0, 0.0]])
    d = {}
    for short in (None, 0.3):
        model = ParticleRenderer(mapped, margin_m=2.0, cap_m=1.0, cap_beyond_m=0.5, cap_short_m=short)
        model.set_scan(dirs[hits.hit], hits.ranges[hits.hit])
        d[short] = model.mean_residuals(a_and_b, np.full(2, 1.73))
    assert d[None][1] < 0.8 * d[None][0], d  # every short ray at the cap: street B wins
    assert d[0.3][0] < 0.9 * d[0.3][1], d  # far-short rays 0.3 m: the car's own street wins


@pytest.mark.parametrize("sensor", ["mq-8", "hdl-64e"])
def test_rays_seen_past_removed_cars_cost_alike_and_rays_through_the_map_into_nothing_cost_more(sensor):
    """The map holds a row of cars parked on the street during the mapping drive; today they are gone,
    so at the true pose many rays read beyond the map's cars, ending on the road or the facades behind
    them (which the map holds). ``explain_beyond`` charges ``cap_beyond_m`` only to rays like those: the
    true pose's cost is the same with it, while every wrong pose (shifted, turned, or anywhere along the
    street) costs more, since its rays that pass through mapped surfaces mostly end where the map has
    nothing."""
    ground = meshgen.grid_patch((-40.0, -30.0, 0.0), (120.0, 0, 0), (0, 120.0, 0), 30, 30)
    world = RayCaster(threads=2)
    world.add_mesh(*meshgen.merge([ground, *_buildings(0.0, 3)]))
    mapped = RayCaster(threads=2)
    mapped.add_mesh(*meshgen.merge([ground, *_buildings(0.0, 3), *_parked_cars(0.0)]))
    geo = RangeImageGeometry.for_spec(load_spec(sensor).with_columns(720))
    dirs = geo.directions.reshape(-1, 3)
    hits = world.cast(np.array([0.0, 0.0, 1.73]), dirs, 40.0)
    rng = np.random.default_rng(1)
    wrong = np.column_stack(
        [rng.uniform(-20, 40, 30), rng.uniform(-3, 3, 30), rng.uniform(-np.pi, np.pi, 30)]
    )
    poses = np.vstack([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi], [5.0, 0.0, 0.0], [0.0, 0.0, 0.3], wrong])
    poses = poses[
        (np.hypot(poses[:, 0], poses[:, 1]) > 1.0)
        | (np.abs(poses[:, 2]) > 0.1)
        | (np.arange(len(poses)) == 0)
    ]
    d = {}
    for explain in (False, True):
        model = ParticleRenderer(mapped, margin_m=2.0, cap_m=1.0, cap_beyond_m=0.5, explain_beyond=explain)
        model.set_scan(dirs[hits.hit], hits.ranges[hits.hit])
        d[explain] = model.mean_residuals(poses, np.full(len(poses), 1.73))
    assert model.scores(poses[:1], np.full(1, 1.73))["beyond"][0] > 0.1  # the cars really are missed
    assert d[True][0] == pytest.approx(d[False][0], abs=1e-4)
    assert (d[True][1:] > d[False][1:] + 0.01).all(), d
    assert d[True][0] < d[True][1:].min()


@pytest.mark.parametrize(
    "cap, beyond, short, top, explain",
    [
        (np.inf, None, None, None, False),
        (1.0, 0.5, 0.3, None, False),
        (1.0, 0.5, 0.3, 0.5, True),
    ],
)
def test_planar_rendering_is_exact_where_every_ray_meets_one_plane(cap, beyond, short, top, explain):
    """A slanted wall of two triangles, 2 km wide: every ray of every particle within a metre and three
    degrees of the reference meets the same plane, so the planar rendering (each particle's ray met with
    the plane the reference's ray met) must give the exact rendering's scores, histogram included;
    measured ranges scattered around the wall's, some far beyond it and some far short of it."""
    caster = RayCaster(threads=2)
    n = np.array([-1.0, 0.3, 0.2]) / np.linalg.norm([-1.0, 0.3, 0.2])
    u = np.cross(n, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    centre = np.array([25.0, 0.0, 0.0])
    corners = [centre + 1000.0 * (a * u + b * w) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    caster.add_mesh(np.array(corners), np.array([[0, 1, 2], [0, 2, 3]]), name="wall")
    rng = np.random.default_rng(7)
    ref = np.array([0.0, 0.0, 0.2])
    z = 1.7
    az = rng.uniform(-0.7, 0.7, 300)
    el = rng.uniform(-0.3, 0.4, 300)
    dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    c, s = np.cos(ref[2]), np.sin(ref[2])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    t = caster.cast(np.array([0.0, 0.0, z]), dirs @ R.T, 500.0).ranges
    assert np.isfinite(t).all()
    measured = t + rng.normal(0, 0.2, len(t))
    measured[::7] += 1.8  # seen past something gone
    measured[3::7] -= 1.8  # met something the map lacks
    renderer = ParticleRenderer(
        caster, margin_m=2.0, cap_m=cap, cap_beyond_m=beyond, cap_short_m=short, explain_beyond=explain
    )
    renderer.set_scan(dirs, measured, structure=rng.random(len(t)) < 0.7, change_top_z=top)
    particles = ref + rng.uniform([-1.0, -1.0, -0.05], [1.0, 1.0, 0.05], (50, 3))
    zs = z + rng.uniform(-0.1, 0.1, 50)
    exact = renderer.scores(particles, zs, hist_bins=12, hist_top_m=60.0)
    planar = renderer.scores(particles, zs, hist_bins=12, hist_top_m=60.0, about=(*ref, z))
    for key in ("mean", "agree", "beyond", "structure"):
        np.testing.assert_allclose(planar[key], exact[key], atol=2e-4, err_msg=key)
    np.testing.assert_array_equal(planar["hist"], exact["hist"])
    assert exact["mean"].std() > 0.05  # the particles do differ
    # several references in one launch (a search's local grids): each particle about its own
    refs = np.array([[*ref, z], [0.3, -0.2, 0.19, z + 0.05], [-0.2, 0.25, 0.21, z - 0.05]])
    of = np.arange(len(particles)) % 3
    multi = renderer.scores(particles, zs, hist_bins=12, hist_top_m=60.0, about=refs, about_of=of)
    for key in ("mean", "agree", "beyond", "structure"):
        np.testing.assert_allclose(multi[key], exact[key], atol=2e-4, err_msg=key)
    with pytest.raises(InputError, match="reference indices"):
        renderer.scores(particles, zs, about=refs, about_of=of[:-1])


def test_planar_rendering_ranks_a_compact_cloud_as_the_exact_one(scene):
    """In a town, a cloud within decimetres of the reference: the planar rendering gives the reference
    its exact scores and ranks the cloud nearly as the exact rendering does."""
    caster, true, z, dirs, measured = scene
    rng = np.random.default_rng(3)
    renderer = ParticleRenderer(caster, margin_m=2.0, cap_m=1.0, cap_beyond_m=0.5)
    renderer.set_scan(dirs, measured)
    cloud = np.vstack([true, true + rng.normal(0, [0.15, 0.15, 0.005], (80, 3))])
    zs = np.full(len(cloud), z)
    exact = renderer.scores(cloud, zs)
    planar = renderer.scores(cloud, zs, about=(*true, z))
    assert planar["mean"][0] == pytest.approx(exact["mean"][0], abs=1e-4)
    assert planar["agree"][0] == pytest.approx(exact["agree"][0], abs=1e-6)
    assert np.corrcoef(planar["mean"], exact["mean"])[0, 1] > 0.9
    assert np.argmin(planar["mean"]) == np.argmin(exact["mean"]) == 0


def test_planar_references_lie_within_reach_of_every_pose_and_are_few_for_a_grid():
    """Random poses around random centres: each pose's reference lies within PLANAR_WITHIN_M and
    PLANAR_WITHIN_DEG of it, references belong to their pose's centre, a pose at its centre is its own
    reference, and a grid of +-2 m and +-8 degrees (the polish's coarse grid) needs 27 references."""
    rng = np.random.default_rng(5)
    centres = np.column_stack([rng.uniform(-50, 50, (7, 2)), rng.uniform(-np.pi, np.pi, 7)])
    of = rng.integers(0, 7, 2000)
    poses = centres[of] + rng.normal(0, [1.5, 1.5, 0.1], (2000, 3))
    poses[:7], of[:7] = centres, np.arange(7)
    refs, ref_of = planar_references(poses, centres, of)
    r = refs[ref_of]
    assert np.hypot(*(poses[:, :2] - r[:, :2]).T).max() <= PLANAR_WITHIN_M + 1e-9
    turn = np.abs(np.angle(np.exp(1j * (poses[:, 2] - r[:, 2]))))
    assert np.degrees(turn).max() <= PLANAR_WITHIN_DEG + 1e-9
    np.testing.assert_allclose(refs[ref_of[:7]], centres, atol=1e-12)
    owner = {}
    for ref, c in zip(ref_of, of, strict=True):
        assert owner.setdefault(int(ref), int(c)) == c  # a reference serves one centre's poses
    ax = np.arange(-2.0, 2.0 + 1e-9, 0.5)
    ay = np.radians(np.arange(-8.0, 8.0 + 1e-9, 2.0))
    g = np.array(np.meshgrid(ax, ax, ay, indexing="ij")).reshape(3, -1).T
    seed = np.array([[10.0, -3.0, 0.7]])
    c, s = np.cos(0.7), np.sin(0.7)
    grid = np.column_stack([10 + c * g[:, 0] - s * g[:, 1], -3 + s * g[:, 0] + c * g[:, 1], 0.7 + g[:, 2]])
    refs, _ = planar_references(grid, seed, np.zeros(len(grid), np.int64))
    assert len(refs) == 27
    with pytest.raises(InputError, match="centre indices"):
        planar_references(poses, centres, of[:-1])


def test_a_local_grid_rendered_planar_about_its_references_peaks_where_the_exact_one_does(scene):
    """The polish's coarse grid (+-2 m, +-8 degrees) around a pose 1 m and 4 degrees off the truth, in a
    town: rendered about its 27 references it peaks within a grid step of the exact rendering's peak, and
    ranks the grid nearly as the exact rendering does."""
    caster, true, z, dirs, measured = scene
    renderer = ParticleRenderer(caster, margin_m=2.0, cap_m=1.0, cap_beyond_m=0.5)
    renderer.set_scan(dirs, measured)
    seed = np.asarray(true, np.float64) + np.array([1.0, -0.5, np.radians(4.0)])
    ax = np.arange(-2.0, 2.0 + 1e-9, 0.5)
    ay = np.radians(np.arange(-8.0, 8.0 + 1e-9, 2.0))
    g = np.array(np.meshgrid(ax, ax, ay, indexing="ij")).reshape(3, -1).T
    c, s = np.cos(seed[2]), np.sin(seed[2])
    grid = np.column_stack(
        [seed[0] + c * g[:, 0] - s * g[:, 1], seed[1] + s * g[:, 0] + c * g[:, 1], seed[2] + g[:, 2]]
    )
    zs = np.full(len(grid), z)
    refs, ref_of = planar_references(grid, seed[None], np.zeros(len(grid), np.int64))
    exact = renderer.scores(grid, zs)["mean"]
    planar = renderer.scores(grid, zs, about=np.column_stack([refs, np.full(len(refs), z)]), about_of=ref_of)
    planar = planar["mean"]
    a, b = grid[np.argmin(exact)], grid[np.argmin(planar)]
    assert np.hypot(*(a[:2] - b[:2])) <= 0.5 + 1e-9 and abs(a[2] - b[2]) <= np.radians(2.0) + 1e-9
    assert np.hypot(*(a[:2] - np.asarray(true)[:2])) <= 0.5  # the exact peak is at the truth
    assert np.corrcoef(planar, exact)[0, 1] > 0.9
