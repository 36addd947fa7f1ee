"""The observation models (paper Eq. 5 and the three baselines): each ranks the true pose above perturbed
poses on a synthetic town; the histogram distance and the surface voxels by their definitions; each model
runs inside the filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.errors import InputError
from rangemcl.localization import LocalizerSettings, ObservationSettings, build_localizer, prepare_rays
from rangemcl.localization.models import MODEL_NAMES, make_model, surface_voxels, wasserstein_1d
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.sensors import load_spec


@pytest.fixture(scope="module")
def scene():
    town = meshgen.town(
        seed=9, size_m=100.0, n_buildings=16, n_poles=20, facade_cell_m=2.0, ground_cell_m=2.0
    )
    v, f = town.merged()
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="town")
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0)
    pose = np.array([float(town.road_xy[0]) + 7.0, float(town.road_xy[1]) - 2.0, 0.7])
    z = float(town.ground_height(pose[0], pose[1])) + 1.73
    geo = RangeImageGeometry.for_spec(load_spec("hdl-32e").with_columns(360))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([pose[0], pose[1], z]), d @ R.T, 80.0)
    points = (d[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)
    rng = np.random.default_rng(0)
    points += rng.normal(0, 0.02, points.shape).astype(np.float32)
    return caster, m, pose, z, points, town


OFFSETS = np.array([[0.8, 0, 0], [0, 0.8, 0], [2.0, -1.5, 0], [-3, 0, 0], [0, 0, 0.15], [0, 0, -0.3]])


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_each_model_ranks_the_true_pose_first(scene, name):
    caster, m, pose, z, points, _ = scene
    o = ObservationSettings(model=name, rays=400, max_range_m=60.0, field_voxel_m=0.2)  # 0.2: a fast test
    model = make_model(name, caster, o, m)
    rays = prepare_rays(points, o, np.random.default_rng(1))
    particles = np.vstack([pose, pose + OFFSETS])
    if name == "histogram":  # histograms do not see yaw: only compare positions
        particles = np.vstack([pose, pose + OFFSETS[:4]])
    loglik, bad = model.score(rays, particles, np.full(len(particles), z))
    assert loglik.shape == bad.shape == (len(particles),) and np.isfinite(loglik).all()
    assert np.argmax(loglik) == 0 and np.argmin(bad) == 0
    assert (loglik[1:] < loglik[0]).all()


def test_wasserstein_distance_by_definition():
    h = np.zeros(10)
    h[2] = 5
    g = np.zeros(10)
    g[7] = 1
    assert wasserstein_1d(h, g)[0] == pytest.approx(5 / 10)  # all mass moved 5 bins of 10
    assert wasserstein_1d(h, h * 3)[0] == 0.0  # normalised
    assert wasserstein_1d(np.zeros(10), h)[0] == 1.0
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(5, 20)), rng.uniform(size=(5, 20))
    np.testing.assert_allclose(wasserstein_1d(a, b), wasserstein_1d(b, a))


def test_surface_voxels_cover_a_plane_and_nothing_else():
    v = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    c = surface_voxels(v, f, 0.1)
    assert np.allclose(c[:, 2], 0.05)  # one layer, voxel centres
    assert 0.9 * 1200 <= len(c) <= 1200  # 40 x 30 voxels, nearly all hit by the samples
    with pytest.raises(InputError, match="no triangles"):
        surface_voxels(v, np.zeros((0, 3), int), 0.1)


def test_surface_voxels_of_a_map_are_cached_and_follow_the_mesh_file(tmp_path, monkeypatch):
    import os

    import rangemcl.localization.models as models
    from rangemcl.maps.meshmap import MeshMap

    monkeypatch.setenv("RANGEMCL_CACHE_DIR", str(tmp_path / "cache"))
    v = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], float)
    MeshMap.from_mesh(v, np.array([[0, 1, 2], [0, 2, 3]])).save(tmp_path / "map")
    m = MeshMap.load(tmp_path / "map")
    first = models.cached_surface_voxels(m, 0.1)
    assert len(list((tmp_path / "cache").glob("surface-voxels-*.npy"))) == 1
    calls = []
    monkeypatch.setattr(models, "surface_voxels", lambda *a, **k: calls.append(1) or np.zeros((1, 3)))
    np.testing.assert_array_equal(models.cached_surface_voxels(m, 0.1), first)  # from the cache
    assert calls == []
    st = (tmp_path / "map" / "tiles.json").stat()  # the tile index changes with every save of the mesh
    os.utime(tmp_path / "map" / "tiles.json", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert len(models.cached_surface_voxels(m, 0.1)) == 1 and calls == [1]  # a changed file: computed


def scan_from(caster, town, pose):
    z = float(town.ground_height(pose[0], pose[1])) + 1.73
    geo = RangeImageGeometry.for_spec(load_spec("hdl-32e").with_columns(180))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(
        np.array([pose[0], pose[1], z]), d @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T, 80.0
    )
    return (d[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)


@pytest.mark.parametrize(
    ("name", "tolerance_m"), [("overlap", 0.35), ("likelihood_field", 0.35), ("histogram", 1.0)]
)
def test_baselines_track_inside_the_filter(scene, name, tolerance_m):
    caster, m, _, _, _, town = scene
    path = [np.array([-30.0 + 0.5 * k, float(town.road_xy[1]) - 2.0, 0.0]) for k in range(25)]
    s = LocalizerSettings()
    s.observation = ObservationSettings(model=name, rays=200, max_range_m=60.0, field_voxel_m=0.2)
    loc = build_localizer(m, s, seed=0, caster=caster)
    loc.start_at(path[0] + [0.4, -0.3, 0.03], 100)
    for k, pose in enumerate(path):
        info = loc.step(np.array([0.5, 0.0, 0.0]) if k else np.zeros(3), scan_from(caster, town, pose))
    assert info.updated and info.converged
    assert np.hypot(*(info.estimate[:2] - path[-1][:2])) < tolerance_m  # histograms blur positions


def test_unknown_model_is_an_error(scene):
    caster, m, *_ = scene
    s = LocalizerSettings()
    s.observation.model = "neural"
    with pytest.raises(InputError, match=r"observation\.model"):
        build_localizer(m, s, caster=caster)
