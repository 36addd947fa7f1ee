"""Strict typed settings: every nesting level rejects unknown keys and wrong types, naming file and key."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest
import yaml

from rangemcl.config import from_dict, load_config, to_dict, write_config
from rangemcl.errors import InputError


@dataclass
class Inner:
    voxel_m: float = 1.0
    enabled: bool = True


@dataclass
class Outer:
    depth: int = 9
    name: str = "x"
    height_m: float | None = None
    inner: Inner = field(default_factory=Inner)


def test_defaults_and_overrides(tmp_path):
    assert load_config(Outer, None) == Outer()
    p = tmp_path / "c.yaml"
    p.write_text("depth: 7\ninner:\n  voxel_m: 2\n")
    c = load_config(Outer, p)
    assert c.depth == 7 and c.inner.voxel_m == 2.0 and isinstance(c.inner.voxel_m, float) and c.inner.enabled
    out = write_config(c, tmp_path / "eff.yaml")
    assert load_config(Outer, out) == c
    assert yaml.safe_load(out.read_text()) == to_dict(c)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("dept: 7\n", r"unknown key 'dept' \(did you mean 'depth'\?\)"),
        ("inner:\n  voxel: 2\n", r"unknown key 'inner.voxel' \(did you mean 'inner.voxel_m'|voxel_m"),
        ("depth: 7.5\n", r"'depth' must be an integer"),
        ("inner:\n  enabled: 1\n", r"'inner.enabled' must be true or false"),
        ("inner: 3\n", r"inner must be a mapping"),
        ("height_m: high\n", r"'height_m' has the wrong type"),
        ("depth: [1\n", r"malformed YAML"),
    ],
)
def test_bad_configs_name_file_and_key(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as err:
        load_config(Outer, p)
    assert str(p) in str(err.value)


def test_missing_file():
    with pytest.raises(InputError, match="no such config file"):
        load_config(Outer, "/nonexistent/c.yaml")


def test_required_key():
    @dataclass
    class Needs:
        size: float

    with pytest.raises(InputError, match="missing key 'size'"):
        from_dict(Needs, {}, "x.yaml")
