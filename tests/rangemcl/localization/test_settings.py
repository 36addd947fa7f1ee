"""Every default of the localizer lives in one place, the settings classes
(:mod:`rangemcl.localization.settings`):

* the cores that the factories build (the filter and each part) take every setting as a required argument:
  a core made by hand cannot fall back on a default of its own that has drifted from the settings';
* every key of the settings reaches what :func:`~rangemcl.localization.factory.build_localizer` builds: a
  key changed alone changes the filter it makes (a key nobody reads is dead weight, or a bug);
* every key is documented where it is defined (an attribute docstring: what it does, with its unit).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import itertools
from pathlib import Path

import numpy as np
import pytest

from rangemcl.localization import settings as settings_module
from rangemcl.localization.calibration import OdometryCalibrator, ParticleCalibration
from rangemcl.localization.factory import build_localizer
from rangemcl.localization.filter import MonteCarloLocalizer
from rangemcl.localization.lost import LostDetector, SignalWatch
from rangemcl.localization.particles import MotionNoise
from rangemcl.localization.refine import ScanRefiner
from rangemcl.localization.scan_prep import select_rays
from rangemcl.localization.settings import LocalizerSettings
from rangemcl.localization.spread import drivable_cells, uniform_particles
from rangemcl.localization.tracking import Tracking
from rangemcl.maps.meshmap import MeshMap

# per-call inputs of a core (not settings): the only parameters with a default
PER_CALL = {"select_rays": {"fire_time_s", "frame_period_s", "frame_motion", "roll_pitch", "sensor_height_m"}}
# keys that the run pipeline reads, not the filter: rangemcl.localization.pipeline and rangemcl.maps.view
NOT_IN_THE_FILTER = {"map_memory_mb"}


@pytest.mark.parametrize(
    "core",
    [
        MonteCarloLocalizer,
        ScanRefiner,
        Tracking,
        LostDetector,
        SignalWatch,
        OdometryCalibrator,
        ParticleCalibration,
        MotionNoise,
        select_rays,
        drivable_cells,
        uniform_particles,
    ],
    ids=lambda c: c.__name__,
)
def test_a_core_has_no_default_of_its_own(core):
    """Built by hand or by a factory, a core gets each setting from the caller: none has a default."""
    params = inspect.signature(core).parameters
    with_default = {k for k, p in params.items() if p.default is not inspect.Parameter.empty}
    assert with_default == PER_CALL.get(core.__name__, set())


def _keys(obj, prefix: str = "") -> dict[str, object]:
    """``{"particles.global_count": value, ...}``: every leaf key of a settings object."""
    out = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_keys(value, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def _set(s: LocalizerSettings, key: str, value) -> LocalizerSettings:
    *path, leaf = key.split(".")
    s = dataclasses.replace(s, **{p: dataclasses.replace(getattr(s, p)) for p in path})
    target = s
    for p in path:
        target = getattr(target, p)
    setattr(target, leaf, value)
    return s


_CHOICES = {  # another valid value of each key that names a method
    "observation.model": "overlap",
    "observation.ray_sampling": "points",
    "observation.rendering": "planar",
    "convergence.method": "tiles",
    "recovery.signal": "residual",
    "motion.calibration": "particles",
}


_ONLY_WITH = {  # keys of a part that another choice selects: tried with that choice
    "motion.calibration_sigma": ("motion.calibration", "particles"),
    "motion.calibration_walk": ("motion.calibration", "particles"),
    "observation.overlap_": ("observation.model", "overlap"),
    "observation.histogram_": ("observation.model", "histogram"),
    "observation.field_": ("observation.model", "likelihood_field"),
}


def _other_values(key: str, value):
    """Candidate values different from ``value`` (the first that passes the settings' check is used)."""
    if key in _CHOICES:
        return [_CHOICES[key]]
    if isinstance(value, bool):
        return [not value]
    if value is None:
        return [0.5, 30.0, 5]
    if isinstance(value, int):
        return [value + 1, max(value - 1, 0)]
    return [value * 1.5 + 0.01, value * 0.5, value + 0.05, value - 0.05]


def _state(obj, depth: int = 0, seen=None) -> object:
    """What an object holds, as plain values: numbers, strings, arrays, and the same of its attributes
    (a partial's keywords, a dataclass's fields), a few levels down; the map, the ray caster and random
    generators left out."""
    seen = set() if seen is None else seen
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    if isinstance(obj, np.ndarray):
        return obj.tobytes() if obj.size < 100_000 else (obj.shape, float(np.nansum(obj)))
    if isinstance(obj, tuple | list):
        return tuple(_state(v, depth + 1, seen) for v in obj)
    if isinstance(obj, dict):
        return tuple(sorted((str(k), _state(v, depth + 1, seen)) for k, v in obj.items()))
    if isinstance(obj, functools.partial):
        return ("partial", obj.func.__name__, _state(obj.keywords, depth + 1, seen))
    if depth > 3 or id(obj) in seen or isinstance(obj, np.random.Generator | MeshMap):
        return type(obj).__name__
    seen.add(id(obj))
    if type(obj).__name__ in ("RayCaster", "TileStore"):
        return type(obj).__name__
    fields = vars(obj) if hasattr(obj, "__dict__") else {}
    return (type(obj).__name__, tuple(sorted((k, _state(v, depth + 1, seen)) for k, v in fields.items())))


@pytest.fixture(scope="module")
def tiny_map():
    """A flat 60 m square with a box, a drive along it (the drivable area)."""
    import trimesh

    ground = trimesh.creation.box(extents=(60.0, 60.0, 1.0))
    ground.apply_translation((0.0, 0.0, -0.5))
    block = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
    block.apply_translation((10.0, 5.0, 2.0))
    mesh = trimesh.util.concatenate([ground, block])
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=1.0)  # measured ground cells
    m = MeshMap.from_mesh(np.asarray(v), np.asarray(f), tile_size_m=30.0)
    m.drive_xy = np.column_stack([np.linspace(-20, 20, 41), np.zeros(41)])
    return m


def test_every_key_reaches_the_filter(tiny_map):
    """Changed alone, each key of the settings changes what build_localizer makes (the filter, its
    parts, the partial that selects the rays), so no key is ignored and no part is built from a value
    other than the settings'."""
    from rangemcl.raycast import RayCaster

    caster = RayCaster("cpu", 1)
    caster.add_mesh(tiny_map.vertices, tiny_map.faces, name="map")

    def state(s):
        return _state(build_localizer(tiny_map, s, seed=0, caster=caster))

    default = LocalizerSettings()
    assert state(default) == state(LocalizerSettings())  # deterministic
    ignored, unchecked = [], []
    for key, value in _keys(default).items():
        if key in NOT_IN_THE_FILTER:
            continue
        base = default
        for prefix, (switch, choice) in _ONLY_WITH.items():  # a key of a part the defaults do not use
            if key.startswith(prefix):
                base = _set(base, switch, choice)
        reference = state(base)
        for other in _other_values(key, value):
            s = _set(base, key, other)
            try:
                s.check()
            except Exception:
                continue
            if state(s) == reference:
                ignored.append(key)
            break
        else:
            unchecked.append(key)
    assert not ignored, f"keys that change nothing the filter holds: {ignored}"
    assert not unchecked, f"keys without a valid other value to try: {unchecked}"


def _settings_classes() -> list[type]:
    return [
        c
        for _, c in inspect.getmembers(settings_module, inspect.isclass)
        if dataclasses.is_dataclass(c) and c.__module__ == settings_module.__name__
    ]


def _attribute_docstrings(cls: type) -> dict[str, str]:
    """``{field: docstring}`` of a dataclass: the string literal right under each field."""
    tree = ast.parse(Path(inspect.getsourcefile(cls)).read_text())
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    docs, body = {}, node.body
    for a, b in itertools.pairwise(body):
        field = isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name)
        doc = isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
        if field and doc and isinstance(b.value.value, str):
            docs[a.target.id] = b.value.value
    return docs


@pytest.mark.parametrize("cls", _settings_classes(), ids=lambda c: c.__name__)
def test_every_key_is_documented(cls):
    """Each key has a docstring of its own (the settings reference is generated from them)."""
    docs = _attribute_docstrings(cls)
    missing = [f.name for f in dataclasses.fields(cls) if len(docs.get(f.name, "").strip()) < 10]
    assert not missing, f"{cls.__name__}: keys without a docstring: {missing}"


def test_the_settings_print_as_yaml_that_loads_back(tmp_path):
    """``rangemcl settings`` prints the defaults, or with ``--config`` a config's effective settings, as
    YAML that ``--config`` takes back to the same settings."""
    from typer.testing import CliRunner

    from rangemcl.cli import app
    from rangemcl.config import load_config

    config = tmp_path / "c.yaml"
    config.write_text("refine:\n  gate_m: 0.4\n")
    runner = CliRunner()
    for args, want in ((["settings"], LocalizerSettings()), (["settings", "--config", str(config)], None)):
        out = runner.invoke(app, args)
        assert out.exit_code == 0, out.output
        printed = tmp_path / "printed.yaml"
        printed.write_text(out.stdout)
        back = load_config(LocalizerSettings, printed)
        if want is None:
            want = LocalizerSettings()
            want.refine.gate_m = 0.4
        assert back == want and "sensor_height_m: null" in out.stdout


def _numeric_keys(obj, prefix=""):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numeric_keys(value, f"{prefix}{f.name}.")
        elif "float" in str(f.type) or "int" in str(f.type):
            yield f"{prefix}{f.name}"


# keys bounded by another key rather than by a rule of their own (LocalizerSettings.check)
BOUNDED_BY_ANOTHER = {"motion.calibration_max_scale", "refine.weak_information"}


def test_every_numeric_key_has_a_range_rule():
    keys = set(_numeric_keys(LocalizerSettings()))
    assert keys - set(settings_module._RULES) - BOUNDED_BY_ANOTHER == set()
    assert set(settings_module._RULES) <= keys


@pytest.mark.parametrize("key", sorted(settings_module._RULES))
def test_a_value_outside_its_rule_is_one_line_naming_the_key(key):
    rule = settings_module._RULES[key]
    bad = {"> 0": 0, ">= 0": -1.0, "in [0, 1]": 1.5, "in (0, 1]": 0.0, "in (0, 1)": 1.0}.get(
        rule, float("nan")
    )
    if rule == "an integer >= 0":
        bad = -1
    s = LocalizerSettings()
    section, _, name = key.rpartition(".")
    setattr(getattr(s, section) if section else s, name, bad)
    with pytest.raises(settings_module.InputError, match=rf"^cfg.yaml: {key.replace('.', '[.]')} must be"):
        s.check("cfg.yaml")
