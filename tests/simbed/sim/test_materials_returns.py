"""Materials and the realistic return model against analytic references: the datasheet's two detection
ranges met exactly, Lambertian and specular reflectivity, window and marking patterns on known
coordinates, material resolution for a scene with a sidecar, and the realistic sensor on a tiny scene
(detection rates against the model's probability, glass passing the beam, intensity of known surfaces)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.sensors import load_spec
from simbed.sim.lidar import SimLidar
from simbed.sim.materials import Material, MaterialTable, RoadMarkings, WindowGrid
from simbed.sim.returns import DATASHEET_DETECTION, SPECULAR_LOBE_RAD, ReturnModel, sensor_extinction
from simbed.sim.world import World


# ---------------------------------------------------------------------- the return model
@pytest.mark.parametrize("seed", range(5))
def test_the_datasheet_ranges_are_where_10_and_80_percent_targets_are_detected(seed):
    rng = np.random.default_rng(seed)
    r10 = float(rng.uniform(10, 80))
    r80 = r10 * float(rng.uniform(1.2, 2.8))  # below sqrt(8): the sensor needs an extinction
    s_th, alpha = sensor_extinction(r10, r80)
    assert alpha > 0
    model = ReturnModel(s_th, alpha, 0.02, 0.1, "reflectivity_8bit")
    assert model.range_limit_m(0.10) == pytest.approx(r10, rel=1e-6)
    assert model.range_limit_m(0.80) == pytest.approx(r80, rel=1e-6)
    # at the stated range the sensor detects with the datasheet's probability, beyond it less
    assert model.detection_probability(model.signal(0.8, r80)) == pytest.approx(DATASHEET_DETECTION)
    p = model.detection_probability(model.signal(0.8, np.linspace(1, 3 * r80, 50)))
    assert np.all(np.diff(p) <= 1e-12) and p[-1] < 0.01


def test_ranges_that_the_inverse_square_explains_need_no_extinction():
    s_th, alpha = sensor_extinction(40.0, 40.0 * math.sqrt(8.0) * 1.1)
    assert alpha == 0.0
    assert ReturnModel(s_th, alpha, 0.02, 0.1, "unit").range_limit_m(0.1) == pytest.approx(40.0)
    with pytest.raises(InputError, match="below the range at 80"):
        sensor_extinction(50.0, 40.0)


def test_effective_reflectivity_lambertian_glint_and_retro():
    cos = np.cos(np.radians([0.0, 30.0, 60.0, 85.0]))
    lam = ReturnModel.effective_reflectivity(0.5, 0.0, 0.0, cos)
    np.testing.assert_allclose(lam, 0.5 * cos)
    glint = ReturnModel.effective_reflectivity(0.0, 0.04, 0.0, cos)
    assert glint[0] == pytest.approx(0.04 / SPECULAR_LOBE_RAD**2)  # a window seen face on: very bright
    assert glint[1] < 1e-6  # and dark 30 degrees off
    retro = ReturnModel.effective_reflectivity(0.0, 0.0, 20.0, cos)
    np.testing.assert_allclose(retro, 20.0 * cos**2)


def test_noise_grows_from_the_strong_to_the_weak_figure_at_the_threshold():
    m = ReturnModel(1e-4, 0.0, 0.02, 0.10, "unit")
    assert m.noise_sigma(1e-4) == pytest.approx(0.10)
    assert m.noise_sigma(1e2) == pytest.approx(0.02, abs=1e-4)
    s = np.geomspace(1e-6, 1e2, 40)
    assert np.all(np.diff(m.noise_sigma(s)) <= 0)


def test_intensity_scales():
    m = ReturnModel(1e-4, 0.0, 0.02, 0.1, "reflectivity_8bit")
    np.testing.assert_array_equal(m.intensity([0.0, 0.1, 0.655, 1.0]), [0, 10, 66, 100])
    bright = m.intensity([2.0, 10.0, 100.0, 1e4])
    assert np.all(bright > 100) and np.all(np.diff(bright) >= 0) and bright[-1] == 255
    u = ReturnModel(1e-4, 0.0, 0.02, 0.1, "unit")
    np.testing.assert_allclose(u.intensity([0.0, 0.3, 5.0]), [0.0, 0.3, 1.0], rtol=1e-6)


def test_the_presets_give_their_return_figures():
    for name in ("mq-8", "vlp-16", "hdl-32e", "hdl-64e", "os1-64", "os1-128"):
        spec = load_spec(name)
        model = ReturnModel.for_spec(spec)
        assert model.range_limit_m(0.1) == pytest.approx(spec.range_at_10pct_m, rel=1e-3)
        assert spec.range_at_80pct_m <= spec.max_range_m * 1.5


def test_a_spec_without_return_figures_is_one_clear_error():
    spec = dataclasses.replace(load_spec("vlp-16"), range_at_10pct_m=None, range_at_80pct_m=None)
    with pytest.raises(InputError, match="realistic sensor model needs range_at_10pct_m"):
        ReturnModel.for_spec(spec)
    with pytest.raises(InputError, match="go together"):
        dataclasses.replace(load_spec("vlp-16"), range_at_10pct_m=None)


# ---------------------------------------------------------------------- materials
def test_materials_refuse_impossible_values():
    with pytest.raises(InputError, match="more light than arrives"):
        Material("x", 0.6, mirror=0.2, transmission=0.5)
    with pytest.raises(InputError, match="reflectivity must be a number in"):
        Material("x", 1.5)
    table = MaterialTable.load()
    assert table.named_in("old_asphalt_road") == "asphalt" and table.named_in("glass") == "glass"
    assert table.named_in("foo") is None


def test_window_grid_on_a_known_facade():
    half = np.array([[10.0, 4.0, 4.5]])  # a 20 x 8 m box, 9 m tall: 3 floors
    bays = math.floor((20 - 2 * WindowGrid.MARGIN_M) / WindowGrid.BAY_M)  # 7 bays on the long façade
    z_window = -4.5 + WindowGrid.SILL_M + WindowGrid.HEIGHT_M / 2  # middle of the ground floor's window
    centre_u = -bays * WindowGrid.BAY_M / 2 + WindowGrid.BAY_M / 2  # middle of the first bay
    pts = np.array(
        [
            [centre_u, -4.0, z_window],  # window, long façade
            [centre_u + WindowGrid.BAY_M / 2, -4.0, z_window],  # between two windows
            [centre_u, -4.0, -4.5 + 0.3],  # under the sill
            [centre_u, -4.0, z_window + WindowGrid.FLOOR_M],  # the next floor's window
            [-9.9, -4.0, z_window],  # the corner margin
            [centre_u, 0.0, 4.5],  # the roof
            [10.0, 0.0, z_window],  # the short façade (8 m: 2 bays), at its middle: between windows
            [10.0, WindowGrid.BAY_M / 2, z_window],  # the short façade's window
        ]
    )
    got = WindowGrid.glass(pts, np.repeat(half, len(pts), 0))
    np.testing.assert_array_equal(got, [True, False, False, True, False, False, False, True])


def test_road_markings_from_the_road_graph():
    nodes = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 50.0], [100.0, -50.0], [150.0, 0.0]])
    edges = np.array([[0, 1], [1, 2], [1, 3], [1, 4]])  # node 1: a junction
    mk = RoadMarkings(nodes, edges, road_width_m=8.0)
    edge_y = 4.0 - mk.EDGE_INSET_M
    pts = np.array(
        [
            [31.0, 0.02],  # centre line, in a dash (27..30 painted? 27+3: s mod 9 = 4 -> gap)
            [28.0, 0.02],  # s mod 9 = 1: a dash
            [28.0, 0.3],  # beside the centre line
            [40.0, edge_y],  # the edge line (solid)
            [40.0, -edge_y + 0.05],
            [40.0, 2.0],  # the lane's middle
            [97.0, edge_y],  # within a road width of the junction: none
        ]
    )
    np.testing.assert_array_equal(mk.painted(pts), [False, True, False, True, True, False, False])


SCENE = """<mujoco model="mats">
  <asset>
    <material name="old_asphalt" rgba="0.2 0.2 0.2 1"/>
    <material name="building2" rgba="0.7 0.5 0.4 1"/>
    <material name="facade" rgba="0.7 0.7 0.7 1"/>
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="50 50 0.1" material="old_asphalt"/>
    <geom name="house" type="box" pos="20 0 4.5" size="4 10 4.5" material="building2"/>
    <geom name="shop" type="box" pos="-20 0 3" size="1 5 3" material="facade"/>
    <geom name="shop_window_1" type="box" pos="-18.95 0 1.5" size="0.01 2 1"/>
    <geom name="thing" type="sphere" pos="0 20 1" size="1"/>
    <body name="parked_v0_3" pos="0 -10 0">
      <geom name="parked_v0_3_body" type="box" pos="0 0 0.6" size="2 0.9 0.4" rgba="0.95 0.95 0.95 1"/>
      <geom name="parked_v0_3_cabin" type="box" pos="0 0 1.3" size="1 0.85 0.3" rgba="0.1 0.1 0.1 1"/>
    </body>
  </worldbody>
</mujoco>"""


def _geom_materials(world: World) -> dict[str, str]:
    import mujoco

    mats = world.materials
    return {
        mujoco.mj_id2name(world.model, mujoco.mjtObj.mjOBJ_GEOM, g): mats.table.materials[m].name
        for g, m in enumerate(mats.geom_material)
    }


def test_scene_materials_resolve_by_sidecar_mjcf_name_and_what_the_geom_is(tmp_path):
    xml = tmp_path / "mats.xml"
    xml.write_text(SCENE)
    (tmp_path / "mats.materials.yaml").write_text(
        "default: concrete\n"
        "materials:\n  shopfront: {reflectivity: 0.0, mirror: 0.05, transmission: 0.8}\n"
        "mjcf_materials:\n  facade: brick\n"
        "geoms:\n  'shop_window_*': shopfront\n"
    )
    got = _geom_materials(World(xml))
    assert got == {
        "ground": "asphalt",  # the longest table name in the MJCF material's name
        "house": "brick",  # a generated town's name
        "shop": "brick",  # the sidecar's mjcf_materials
        "shop_window_1": "shopfront",  # the sidecar's geom glob, with its own material
        "thing": "concrete",  # the sidecar's default
        "parked_v0_3_body": "car_paint_0.65",  # a white parked car (luminance 0.89)
        "parked_v0_3_cabin": "glass",
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("default: marble\n", "no material 'marble'"),
        ("colours: {}\n", "unknown key 'colours'"),
        ("materials:\n  x: {reflectivity: 2}\n", "reflectivity must be a number in"),
        ("geoms:\n  'a*': nothing\n", "geoms: a\\*: no material 'nothing'"),
        ("geoms: [1, 2\n", None),
    ],
)
def test_a_bad_material_sidecar_is_one_line_naming_it(tmp_path, text, message):
    xml = tmp_path / "mats.xml"
    xml.write_text(SCENE)
    side = tmp_path / "mats.materials.yaml"
    side.write_text(text)
    with pytest.raises(InputError) as err:
        World(xml).materials  # noqa: B018
    assert str(side) in str(err.value) and "\n" not in str(err.value)
    assert message is None or __import__("re").search(message, str(err.value))


def test_a_towns_terrain_roads_buildings_and_cars_have_their_materials():
    world = World("town_small")
    got = _geom_materials(world)
    mats = world.materials
    assert mats.ground is not None and mats.markings is not None
    names = {n for n in got.values()}
    assert {"asphalt", "concrete", "steel", "bark", "vegetation", "glass"} <= names
    assert any(n.startswith("car_paint_") for n in names)
    # the terrain under the spawn pose (a road) is asphalt, a point far from any road grass or sidewalk
    t = world.town
    xy = np.array([t.spawn[:2]])
    assert mats.table.materials[int(mats.ground.at(xy)[0])].name == "asphalt"


# ---------------------------------------------------------------------- the realistic sensor
WALLS = """<mujoco model="walls">
  <asset>
    <material name="plaster" rgba="1 1 1 1"/>
    <material name="asphalt" rgba="0.2 0.2 0.2 1"/>
    <material name="glass" rgba="0.5 0.5 0.9 0.3"/>
  </asset>
  <worldbody>
    <geom name="bright" type="box" pos="{d} 0 0" size="0.5 {w} 30" material="plaster"/>
    <geom name="dark" type="box" pos="-{d} 0 0" size="0.5 {w} 30" material="asphalt"/>
    <geom name="pane" type="box" pos="0 {g} 0" size="{w} 0.005 30" material="glass"/>
    <geom name="behind" type="box" pos="0 {b} 0" size="{w} 0.5 30" material="plaster"/>
  </worldbody>
</mujoco>"""


def _sweep(tmp_path, spec, d, seed=0, g=10.0, b=20.0):
    xml = tmp_path / "walls.xml"
    xml.write_text(WALLS.format(d=d, w=4 * d, g=g, b=b))
    world = World(xml)
    lidar = SimLidar(
        spec,
        world.caster,
        np.random.default_rng(seed),
        skew=False,
        materials=world.materials,
        returns=ReturnModel.for_spec(spec),
    )
    T = np.eye(4)
    lidar.cast_columns(slice(None), 0.0, np.array([0.0, 1.0]), np.stack([T, T]))
    return lidar, lidar.finish(0.0, np.array([0.0, 1.0]), np.stack([T, T]))


def test_detection_follows_the_model_on_walls_of_known_material(tmp_path):
    """Two walls face to face at +-d: the share of pixels that return matches the model's probability
    within binomial error, and the intensity of the face-on plaster is 100 x its reflectivity x cos."""
    spec = dataclasses.replace(load_spec("vlp-16"), range_noise_m=0.0, range_noise_weak_m=0.0)
    model = ReturnModel.for_spec(spec)
    d = 0.9 * model.range_limit_m(0.10) - 0.5  # the dark wall near its limit, the bright one well within
    lidar, sweep = _sweep(tmp_path, spec, d)
    geo = lidar.geometry
    dirs = geo.directions.reshape(-1, 3)
    rows, cols = np.unravel_index(np.arange(len(dirs)), geo.shape)
    table = MaterialTable.load()
    plaster, asphalt = (table.materials[table.id(n)].reflectivity for n in ("plaster", "asphalt"))
    for sign, refl in ((+1, plaster), (-1, asphalt)):
        toward = sign * dirs[:, 0] > 0.97  # pixels that face this wall (not the pane's plane)
        cos = sign * dirs[toward, 0]
        r = (d - 0.5) / cos
        p = model.detection_probability(model.signal(refl * cos, r))
        returned = sweep.ranges[rows[toward], cols[toward]] > 0
        n = toward.sum()
        assert abs(returned.sum() - p.sum()) < 4 * math.sqrt(max(1.0, (p * (1 - p)).sum())) + 1, (refl, n)
    bright = (sweep.points[:, 0] > d - 1) & (np.abs(sweep.points[:, 1]) < 9)  # not the pane's side
    expected = np.round(100 * plaster * (d - 0.5) / np.linalg.norm(sweep.points[bright], axis=1))
    np.testing.assert_allclose(sweep.intensity[bright], expected, atol=1.0)


def test_grazing_rays_on_a_dark_surface_drop_more_often_than_face_on_white_at_the_models_rates(tmp_path):
    """The same two walls, now at 12 m: the dark wall's grazing pixels (60-75 degrees off its normal) and
    the white wall's face-on pixels (within 15 degrees), each group's dropped share within binomial error
    of the model's mean probability, and the dark grazing group's far larger."""
    spec = dataclasses.replace(load_spec("vlp-16"), range_noise_m=0.0, range_noise_weak_m=0.0)
    model = ReturnModel.for_spec(spec)
    d = 12.5
    lidar, sweep = _sweep(tmp_path, spec, d, g=400.0, b=500.0)  # the pane and the wall behind it far away
    geo = lidar.geometry
    dirs = geo.directions.reshape(-1, 3)
    rows, cols = np.unravel_index(np.arange(len(dirs)), geo.shape)
    table = MaterialTable.load()
    plaster, asphalt = (table.materials[table.id(n)].reflectivity for n in ("plaster", "asphalt"))
    dropped = {}
    for name, sign, refl, lo, hi in (
        ("white face-on", +1, plaster, 15, 0),
        ("dark grazing", -1, asphalt, 75, 60),
    ):
        cos = sign * dirs[:, 0]
        group = (cos > np.cos(np.radians(lo))) & (cos <= np.cos(np.radians(hi)))
        c = cos[group]
        p = model.detection_probability(model.signal(refl * c, (d - 0.5) / c))
        lost = (sweep.ranges[rows[group], cols[group]] == 0).sum()
        assert abs(lost - (1 - p).sum()) < 4 * math.sqrt(max(1.0, (p * (1 - p)).sum())) + 1, name
        dropped[name] = lost / group.sum()
    assert dropped["dark grazing"] > 0.2 and dropped["white face-on"] < 0.01


def test_glass_passes_the_beam_to_what_lies_behind(tmp_path):
    """A pane (a 1 cm glass box) at y = 10 before a plaster wall at y = 19.5: rays toward +y return from
    the wall, dimmed by the pane's two surfaces there and back, except near face on, where the pane's glint
    is the stronger return."""
    spec = dataclasses.replace(load_spec("vlp-16"), range_noise_m=0.0, range_noise_weak_m=0.0)
    _, sweep = _sweep(tmp_path, spec, d=500.0, g=10.0, b=20.0)  # the side walls out of range
    p = sweep.points
    toward = p[:, 1] > 5
    y = p[toward, 1]
    on_wall = np.abs(y - 19.5) < 0.05
    on_pane = np.abs(y - 9.995) < 0.05
    assert on_wall.sum() > 0.9 * toward.sum() and on_wall.sum() + on_pane.sum() == toward.sum()
    # which return is the strongest, analytically: the pane's glint or the wall behind it (both face +y)
    table = MaterialTable.load()
    plaster = table.materials[table.id("plaster")].reflectivity
    model = ReturnModel.for_spec(spec)
    cos = p[toward, 1] / np.linalg.norm(p[toward], axis=1)  # incidence on both
    t = table.materials[table.id("glass")].transmission
    pane = t**4  # two surfaces, there and back
    # the glints of the pane's two surfaces, 1 cm apart, are one echo (the second dimmed by the first)
    glint = model.signal(model.effective_reflectivity(0.0, 0.04, 0.0, cos), 10.0 / cos) * (1 + t**2)
    wall = model.signal(model.effective_reflectivity(plaster, 0.0, 0.0, cos), 19.5 / cos, pane)
    clear = np.abs(np.log(np.maximum(glint, 1e-30) / wall)) > 0.1
    assert on_pane.any() and clear.sum() > 0.95 * toward.sum()
    np.testing.assert_array_equal(on_pane[clear], (glint > wall)[clear])
    assert np.degrees(np.arccos(cos[on_pane])).max() < 6.0  # glints only near face on
    # the wall behind the pane is reported dimmer by the pane's two-way transmission
    expected = np.round(100 * plaster * pane * cos[on_wall])
    np.testing.assert_allclose(sweep.intensity[toward][on_wall], expected, atol=1.0)


def test_the_realistic_sweep_is_reproducible(tmp_path):
    spec = load_spec("vlp-16")
    _, a = _sweep(tmp_path, spec, 30.0, seed=4)
    _, b = _sweep(tmp_path, spec, 30.0, seed=4)
    _, c = _sweep(tmp_path, spec, 30.0, seed=5)
    assert a.points.tobytes() == b.points.tobytes() and a.intensity.tobytes() == b.intensity.tobytes()
    assert a.points.tobytes() != c.points.tobytes()


def test_a_realistic_recording_writes_intensity_and_loses_weak_returns(tmp_path):
    """Two frames of town_small with each model, the same seed: the realistic scan reports intensities
    that follow the materials (lane markings and façades brighter than the asphalt), keeps fewer points,
    and says which model made it."""
    from rangemcl.datasets.kitti import load_sequence
    from simbed.record import record

    for model in ("ideal", "realistic"):
        record(
            "town_small",
            "test",
            "vlp-16",
            tmp_path / model,
            frames=2,
            seed=1,
            progress=False,
            sensor_model=model,
        )
    ideal, real = load_sequence(tmp_path / "ideal"), load_sequence(tmp_path / "realistic")
    assert real.meta["sensor_model"] == "realistic" and ideal.meta["sensor_model"] == "ideal"
    pts_i, int_i = ideal.scan_with_intensity(1)
    pts_r, int_r = real.scan_with_intensity(1)
    assert not int_i.any()
    assert 0.5 * len(pts_i) < len(pts_r) < len(pts_i)
    assert int_r.min() >= 0 and int_r.max() <= 255 and np.unique(np.round(int_r)).size > 20
    ground = pts_r[:, 2] < -1.5  # the road around the car (sensor 1.73 m up)
    up = pts_r[:, 2] > 0.5  # façades, trees, cars' cabins
    assert np.median(int_r[up]) > 2 * np.median(int_r[ground])
    meta = real.point_meta(1)
    assert set(meta) >= {"echo", "snr"} and "snr" not in ideal.point_meta(1)
    assert np.all(meta["snr"] > 0) and np.median(meta["snr"]) > 12  # most returns well above the threshold


def test_the_realistic_model_is_refused_for_a_sensor_without_its_figures(tmp_path):
    from simbed.record import record

    spec = load_spec("vlp-16").to_dict()
    for key in ("range_at_10pct_m", "range_at_80pct_m", "range_noise_weak_m"):
        spec.pop(key)
    import yaml

    (tmp_path / "mine.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(InputError, match="realistic sensor model needs"):
        record(
            "town_small",
            "test",
            str(tmp_path / "mine.yaml"),
            tmp_path / "out",
            frames=1,
            progress=False,
            sensor_model="realistic",
        )
    assert not (tmp_path / "out").exists()
    with pytest.raises(InputError, match="sensor model 'fancy'"):
        record(
            "town_small", "test", "vlp-16", tmp_path / "out", frames=1, progress=False, sensor_model="fancy"
        )


# ---------------------------------------------------------------------- footprints, echoes, weather
POST_ROLL_DEG = 20.0  # the post leans, so its edges cross the footprints of some rows whatever the columns
EDGES = """<mujoco model="edges">
  <asset><material name="plaster" rgba="1 1 1 1"/></asset>
  <worldbody>
    <geom name="post" type="box" pos="10.1 0 0" size="0.1 1 40" euler="20 0 0" material="plaster"/>
    <geom name="wall" type="box" pos="{wall} 0 0" size="0.1 200 40" material="plaster"/>
  </worldbody>
</mujoco>"""


POST = '<geom name="post" type="box" pos="10.1 0 0" size="0.1 1 40" euler="20 0 0" material="plaster"/>'


def _edge_sweep(tmp_path, spec, wall_x, mode="strongest", weather=None, seed=0, xml=EDGES):
    path = tmp_path / f"edges{wall_x}.xml"
    path.write_text(xml.format(wall=wall_x + 0.1))
    world = World(path)
    lidar = SimLidar(
        spec,
        world.caster,
        np.random.default_rng(seed),
        skew=False,
        materials=world.materials,
        returns=ReturnModel.for_spec(spec, weather),
        weather=weather,
        return_mode=mode,
    )
    T = np.eye(4)
    lidar.cast_columns(slice(None), 0.0, np.array([0.0, 1.0]), np.stack([T, T]))
    return lidar.finish(0.0, np.array([0.0, 1.0]), np.stack([T, T]))


def _quiet(name):
    return dataclasses.replace(load_spec(name), range_noise_m=0.0, range_noise_weak_m=0.0)


def test_mixed_pixels_appear_only_at_depth_edges(tmp_path):
    """A post 10 m ahead, 2 m wide and leaning 20 degrees sideways, before a wall 0.6 m behind it: points
    between the two surfaces (mixed pixels) appear, and only within a column and a footprint of the
    post's two edges. With the wall 15 m behind, the two are separate echoes: nothing in between."""
    spec = _quiet("os1-64")
    sweep = _edge_sweep(tmp_path, spec, 10.6)
    p = sweep.points
    ahead = p[:, 0] > 5
    x = p[ahead, 0]
    between = (x > 10.0 + 0.02) & (x < 10.6 - 0.02)
    assert between.sum() >= 10
    # the post's edges: where its own across coordinate y cos(roll) + z sin(roll) is +-1
    roll = math.radians(POST_ROLL_DEG)
    at_post = p[ahead] * (10.0 / x[:, None])  # where each ray crossed the post's plane
    across = at_post[:, 1] * math.cos(roll) + at_post[:, 2] * math.sin(roll)
    reach = 10.0 * (math.radians(360.0 / spec.columns) + spec.beam_divergence_mrad * 1e-3)
    near_edge = np.abs(np.abs(across) - 1.0) < reach
    assert np.all(near_edge[between])
    # everywhere else each pixel is on one surface
    assert np.all(np.isclose(x[~near_edge], 10.0, atol=5e-3) | np.isclose(x[~near_edge], 10.6, atol=5e-3))
    far = _edge_sweep(tmp_path, spec, 25.0).points
    xf = far[far[:, 0] > 5, 0]
    assert not np.any((xf > 10.05) & (xf < 24.95))


def test_dual_returns_report_the_background_behind_an_edge(tmp_path):
    """The VLP-16 in dual mode: the pixels across the post's edges return the post and, as a second
    echo, the wall 15 m behind; elsewhere one echo each. A sensor without dual returns refuses the mode."""
    spec = _quiet("vlp-16")
    single = _edge_sweep(tmp_path, spec, 25.0)
    dual = _edge_sweep(tmp_path, spec, 25.0, mode="dual")
    second = dual.echo == 1
    assert second.any() and not single.echo.any()
    q = dual.points[second]
    assert np.all(np.abs(q[:, 0] - 25.0) < 0.05)
    roll = math.radians(POST_ROLL_DEG)
    at_post = q * (10.0 / q[:, :1])  # where the ray crossed the post's plane
    across = at_post[:, 1] * math.cos(roll) + at_post[:, 2] * math.sin(roll)
    assert np.all(np.abs(np.abs(across) - 1.0) < 10.0 * math.radians(0.5))
    # the strongest echoes are the single mode's points, the last ones come on top
    assert len(dual.points) - second.sum() == len(single.points)
    with pytest.raises(InputError, match="strongest echo only"):
        _edge_sweep(tmp_path, _quiet("os1-64"), 25.0, mode="dual")


def test_fog_shortens_the_range_by_the_stated_extinction():
    """Koschmieder's extinction 3.912/V is added to the sensor's: a target's detection limit in fog solves
    rho exp(-2 (alpha + 3.912/V) r) / r^2 = S_th (an independent root-finder)."""
    from scipy.optimize import brentq

    from simbed.sim.weather import Weather

    spec = load_spec("hdl-64e")
    clear = ReturnModel.for_spec(spec)
    for vis in (50.0, 200.0, 1000.0):
        fog = ReturnModel.for_spec(spec, Weather.parse(f"fog:{vis:g}"))
        a = clear.alpha_per_m + 3.912 / vis
        for rho in (0.1, 0.8):
            root = brentq(
                lambda r, rho=rho, a=a: (
                    math.log(rho) - 2 * a * r - 2 * math.log(r) - math.log(clear.s_threshold)
                ),
                0.1,
                500,
            )
            assert fog.range_limit_m(rho) == pytest.approx(root, rel=1e-6)
            assert fog.range_limit_m(rho) < clear.range_limit_m(rho)
    assert ReturnModel.for_spec(spec, Weather.parse("rain:10")).extra_alpha_per_m == pytest.approx(
        0.00156, rel=0.01
    )


def test_fog_clutter_hides_a_wall_at_the_rate_the_model_states(tmp_path):
    """In fog the pulse's strongest echo is either the fog near the sensor or the wall. The share of the
    wall's pixels that return the wall matches the model's expectation: the chance that the fog echo (its
    range drawn with density exp(-2 a r)/r^2 between the overlap distance and the wall) is weaker than the
    wall, times the wall's detection probability."""
    from simbed.sim.weather import FOG_BACKSCATTER_RATIO, OVERLAP_M, PULSE_LENGTH_M, Weather

    spec = _quiet("hdl-64e")
    sky = Weather.parse("fog:300")
    model = ReturnModel.for_spec(spec, sky)
    d = 30.0
    xml = EDGES.replace(POST, "")
    sweep = _edge_sweep(tmp_path, spec, d, weather=sky, seed=3, xml=xml)
    from rangemcl.rangeimage import RangeImageGeometry

    geo = RangeImageGeometry.for_spec(spec)
    dirs = geo.directions.reshape(-1, 3)
    toward = dirs[:, 0] > 0.95
    cos = dirs[toward, 0]
    r_wall = d / cos
    table = MaterialTable.load()
    s_wall = model.signal(table.materials[table.id("plaster")].reflectivity * cos, r_wall)
    a = model.alpha_per_m + model.extra_alpha_per_m
    rho_fog = math.pi * FOG_BACKSCATTER_RATIO * sky.extinction_per_m * PULSE_LENGTH_M
    grid = np.geomspace(OVERLAP_M, r_wall.max(), 20000)
    dens = np.exp(-2 * a * grid) / grid**2 * grid  # per sample of the log-spaced grid (dr = r du)
    s_fog = rho_fog * np.exp(-2 * a * grid) / grid**2
    expected = 0.0
    for rw, sw in zip(r_wall, s_wall, strict=True):
        inside = grid <= rw
        weaker = inside & (s_fog < sw)
        expected += dens[weaker].sum() / dens[inside].sum() * model.detection_probability(sw)
    p = sweep.points
    on_wall = (np.abs(p[:, 0] - d) < 0.5) & (p[:, 0] / np.linalg.norm(p, axis=1) > 0.95)
    n = toward.sum()
    assert abs(on_wall.sum() - expected) < 4 * math.sqrt(expected * (1 - expected / n)) + 5, (
        on_wall.sum(),
        expected,
    )
    clutter = (np.linalg.norm(p, axis=1) < d - 1) & (p[:, 0] > 0)
    assert clutter.any() and np.linalg.norm(p[clutter], axis=1).min() >= OVERLAP_M - 1e-6


def test_rain_droplets_return_from_near_the_sensor_at_the_stated_share(tmp_path):
    from simbed.sim.weather import RAIN_CLUTTER_MAX_M, RAIN_CLUTTER_PER_MM_H, Weather

    spec = _quiet("os1-64")
    sky = Weather.parse("rain:40")
    xml = EDGES.replace(POST, "")
    sweep = _edge_sweep(tmp_path, spec, 30.0, weather=sky, seed=5, xml=xml)
    near = np.linalg.norm(sweep.points, axis=1) < RAIN_CLUTTER_MAX_M + 1e-6
    n = spec.beams * spec.columns
    p = 1 - math.exp(-RAIN_CLUTTER_PER_MM_H * 40)
    assert abs(near.sum() - n * p) < 4 * math.sqrt(n * p * (1 - p)), (near.sum(), n * p)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("fog", "expected clear"),
        ("fog:-3", "must be a number > 0"),
        ("snow:3", "expected clear"),
        ("rain:x", "expected clear"),
    ],
)
def test_bad_weather_is_one_clear_line(text, message):
    from simbed.sim.weather import Weather

    with pytest.raises(InputError, match=message):
        Weather.parse(text)


def test_the_markings_raster_only_skips_points_far_from_any_line():
    """The raster that spares the tree look-ups changes no answer (random points over a town's roads)."""
    world = World("town_small")
    mk = world.materials.markings
    rng = np.random.default_rng(0)
    t = world.town
    xy = rng.uniform(-t.size_m / 2, t.size_m / 2, (200_000, 2))
    np.testing.assert_array_equal(mk.painted(xy), mk._painted(xy))
    assert mk.painted(xy).sum() > 100


def test_the_demo_checks_its_sensor_model_before_it_records():
    from simbed.demo import DemoSettings

    DemoSettings(sensor_model="realistic").check()
    with pytest.raises(InputError, match="sensor model 'fancy': expected ideal, realistic"):
        DemoSettings(sensor_model="fancy").check()
