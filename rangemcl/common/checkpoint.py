"""The state of a running filter, saved and restored without pickle (``rangemcl localize --resume``).

:func:`save_state` walks an object's attributes and writes what changes while a filter runs: numbers,
strings, numpy arrays, random generators, and lists, tuples, dicts and deques of them, recursively into
the objects of rangemcl's own classes. What is built from the map and the settings (the map, the ray
caster, the renderer, the place prior, scoring kernels: see :data:`RESOURCES`) and anything of another
library is left out: a resumed run builds those again from the same inputs.

:func:`restore_state` writes the saved values back into a freshly built object of the same structure,
in place: a random generator shared by several components gets its state once and stays shared, and
objects of rangemcl's classes that did not exist at build time (e.g. the leading hypothesis) are made
again by setting their attributes (no constructor, no code from the file is run). Arrays go into one
``.npz`` file (``allow_pickle=False``) with everything else as JSON text beside them, written
atomically, so a checkpoint is whole or absent and as safe to load as the rest of a results folder.
"""

from __future__ import annotations

import importlib
import json
import math
from collections import deque
from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write, savez_stable
from rangemcl.errors import InputError

FORMAT = 1

# Classes whose objects are built from the map and the settings, never state.
RESOURCES = {
    "rangemcl.maps.meshmap.MeshMap",
    "rangemcl.maps.view.MapView",
    "rangemcl.raycast.RayCaster",
    "rangemcl.raycast.MeshInfo",
    "rangemcl.rangeimage.RangeImageGeometry",
    "rangemcl.sensors.LidarSpec",
    "rangemcl.localization.renderer.ParticleRenderer",
    "rangemcl.localization.place_prior.PlacePrior",
    "rangemcl.localization.spread.DrivableArea",
}


def _qualname(obj) -> str:
    cls = type(obj)
    return f"{cls.__module__}.{cls.__qualname__}"


def _is_ours(obj) -> bool:
    return type(obj).__module__.startswith("rangemcl.") and _qualname(obj) not in RESOURCES


class _Writer:
    def __init__(self):
        self.arrays: dict[str, np.ndarray] = {}
        self.seen: dict[int, str] = {}  # id of an array or object already written -> its reference

    def value(self, v, path: str):
        if v is None or isinstance(v, (bool, str)):
            return v
        if isinstance(v, (int, np.integer)) and not isinstance(v, np.bool_):
            return int(v) if isinstance(v, int) else {"np": v.dtype.str, "v": int(v)}
        if isinstance(v, float):
            return v if math.isfinite(v) else {"float": repr(v)}
        if isinstance(v, np.generic):
            if v.dtype.kind == "f" and not math.isfinite(float(v)):
                return {"np": v.dtype.str, "v": repr(float(v))}
            if v.dtype.kind not in "biuf":
                return _SKIP
            return {"np": v.dtype.str, "v": v.item()}
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                return _SKIP
            if id(v) in self.seen:
                return {"ref": self.seen[id(v)]}
            key = f"a{len(self.arrays)}"
            self.arrays[key] = v
            self.seen[id(v)] = key
            return {"arr": key}
        if isinstance(v, np.random.Generator):
            if id(v) in self.seen:
                return {"ref": self.seen[id(v)]}
            self.seen[id(v)] = path
            return {"rng": type(v.bit_generator).__name__, "state": _json_ints(v.bit_generator.state)}
        if isinstance(v, (list, tuple, deque)):
            items = [self.value(x, f"{path}[{i}]") for i, x in enumerate(v)]
            if any(x is _SKIP for x in items):
                return _SKIP
            kind = "deque" if isinstance(v, deque) else type(v).__name__
            out = {kind: items}
            if isinstance(v, deque):
                out["maxlen"] = v.maxlen
            return out
        if isinstance(v, dict):
            if not all(isinstance(k, (str, int)) for k in v):
                return _SKIP
            items = [[k, self.value(x, f"{path}.{k}")] for k, x in v.items()]
            if any(x is _SKIP for _, x in items):
                return _SKIP
            return {"dict": items}
        if _is_ours(v) and hasattr(v, "__dict__"):
            if id(v) in self.seen:
                return {"ref": self.seen[id(v)]}
            self.seen[id(v)] = path
            attrs = {}
            for k, x in vars(v).items():
                w = self.value(x, f"{path}.{k}")
                if w is not _SKIP:
                    attrs[k] = w
            return {"obj": _qualname(v), "attrs": attrs}
        return _SKIP


class _Skip:
    pass


_SKIP = _Skip()


def _json_ints(state):
    """A bit generator's state as JSON (its big integers are plain ints: JSON holds them exactly)."""
    if isinstance(state, dict):
        return {k: _json_ints(x) for k, x in state.items()}
    if isinstance(state, np.ndarray):
        return {"uint_array": state.tolist(), "dtype": state.dtype.str}
    return state


def _state_ints(state):
    if isinstance(state, dict):
        if set(state) == {"uint_array", "dtype"}:
            return np.asarray(state["uint_array"], dtype=state["dtype"])
        return {k: _state_ints(x) for k, x in state.items()}
    return state


def save_state(path: str | Path, parts: dict, extra: dict | None = None) -> None:
    """Write ``parts`` (name -> object) and ``extra`` (plain JSON) to the ``.npz`` file ``path`` in one
    atomic write: the arrays as members, the rest as JSON text in the member ``__state__``."""
    w = _Writer()
    tree = {name: w.value(obj, name) for name, obj in parts.items()}
    doc = json.dumps({"format": FORMAT, "state": tree, "extra": extra or {}})
    members = {**w.arrays, "__state__": np.frombuffer(doc.encode(), np.uint8)}
    atomic_write(Path(path), lambda fh: savez_stable(fh, **members))


def read_state(path: str | Path) -> tuple[dict, dict, dict[str, np.ndarray]]:
    """``(state tree, extra, arrays)`` of a checkpoint written by :func:`save_state`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        doc = json.loads(arrays.pop("__state__").tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: unreadable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{path}: not a checkpoint of this version (format {doc.get('format')!r})")
    return doc["state"], doc.get("extra", {}), arrays


class _Reader:
    def __init__(self, arrays: dict[str, np.ndarray], where: str):
        self.arrays = arrays
        self.where = where
        self.made: dict[str, object] = {}  # reference -> the restored object

    def fail(self, path: str, what: str):
        raise InputError(f"{self.where}: checkpoint does not fit this run at {path} ({what})")

    def value(self, w, current, path: str):
        """The value to hold at ``path``: ``current`` updated in place where it can be."""
        if w is None or isinstance(w, (bool, int, float, str)):
            return w
        if not isinstance(w, dict):
            self.fail(path, "unknown entry")
        if "ref" in w:
            if w["ref"] in self.made:
                return self.made[w["ref"]]
            if w["ref"] in self.arrays:
                return self.arrays[w["ref"]]
            self.fail(path, f"dangling reference {w['ref']}")
        if "float" in w:
            return float(w["float"])
        if "np" in w:
            v = w["v"]
            return np.dtype(w["np"]).type(float(v) if isinstance(v, str) else v)
        if "arr" in w:
            arr = self.arrays.get(w["arr"])
            if arr is None:
                self.fail(path, f"array {w['arr']} missing")
            self.made[w["arr"]] = arr
            return arr
        if "rng" in w:
            if not isinstance(current, np.random.Generator):
                self.fail(path, "expected a random generator")
            if type(current.bit_generator).__name__ != w["rng"]:
                self.fail(path, f"bit generator {w['rng']} expected")
            current.bit_generator.state = _state_ints(w["state"])
            self.made[path] = current
            return current
        for kind in ("list", "tuple", "deque"):
            if kind in w:
                cur = list(current) if isinstance(current, (list, tuple, deque)) else []
                items = [
                    self.value(x, cur[i] if i < len(cur) else None, f"{path}[{i}]")
                    for i, x in enumerate(w[kind])
                ]
                if kind == "tuple":
                    return tuple(items)
                if kind == "deque":
                    return deque(items, maxlen=w.get("maxlen"))
                if isinstance(current, list):
                    current[:] = items  # lists shared by reference stay shared
                    return current
                return items
        if "dict" in w:
            cur = current if isinstance(current, dict) else {}
            items = {k: self.value(x, cur.get(k), f"{path}.{k}") for k, x in w["dict"]}
            if isinstance(current, dict):
                current.clear()
                current.update(items)
                return current
            return items
        if "obj" in w:
            obj = current
            if obj is None or _qualname(obj) != w["obj"]:
                obj = _new(w["obj"], path, self)
            self.made[path] = obj
            for k, x in w["attrs"].items():
                # object.__setattr__: frozen dataclasses too (the value is the one the run held)
                object.__setattr__(obj, k, self.value(x, getattr(obj, k, None), f"{path}.{k}"))
            return obj
        self.fail(path, "unknown entry")


def _new(qualname: str, path: str, reader: _Reader):
    """An empty object of one of rangemcl's own classes (attributes are set by the caller)."""
    module, _, name = qualname.rpartition(".")
    if not module.startswith("rangemcl.") or qualname in RESOURCES:
        reader.fail(path, f"class {qualname} is not restorable")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        reader.fail(path, f"class {qualname} not found")
    if not isinstance(cls, type):
        reader.fail(path, f"{qualname} is not a class")
    return cls.__new__(cls)


def restore_state(path: str | Path, parts: dict) -> dict:
    """Write a checkpoint's state back into ``parts`` (name -> the freshly built object, restored in
    place); return the checkpoint's ``extra``."""
    tree, extra, arrays = read_state(path)
    reader = _Reader(arrays, str(path))
    missing = set(parts) - set(tree)
    if missing:
        reader.fail(", ".join(sorted(missing)), "not in the checkpoint")
    for name, obj in parts.items():
        out = reader.value(tree[name], obj, name)
        if out is not obj and not isinstance(obj, (np.ndarray,)):
            reader.fail(name, "could not be restored in place")
    return extra
