"""LiDAR specs: presets against the makers' published beam tables, row order, YAML round trips and strict
loading."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rangemcl.errors import InputError
from rangemcl.sensors import LidarSpec, load_spec, load_spec_file, preset_names, spec_from_dict

# Typed in from the makers' published beam tables (index order; each preset's ``source`` names its
# origin), independently of the preset files.
MQ8 = [-14.00, -10.50, -8.10, -5.90, -4.50, -3.17, -2.37, -1.57]
VLP16 = [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15]
VLP16_VERTICAL_MM = [11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2]
HDL32E = [
    -30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33, -25.33, -4.00, -24.00, -2.67, -22.67, -1.33,
    -21.33, 0.00, -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33, -14.67, 6.67, -13.33, 8.00, -12.00,
    9.33, -10.67, 10.67,
]  # fmt: skip
HDL64E = [
    -8.77, -8.36, 2.49, 2.98, -7.78, -7.26, -10.86, -10.36, -6.86, -6.26, -9.82, -9.34, -2.59, -2.06, -5.67,
    -5.19, -1.59, -1.15, -4.70, -4.17, -0.57, -0.22, -3.71, -3.19, 3.50, 4.00, 0.51, 0.98, 4.49, 4.97, 1.45,
    1.97, -22.73, -22.36, -11.52, -10.95, -21.89, -21.31, -24.85, -24.42, -20.86, -20.12, -23.85, -23.18,
    -16.55, -16.11, -19.57, -19.18, -15.69, -15.18, -18.72, -18.22, -14.60, -14.08, -17.76, -17.11, -10.54,
    -9.99, -13.41, -12.97, -9.62, -9.07, -12.42, -12.07,
]  # fmt: skip


def uniform(top: float, bottom: float, n: int) -> np.ndarray:
    """Uniform grid top to bottom, rounded to 4 decimals as the preset files write it."""
    return np.round(np.linspace(top, bottom, n), 4)


# name: (beams, elevations, fov up, fov down, columns, max range, range noise)
PRESETS = {
    "mq-8": (8, MQ8, -1.57, -14.0, 5383, 150.0, 0.03),
    "vlp-16": (16, VLP16, 15.0, -15.0, 1808, 100.0, 0.03),
    "hdl-32e": (32, HDL32E, 10.67, -30.67, 2170, 100.0, 0.02),
    "hdl-64e": (64, HDL64E, 4.97, -24.85, 2083, 120.0, 0.02),
    "hdl-64e-nominal": (64, uniform(2.0, -24.9, 64), 2.0, -24.9, 2083, 120.0, 0.02),
    "os1-64": (64, uniform(16.6, -16.6, 64), 16.6, -16.6, 1024, 120.0, 0.03),
    "os1-128": (128, uniform(20.95, -21.82, 128), 20.95, -21.82, 1024, 120.0, 0.03),
}

BASE = {
    "name": "test",
    "elevation_deg": [2.0, -2.0],
    "columns": 360,
    "rotation_hz": 10.0,
    "min_range_m": 0.3,
    "max_range_m": 50.0,
    "range_noise_m": 0.01,
}


def assert_same_spec(a: LidarSpec, b: LidarSpec) -> None:
    for f in dataclasses.fields(LidarSpec):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f.name


def write(tmp_path, text: str | dict):
    """A YAML file from text, or from a flat dict written one ``key: value`` line each."""
    if isinstance(text, dict):
        text = "".join(f"{key}: {value}\n" for key, value in text.items())
    path = tmp_path / "sensor.yaml"
    path.write_text(text)
    return path


# --- presets against the published tables -------------------------------------------------------------


def test_preset_names_are_the_documented_ones():
    assert preset_names() == sorted(PRESETS)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_preset_matches_sensors_md(name):
    beams, elevations, fov_up, fov_down, columns, max_range, noise = PRESETS[name]
    spec = load_spec(name)
    assert spec.name == name
    assert spec.beams == beams == len(elevations)
    np.testing.assert_allclose(spec.elevation_deg, elevations, rtol=0, atol=1e-6)
    assert spec.fov_up_deg == pytest.approx(fov_up, abs=1e-6)
    assert spec.fov_down_deg == pytest.approx(fov_down, abs=1e-6)
    assert spec.fov_deg == pytest.approx(fov_up - fov_down, abs=1e-6)
    assert spec.columns == columns
    assert spec.max_range_m == max_range
    assert spec.range_noise_m == noise
    assert spec.rotation_hz == 10.0
    assert spec.sweep_period_s == pytest.approx(0.1)
    assert spec.min_range_m == (0.3 if name.startswith("os1") else 0.5)
    assert "assumed" in spec.source
    np.testing.assert_array_equal(spec.T_base_sensor[:3, 3], [0.0, 0.0, 1.73])
    np.testing.assert_array_equal(spec.T_base_sensor[:3, :3], np.eye(3))


def test_per_beam_offsets():
    vlp = load_spec("vlp-16")
    np.testing.assert_allclose(vlp.beam_vertical_offset_m, np.array(VLP16_VERTICAL_MM) / 1000, atol=1e-9)
    np.testing.assert_array_equal(vlp.azimuth_offset_deg, np.zeros(16))
    for name, pattern in [("os1-64", [3.164, 1.055, -1.055, -3.164]), ("os1-128", [4.2, 1.4, -1.4, -4.2])]:
        spec = load_spec(name)
        np.testing.assert_allclose(spec.azimuth_offset_deg, np.tile(pattern, spec.beams // 4))
        assert spec.beam_origin_radius_m == 0.015806
    np.testing.assert_array_equal(load_spec("hdl-64e").azimuth_offset_deg, np.zeros(64))


def test_mq8_is_all_below_horizontal():
    spec = load_spec("mq-8")
    assert spec.fov_up_deg < 0
    assert spec.fov_deg == pytest.approx(12.43)


# --- rows ---------------------------------------------------------------------------------------------


def check_rows(spec: LidarSpec) -> None:
    rows = spec.rows_by_elevation
    assert sorted(rows.tolist()) == list(range(spec.beams))
    elevation = spec.elevation_deg[rows]
    assert np.all(np.diff(elevation) <= 0)
    ties = np.diff(elevation) == 0
    assert np.all(np.diff(rows)[ties] > 0), "ties keep index order"
    np.testing.assert_array_equal(spec.row_of_beam[rows], np.arange(spec.beams))
    np.testing.assert_array_equal(rows[spec.row_of_beam], np.arange(spec.beams))


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_rows_of_presets(name):
    spec = load_spec(name)
    check_rows(spec)
    assert spec.elevation_deg[spec.rows_by_elevation[0]] == spec.fov_up_deg
    assert spec.elevation_deg[spec.rows_by_elevation[-1]] == spec.fov_down_deg


def test_rows_of_vlp16_interleave():
    assert load_spec("vlp-16").rows_by_elevation.tolist() == [
        15, 13, 11, 9, 7, 5, 3, 1, 14, 12, 10, 8, 6, 4, 2, 0,
    ]  # fmt: skip


@given(st.lists(st.sampled_from([-10.0, -2.5, 0.0, 3.0]) | st.floats(-90, 90), min_size=1, max_size=40))
def test_rows_are_a_stable_descending_permutation(elevations):
    check_rows(spec_from_dict({**BASE, "elevation_deg": elevations}))


# --- round trips --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_dict_and_yaml_round_trip(name, tmp_path):
    spec = load_spec(name)
    assert_same_spec(spec_from_dict(spec.to_dict()), spec)
    path = tmp_path / f"{name}-copy.yaml"
    spec.to_yaml(path)
    assert_same_spec(load_spec(str(path)), spec)
    assert_same_spec(load_spec(path), spec)


@given(
    xyz=st.lists(st.floats(-5, 5), min_size=3, max_size=3),
    rpy=st.lists(st.floats(-179, 179), min_size=3, max_size=3).filter(lambda r: abs(r[1]) < 89),
)
def test_mount_round_trip(xyz, rpy):
    spec = spec_from_dict({**BASE, "mount": {"xyz_m": xyz, "rpy_deg": rpy}})
    data = spec.to_dict()
    np.testing.assert_allclose(data["mount"]["rpy_deg"], rpy, atol=1e-7)
    again = spec_from_dict(data)
    np.testing.assert_allclose(again.T_base_sensor, spec.T_base_sensor, atol=1e-12)


@pytest.mark.parametrize("pitch", [90.0, -90.0])
def test_mount_round_trip_at_gimbal_lock(pitch):
    spec = spec_from_dict({**BASE, "mount": {"rpy_deg": [30.0, pitch, 50.0]}})
    np.testing.assert_allclose(spec_from_dict(spec.to_dict()).T_base_sensor, spec.T_base_sensor, atol=1e-12)


def test_mount_angles_compose_as_rz_ry_rx():
    mount = {"xyz_m": [1.0, 2.0, 3.0], "rpy_deg": [90.0, 0.0, 90.0]}
    T = spec_from_dict({**BASE, "mount": mount}).T_base_sensor
    # Rz(90) Rx(90) sends y to z (Rx(90) Rz(90) would send it to -x).
    np.testing.assert_allclose(T @ [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T @ [0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0, 1.0])
    pitched = spec_from_dict({**BASE, "mount": {"rpy_deg": [0.0, 10.0, 0.0]}}).T_base_sensor
    assert pitched[2, 0] < 0, "positive pitch tilts the x axis down"


def test_defaults_and_conversions():
    spec = spec_from_dict(BASE)
    assert spec.description == spec.source == ""
    np.testing.assert_array_equal(spec.azimuth_offset_deg, [0.0, 0.0])
    np.testing.assert_array_equal(spec.beam_vertical_offset_m, [0.0, 0.0])
    assert spec.dropout_prob == 0.0
    assert spec.beam_origin_radius_m == 0.0
    assert spec.elevation_deg.dtype == np.float64
    np.testing.assert_array_equal(spec.T_base_sensor[:3, 3], [0.0, 0.0, 1.73])


def test_spec_is_immutable():
    spec = load_spec("vlp-16")
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.columns = 5  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        spec.elevation_deg[0] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        spec.T_base_sensor[0, 3] = 1.0


def test_with_columns():
    spec = load_spec("os1-64")
    wide = spec.with_columns(2048)
    assert wide.columns == 2048 and spec.columns == 1024
    assert_same_spec(wide.with_columns(1024), spec)
    with pytest.raises(InputError, match="columns"):
        spec.with_columns(0)
    with pytest.raises(InputError, match="columns must be an integer"):
        spec.with_columns(10.5)


def test_exponent_floats_without_dot_are_numbers(tmp_path):
    assert load_spec_file(write(tmp_path, {**BASE, "max_range_m": "1e3"})).max_range_m == 1000.0


# --- errors -------------------------------------------------------------------------------------------


def test_misspelled_top_level_key(tmp_path):
    path = write(tmp_path, "colums: 1024\n")
    with pytest.raises(
        InputError, match=rf"{re.escape(str(path))}: unknown key 'colums' \(did you mean 'columns'\?\)"
    ):
        load_spec(str(path))


def test_misspelled_mount_key():
    data = {**BASE, "mount": {"xyz_m": [0, 0, 2], "rpy_dg": [0, 0, 0]}}
    with pytest.raises(InputError, match=r"unknown key 'rpy_dg' in 'mount' \(did you mean 'rpy_deg'\?\)"):
        spec_from_dict(data)


def test_unknown_key_without_close_match_lists_valid_keys():
    with pytest.raises(InputError, match=r"unknown key 'zzz' \(valid keys: name, description"):
        spec_from_dict({**BASE, "zzz": 1})


def test_missing_required_key():
    data = {k: v for k, v in BASE.items() if k != "columns"}
    with pytest.raises(InputError, match=r"sensor\.yaml: missing required key\(s\) 'columns'"):
        spec_from_dict(data, where="sensor.yaml")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"min_range_m": -0.1}, r"min_range_m must be >= 0"),
        ({"max_range_m": 0.3}, r"max_range_m \(0\.3\) must be > min_range_m \(0\.3\)"),
        ({"max_range_m": 0.1}, r"max_range_m .* must be > min_range_m"),
        ({"elevation_deg": []}, r"empty beam table"),
        ({"azimuth_offset_deg": [1.0]}, r"lengths differ: elevation_deg has 2, azimuth_offset_deg 1"),
        ({"beam_vertical_offset_m": [0.0, 0.0, 0.0]}, r"lengths differ"),
        ({"elevation_deg": [float("nan"), 1.0]}, r"elevation_deg\[0\] is not finite"),
        ({"azimuth_offset_deg": [0.0, float("inf")]}, r"azimuth_offset_deg\[1\] is not finite"),
        ({"max_range_m": float("inf")}, r"max_range_m is not finite"),
        ({"elevation_deg": [0.0, 95.0]}, r"elevation_deg\[1\] = 95\.0 is outside \[-90, 90\]"),
        ({"columns": 0}, r"columns must be >= 1"),
        ({"rotation_hz": 0.0}, r"rotation_hz must be > 0"),
        ({"range_noise_m": -0.01}, r"range_noise_m must be >= 0"),
        ({"dropout_prob": 1.0}, r"dropout_prob must be in \[0, 1\)"),
        ({"dropout_prob": -0.1}, r"dropout_prob must be in \[0, 1\)"),
        ({"beam_origin_radius_m": -1.0}, r"beam_origin_radius_m must be >= 0"),
        ({"columns": "1024"}, r"columns must be an integer, got '1024'"),
        ({"columns": 1024.0}, r"columns must be an integer"),
        ({"max_range_m": "100"}, r"max_range_m must be a number, got '100'"),
        ({"rotation_hz": True}, r"rotation_hz must be a number"),
        ({"elevation_deg": 5.0}, r"elevation_deg must be a list of numbers"),
        ({"elevation_deg": [1.0, "x"]}, r"elevation_deg\[1\] must be a number"),
        ({"name": 64}, r"name must be a string"),
        ({"mount": [0, 0, 1]}, r"mount must be a mapping"),
        ({"mount": {"xyz_m": [0.0, 1.0]}}, r"mount\.xyz_m must be a list of 3 numbers"),
        ({"mount": {"rpy_deg": 5}}, r"mount\.rpy_deg must be a list of 3 numbers"),
    ],
)
def test_invalid_values(change, message):
    with pytest.raises(InputError, match=message) as info:
        spec_from_dict({**BASE, **change}, where="custom.yaml")
    assert str(info.value).startswith("custom.yaml: ")
    assert "\n" not in str(info.value)


def test_validation_error_names_file_and_spec(tmp_path):
    path = write(tmp_path, {**BASE, "min_range_m": -1.0})
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: lidar spec 'test': min_range_m") as info:
        load_spec(str(path))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "T",
    [np.eye(3), np.diag([2.0, 1.0, 1.0, 1.0]), np.diag([1.0, 1.0, -1.0, 1.0]), np.full((4, 4), np.nan)],
    ids=["3x3", "scaled", "reflection", "nan"],
)
def test_non_rigid_mount_is_rejected(T):
    with pytest.raises(InputError, match=r"lidar spec 'test': T_base_sensor"):
        LidarSpec(**{**BASE, "T_base_sensor": T})


def test_bad_last_row_is_rejected():
    T = np.eye(4)
    T[3, 0] = 0.5
    with pytest.raises(InputError, match="last row"):
        LidarSpec(**{**BASE, "T_base_sensor": T})


def test_missing_file(tmp_path):
    path = tmp_path / "nope.yaml"
    with pytest.raises(InputError, match=rf"{re.escape(str(path))}: no such LiDAR spec file"):
        load_spec(str(path))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("columns: [1, 2\n", r"malformed YAML at line \d+, column \d+"),
        ("name: a\nname: b\n", r"malformed YAML at line 2, column 1: duplicate key 'name'"),
        ("- 1\n- 2\n", r"expected a mapping of LiDAR spec keys, got a list"),
        ("", r"expected a mapping of LiDAR spec keys, got an empty file"),
    ],
)
def test_malformed_files(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: {message}") as info:
        load_spec_file(path)
    assert "\n" not in str(info.value)


def test_unknown_preset_name():
    with pytest.raises(InputError, match=r"unknown LiDAR preset 'vlp-61' \(did you mean 'vlp-16'\?") as info:
        load_spec("vlp-61")
    assert all(name in str(info.value) for name in PRESETS)


@pytest.mark.parametrize(
    ("alias", "name"),
    [
        ("VLP-16", "vlp-16"),
        ("vlp16", "vlp-16"),
        ("Puck", "vlp-16"),
        ("Velodyne VLP-16", "vlp-16"),
        ("hdl32", "hdl-32e"),
        ("HDL-32E", "hdl-32e"),
        ("hdl64", "hdl-64e"),
        ("velodyne_hdl64e", "hdl-64e"),
        ("HDL-64E-Nominal", "hdl-64e-nominal"),
        ("os1-128", "os1-128"),
        ("OS1_64", "os1-64"),
        ("ouster-os1-64", "os1-64"),
        ("mq8", "mq-8"),
        (" Quanergy MQ-8 ", "mq-8"),
    ],
)
def test_names_are_case_insensitive_and_aliases_resolve(alias, name):
    assert load_spec(alias).name == name
