"""Typed settings: nested dataclasses with defaults in one place, loaded strictly from YAML.

A misspelled or unknown key at any nesting level, a missing required key or a value of the wrong type is
an :class:`InputError` that names the file and the dotted key (and suggests the closest valid key). Core
classes never see these objects: small factories turn them into plain constructor arguments.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rangemcl.common.atomic import atomic_write
from rangemcl.common.yamlio import parse_yaml, read_text
from rangemcl.errors import InputError

T = TypeVar("T")


def from_dict(cls: type[T], data: Any, where: str, path: str = "") -> T:
    """Build dataclass ``cls`` from a mapping, recursively and strictly (see module docstring)."""
    if data is None:
        data = {}
    label = path or "the top level"
    if not isinstance(data, dict):
        raise InputError(f"{where}: {label} must be a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key in data:
        if key not in fields:
            close = difflib.get_close_matches(str(key), list(fields), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (valid: {', '.join(fields)})"
            raise InputError(f"{where}: unknown key '{_join(path, key)}'{hint}")
    values = {}
    for name, f in fields.items():
        dotted = _join(path, name)
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(f"{where}: missing key '{dotted}'")
            continue
        values[name] = _convert(hints[name], data[name], where, dotted)
    return cls(**values)


def _join(path: str, key) -> str:
    return f"{path}.{key}" if path else str(key)


def _convert(tp, value, where: str, dotted: str):
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, where, dotted)
            except InputError:
                continue
        raise InputError(f"{where}: '{dotted}' has the wrong type ({value!r})")
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where, dotted)
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise InputError(f"{where}: '{dotted}' must be a list, got {value!r}")
        (item,) = typing.get_args(tp)[:1] or (Any,)
        return type(value)(_convert(item, v, where, f"{dotted}[{i}]") for i, v in enumerate(value))
    if tp is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: '{dotted}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: '{dotted}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"{where}: '{dotted}' must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: '{dotted}' must be a string, got {value!r}")
        return value
    return value


def load_config(cls: type[T], path: str | os.PathLike | None) -> T:
    """Defaults of ``cls``, overridden by the YAML file at ``path`` (if given), and checked (``check()``,
    where the class has one) so that a bad value is refused before any work, naming the file and key."""
    if path is None:
        return cls()
    text = read_text(path, "config file")
    out = from_dict(cls, parse_yaml(text, str(path)), str(path))
    if hasattr(out, "check"):
        out.check(str(path))
    return out


def to_dict(config) -> dict:
    """Plain nested dict of a settings dataclass (for writing the effective config)."""
    return dataclasses.asdict(config)


def write_config(config, path: str | os.PathLike) -> Path:
    """Write the effective settings as YAML next to a run's results."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, yaml.safe_dump(to_dict(config), sort_keys=False))
