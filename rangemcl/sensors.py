"""LiDAR sensor specs as data: per-beam tables and sweep parameters, presets, and a strict YAML loader.

A :class:`LidarSpec` holds what a spinning multi-beam LiDAR measures; the simulated LiDAR and the localizer
read the same spec. Presets live as YAML files in ``rangemcl/presets/`` and go through the same loader as
a user's own file (each preset's facts and their sources: its ``source`` field; all presets side by side:
``docs/testbed.md``, "Sensors and presets").

Conventions:

* Beam tables are in the device's laser-id (index) order; range-image rows are beams sorted by elevation,
  highest first (:attr:`LidarSpec.rows_by_elevation`).
* Elevations are degrees, positive up. Azimuth offsets are degrees in the sweep direction (clockwise seen
  from above, the way the column index grows): a beam's horizontal angle ``atan2(y, x)`` is its column's
  angle minus its offset, as ouster-sdk applies ``beam_azimuth_angles``.
* Beam origins sit ``beam_origin_radius_m`` from the rotation axis along the column's azimuth, raised by
  the beam's ``beam_vertical_offset_m``.
* The mount ``T_base_sensor`` maps sensor-frame points into the car base frame. In YAML it is
  ``mount: {xyz_m, rpy_deg}`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import os
import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache, lru_cache
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import yaml

from rangemcl.common.yamlio import parse_yaml, read_text
from rangemcl.errors import InputError
from rangemcl.se2 import transform_from_xyz_rpy, xyz_rpy_from_transform

DEFAULT_MOUNT_XYZ_M = (0.0, 0.0, 1.73)
"""Default sensor position on the car base: 1.73 m above the ground under the rear axle, level."""

_SCALAR_KEYS = (
    "beam_origin_radius_m",
    "rotation_hz",
    "min_range_m",
    "max_range_m",
    "range_noise_m",
    "dropout_prob",
)


_RETURN_KEYS = ("range_at_10pct_m", "range_at_80pct_m", "range_noise_weak_m", "beam_divergence_mrad")
INTENSITY_SCALES = ("reflectivity_8bit", "unit")


def _default_mount() -> np.ndarray:
    return transform_from_xyz_rpy(DEFAULT_MOUNT_XYZ_M, (0.0, 0.0, 0.0))


@dataclass(frozen=True, eq=False, kw_only=True)
class LidarSpec:
    """One LiDAR model: beam tables in index order, sweep geometry, range limits and noise.

    Attributes:
        name: preset id or the user's name for the sensor, e.g. ``"os1-64"``.
        description: one line for people, e.g. ``"Ouster OS1-64 (gen 1), near-uniform beams"``.
        elevation_deg: (B,) beam elevations, index order, positive up.
        azimuth_offset_deg: (B,) beam azimuth offsets in the sweep direction (zeros if ``None``).
        beam_vertical_offset_m: (B,) beam origin heights above the sensor origin (zeros if ``None``).
        beam_origin_radius_m: distance of the beam origins from the rotation axis.
        columns: firings (range-image columns) per 360° sweep.
        rotation_hz: sweeps per second.
        min_range_m, max_range_m: no return outside this interval.
        range_noise_m: 1-sigma Gaussian range noise.
        dropout_prob: probability that a return is dropped (on top of the realistic return model).
        range_at_10pct_m, range_at_80pct_m: the datasheet's detection range for a 10 % and an 80 %
            reflectivity target (the realistic return model's detection threshold and extinction).
        range_noise_weak_m: 1-sigma range noise of returns at the detection threshold (realistic model).
        beam_divergence_mrad: the beam's full divergence (the realistic model's footprint: mixed
            pixels at depth edges); None: a ray without a footprint.
        dual_return: the sensor can report its last echo, or both the strongest and the last.
        intensity_scale: what the sensor reports as intensity: ``reflectivity_8bit`` (0-100 diffuse,
            101-255 retro-reflective: Velodyne's calibrated reflectivity, Ouster's reflectivity channel)
            or ``unit`` (0..1, as the KITTI HDL-64E scans store it).
        T_base_sensor: (4, 4) mounting, sensor frame to car base frame (default 1.73 m up, level).
        source: where the facts come from and which values are assumed.

    Arrays are converted to read-only float64 copies. Every invalid value raises :class:`InputError`
    with one line naming the spec and the problem.
    """

    name: str
    description: str = ""
    elevation_deg: np.ndarray = field(repr=False)
    azimuth_offset_deg: np.ndarray | None = field(default=None, repr=False)
    beam_vertical_offset_m: np.ndarray | None = field(default=None, repr=False)
    beam_origin_radius_m: float = 0.0
    columns: int
    rotation_hz: float
    min_range_m: float
    max_range_m: float
    range_noise_m: float
    dropout_prob: float = 0.0
    range_at_10pct_m: float | None = None
    range_at_80pct_m: float | None = None
    range_noise_weak_m: float | None = None
    beam_divergence_mrad: float | None = None
    dual_return: bool = False
    intensity_scale: str = "reflectivity_8bit"
    T_base_sensor: np.ndarray = field(default_factory=_default_mount, repr=False)
    source: str = field(default="", repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise InputError(f"lidar spec: name must be a non-empty string, got {reprlib.repr(self.name)}")
        for key in ("description", "source"):
            if not isinstance(getattr(self, key), str):
                self._fail(f"{key} must be a string")
        set_ = object.__setattr__
        elevation = self._table("elevation_deg", self.elevation_deg)
        if elevation.size == 0:
            self._fail("empty beam table (elevation_deg has no entries)")
        for key in ("azimuth_offset_deg", "beam_vertical_offset_m"):
            value = getattr(self, key)
            table = np.zeros_like(elevation) if value is None else self._table(key, value)
            if table.size != elevation.size:
                self._fail(
                    f"beam table lengths differ: elevation_deg has {elevation.size}, {key} {table.size}"
                )
            table.flags.writeable = False
            set_(self, key, table)
        elevation.flags.writeable = False
        set_(self, "elevation_deg", elevation)
        if np.any(np.abs(elevation) > 90.0):
            bad = int(np.argmax(np.abs(elevation) > 90.0))
            self._fail(f"elevation_deg[{bad}] = {elevation[bad]} is outside [-90, 90]")

        if isinstance(self.columns, bool) or not isinstance(self.columns, numbers.Integral):
            self._fail(f"columns must be an integer, got {reprlib.repr(self.columns)}")
        set_(self, "columns", int(self.columns))
        for key in _SCALAR_KEYS:
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                self._fail(f"{key} must be a number, got {reprlib.repr(value)}")
            if not math.isfinite(value):
                self._fail(f"{key} is not finite ({value})")
            set_(self, key, float(value))
        if self.columns < 1:
            self._fail(f"columns must be >= 1, got {self.columns}")
        if self.rotation_hz <= 0:
            self._fail(f"rotation_hz must be > 0, got {self.rotation_hz}")
        if self.min_range_m < 0:
            self._fail(f"min_range_m must be >= 0, got {self.min_range_m}")
        if self.max_range_m <= self.min_range_m:
            self._fail(f"max_range_m ({self.max_range_m}) must be > min_range_m ({self.min_range_m})")
        if self.range_noise_m < 0:
            self._fail(f"range_noise_m must be >= 0, got {self.range_noise_m}")
        if not 0.0 <= self.dropout_prob < 1.0:
            self._fail(f"dropout_prob must be in [0, 1), got {self.dropout_prob}")
        if self.beam_origin_radius_m < 0:
            self._fail(f"beam_origin_radius_m must be >= 0, got {self.beam_origin_radius_m}")
        for key in _RETURN_KEYS:
            value = getattr(self, key)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                self._fail(f"{key} must be a finite number, got {reprlib.repr(value)}")
            if value < 0 or (value == 0 and key != "range_noise_weak_m"):
                self._fail(f"{key} must be {'>= 0' if key == 'range_noise_weak_m' else '> 0'}, got {value}")
            set_(self, key, float(value))
        r10, r80 = self.range_at_10pct_m, self.range_at_80pct_m
        if (r10 is None) != (r80 is None):
            self._fail("range_at_10pct_m and range_at_80pct_m go together (give both or neither)")
        if r10 is not None and r10 >= r80:
            self._fail(f"range_at_10pct_m ({r10}) must be below range_at_80pct_m ({r80})")
        if not isinstance(self.dual_return, bool):
            self._fail(f"dual_return must be true or false, got {reprlib.repr(self.dual_return)}")
        if self.intensity_scale not in INTENSITY_SCALES:
            self._fail(
                f"intensity_scale must be one of {', '.join(INTENSITY_SCALES)}, got {self.intensity_scale!r}"
            )
        set_(self, "T_base_sensor", self._rigid_transform(self.T_base_sensor))

    def _fail(self, problem: str) -> NoReturn:
        raise InputError(f"lidar spec {self.name!r}: {problem}")

    def _table(self, key: str, value: Any) -> np.ndarray:
        try:
            table = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            self._fail(f"{key} must be a 1-D array of numbers")
        if table.ndim != 1:
            self._fail(f"{key} must be 1-D, got shape {table.shape}")
        if not np.all(np.isfinite(table)):
            bad = int(np.argmin(np.isfinite(table)))
            self._fail(f"{key}[{bad}] is not finite ({table[bad]})")
        return table

    def _rigid_transform(self, value: Any) -> np.ndarray:
        try:
            T = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            self._fail("T_base_sensor must be a 4x4 array of numbers")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            self._fail(f"T_base_sensor must be a finite 4x4 transform, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            self._fail(f"T_base_sensor is not a rigid transform: last row is {T[3].tolist()}")
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            self._fail("T_base_sensor is not a rigid transform: rotation part is not a proper rotation")
        T.flags.writeable = False
        return T

    @property
    def beams(self) -> int:
        """Number of beams (B), i.e. rows of the range image."""
        return int(self.elevation_deg.size)

    @property
    def fov_up_deg(self) -> float:
        """Highest beam elevation in degrees."""
        return float(self.elevation_deg.max())

    @property
    def fov_down_deg(self) -> float:
        """Lowest beam elevation in degrees (negative for every preset)."""
        return float(self.elevation_deg.min())

    @property
    def fov_deg(self) -> float:
        """Vertical field of view in degrees, ``fov_up_deg - fov_down_deg``."""
        return self.fov_up_deg - self.fov_down_deg

    @property
    def rows_by_elevation(self) -> np.ndarray:
        """(B,) beam index of each range-image row; row 0 is the highest beam, ties keep index order."""
        return np.argsort(-self.elevation_deg, kind="stable")

    @property
    def row_of_beam(self) -> np.ndarray:
        """(B,) range-image row of each beam index: the inverse of :attr:`rows_by_elevation`."""
        rows = self.rows_by_elevation
        inverse = np.empty_like(rows)
        inverse[rows] = np.arange(rows.size)
        return inverse

    @property
    def sweep_period_s(self) -> float:
        """Duration of one 360° sweep in seconds."""
        return 1.0 / self.rotation_hz

    def with_columns(self, columns: int) -> LidarSpec:
        """A copy with another number of columns per sweep (validated like the original)."""
        return dataclasses.replace(self, columns=columns)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (str, float, int, lists) in the YAML schema; ``spec_from_dict`` reads it back."""
        data = {
            key: getattr(self, key)
            for key in _SCHEMA
            if key != "mount" and not (key in _RETURN_KEYS and getattr(self, key) is None)
        }
        data = {
            key: value.tolist() if isinstance(value, np.ndarray) else value for key, value in data.items()
        }
        xyz_m, rpy_deg = xyz_rpy_from_transform(self.T_base_sensor)
        data["mount"] = {"xyz_m": xyz_m, "rpy_deg": rpy_deg}
        return data

    def to_yaml(self, path: str | os.PathLike[str]) -> None:
        """Write the spec as a YAML file that :func:`load_spec_file` reads back."""
        text = yaml.safe_dump(
            self.to_dict(), sort_keys=False, default_flow_style=None, width=110, allow_unicode=True
        )
        Path(path).write_text(text, encoding="utf-8")


# --- mount <-> transform -----------------------------------------------------------------------------


# --- YAML schema and loader --------------------------------------------------------------------------

# key -> (kind, required); the order is the order of to_dict() and of the preset files
_SCHEMA: dict[str, tuple[str, bool]] = {
    "name": ("str", True),
    "description": ("str", False),
    "source": ("str", False),
    "elevation_deg": ("list", True),
    "azimuth_offset_deg": ("list", False),
    "beam_vertical_offset_m": ("list", False),
    "beam_origin_radius_m": ("float", False),
    "columns": ("int", True),
    "rotation_hz": ("float", True),
    "min_range_m": ("float", True),
    "max_range_m": ("float", True),
    "range_noise_m": ("float", True),
    "dropout_prob": ("float", False),
    "range_at_10pct_m": ("float", False),
    "range_at_80pct_m": ("float", False),
    "range_noise_weak_m": ("float", False),
    "beam_divergence_mrad": ("float", False),
    "dual_return": ("bool", False),
    "intensity_scale": ("str", False),
    "mount": ("mount", False),
}
_MOUNT_KEYS = ("xyz_m", "rpy_deg")


def _check_keys(data: Mapping[Any, Any], valid: Any, where: str, inside: str = "") -> None:
    for key in data:
        if key not in valid:
            close = difflib.get_close_matches(str(key), list(valid), n=1)
            tip = f"did you mean {close[0]!r}?" if close else "valid keys: " + ", ".join(valid)
            raise InputError(f"{where}: unknown key {key!r}{inside} ({tip})")


def _text(value: Any, key: str, where: str) -> str:
    if not isinstance(value, str):
        raise InputError(f"{where}: {key} must be a string, got {reprlib.repr(value)}")
    return value


def _number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{where}: {key} must be a number, got {reprlib.repr(value)}")
    return float(value)


def _integer(value: Any, key: str, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{where}: {key} must be an integer, got {reprlib.repr(value)}")
    return value


def _numbers(value: Any, key: str, where: str, length: int | None = None) -> list[float]:
    if not isinstance(value, list | tuple) or (length is not None and len(value) != length):
        what = "a list of numbers" if length is None else f"a list of {length} numbers"
        raise InputError(f"{where}: {key} must be {what}, got {reprlib.repr(value)}")
    return [_number(item, f"{key}[{i}]", where) for i, item in enumerate(value)]


def _mount(value: Any, key: str, where: str) -> np.ndarray:
    if not isinstance(value, Mapping):
        raise InputError(
            f"{where}: {key} must be a mapping with keys xyz_m, rpy_deg, got {reprlib.repr(value)}"
        )
    _check_keys(value, _MOUNT_KEYS, where, inside=f" in {key!r}")
    xyz_m = _numbers(value.get("xyz_m", list(DEFAULT_MOUNT_XYZ_M)), f"{key}.xyz_m", where, length=3)
    rpy_deg = _numbers(value.get("rpy_deg", [0.0, 0.0, 0.0]), f"{key}.rpy_deg", where, length=3)
    return transform_from_xyz_rpy(xyz_m, rpy_deg)


def _flag(value: Any, key: str, where: str) -> bool:
    if not isinstance(value, bool):
        raise InputError(f"{where}: {key} must be true or false, got {reprlib.repr(value)}")
    return value


_PARSERS = {"bool": _flag, "str": _text, "float": _number, "int": _integer, "list": _numbers, "mount": _mount}


def spec_from_dict(data: Mapping[str, Any], where: str = "<dict>") -> LidarSpec:
    """Build a spec from a mapping in the YAML schema; ``where`` (e.g. the file path) prefixes errors.

    Unknown keys (at any level), missing required keys and wrong types raise :class:`InputError`.
    """
    if not isinstance(data, Mapping):
        raise InputError(f"{where}: a LiDAR spec must be a mapping of keys, got {type(data).__name__}")
    _check_keys(data, _SCHEMA, where)
    missing = [key for key, (_, required) in _SCHEMA.items() if required and key not in data]
    if missing:
        raise InputError(f"{where}: missing required key(s) {', '.join(map(repr, missing))}")
    kwargs = {key: _PARSERS[_SCHEMA[key][0]](value, key, where) for key, value in data.items()}
    if "mount" in kwargs:
        kwargs["T_base_sensor"] = kwargs.pop("mount")
    try:
        return LidarSpec(**kwargs)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _spec_from_yaml(text: str, where: str) -> LidarSpec:
    data = parse_yaml(text, where)
    if not isinstance(data, dict):
        got = "an empty file" if data is None else f"a {type(data).__name__}"
        raise InputError(f"{where}: expected a mapping of LiDAR spec keys, got {got}")
    return spec_from_dict(data, where)


def load_spec_file(path: str | os.PathLike[str]) -> LidarSpec:
    """Load a spec from a YAML file; a missing, unreadable or malformed file raises :class:`InputError`."""
    return _spec_from_yaml(read_text(path, "LiDAR spec file"), str(path))


# --- presets -----------------------------------------------------------------------------------------

_VENDORS = ("velodyne-", "ouster-", "quanergy-")
_ALIASES = {
    "mq8": "mq-8",
    "vlp16": "vlp-16",
    "puck": "vlp-16",
    "hdl32": "hdl-32e",
    "hdl-32": "hdl-32e",
    "hdl32e": "hdl-32e",
    "hdl64": "hdl-64e",
    "hdl-64": "hdl-64e",
    "hdl64e": "hdl-64e",
    "hdl-64e-s2": "hdl-64e",
    "hdl64-nominal": "hdl-64e-nominal",
    "hdl-64-nominal": "hdl-64e-nominal",
    "hdl64e-nominal": "hdl-64e-nominal",
    "os1-64-gen1": "os1-64",
    "os164": "os1-64",
    "os1128": "os1-128",
}


@lru_cache(maxsize=1)
def _preset_files() -> dict[str, Traversable]:
    folder = resources.files("rangemcl") / "presets"
    return {item.name.removesuffix(".yaml"): item for item in folder.iterdir() if item.name.endswith(".yaml")}


@cache
def _load_preset(name: str) -> LidarSpec:
    # Specs are immutable (frozen, read-only arrays), so one shared instance per preset is safe.
    return _spec_from_yaml(_preset_files()[name].read_text(encoding="utf-8"), f"rangemcl/presets/{name}.yaml")


def _canonical(name: str) -> str:
    key = "-".join(name.strip().lower().replace("_", " ").split())
    key = next((key.removeprefix(v) for v in _VENDORS if key.startswith(v)), key)
    return _ALIASES.get(key, key)


def preset_names() -> list[str]:
    """Names of the built-in presets, sorted."""
    return sorted(_preset_files())


def load_spec(name_or_path: str | os.PathLike[str]) -> LidarSpec:
    """A preset by name (case-insensitive, aliases such as ``vlp16`` accepted) or a spec from a YAML file.

    Anything ending in ``.yaml``/``.yml`` or containing a path separator is read as a file.
    """
    text = os.fspath(name_or_path)
    if (
        isinstance(name_or_path, os.PathLike)
        or Path(text).suffix.lower() in (".yaml", ".yml")
        or ("/" in text or os.sep in text)
    ):
        return load_spec_file(text)
    key = _canonical(text)
    if key in _preset_files():
        return _load_preset(key)
    if Path(text).is_file():
        return load_spec_file(text)
    close = difflib.get_close_matches(key, sorted({*preset_names(), *_ALIASES}), n=1)
    tip = f"did you mean {_ALIASES.get(close[0], close[0])!r}? " if close else ""
    names = ", ".join(preset_names())
    raise InputError(f"unknown LiDAR preset {text!r} ({tip}valid names: {names}; or give a YAML file path)")
