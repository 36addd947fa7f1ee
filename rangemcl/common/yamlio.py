"""Strict YAML for every file a user hands us (sensor specs, sequence metadata, configs)."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml

from rangemcl.errors import InputError


class StrictLoader(yaml.SafeLoader):
    """Safe loader that rejects duplicate keys and reads YAML 1.2 floats such as ``1e3``."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        self.flatten_mapping(node)
        keys = [key.value for key, _ in node.value if isinstance(key, yaml.ScalarNode)]
        for i, key in enumerate(keys):
            if key in keys[:i]:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", node.value[i][0].start_mark
                )
        return super().construct_mapping(node, deep)


# PyYAML follows YAML 1.1, where "1e3" (no dot) is a string.
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"),
)


def read_text(path: str | os.PathLike, what: str = "file") -> str:
    """A user's text file; missing, unreadable or not UTF-8 is one ``InputError`` line naming it."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (not UTF-8)") from None
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None


def parse_yaml(text: str, where: str) -> Any:
    """Parse YAML text; malformed YAML is an ``InputError`` naming ``where`` and the line and column."""
    try:
        return yaml.load(text, Loader=StrictLoader)  # a SafeLoader subclass: safe
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
        raise InputError(f"{where}: malformed YAML{at}: {problem}") from None
