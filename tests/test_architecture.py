"""The import structure of the two packages, read from the source (every import, those inside functions
included): ``python -m pytest tests/test_architecture.py -v`` is the check anyone can run.

* ``rangemcl`` runs on real data with no simulator: it imports nothing of ``simbed``, MuJoCo or Gymnasium;
* no circle: no module of ``rangemcl`` or ``simbed`` reaches itself through the imports of others;
* no arrow back up: ``rangemcl``'s modules sit in layers (:data:`LAYERS`, from the foundation to the
  command line) and a module imports only from its own layer or those below;
* no private name (``_name``) is imported from another module, in the packages and in ``tools/``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# rangemcl's layers, lowest first: a module's layer is that of its longest listed prefix
LAYERS = [
    # the foundation: errors, configs, pose math, synthetic meshes, files, pools, checkpoints
    ["errors", "config", "se2", "meshgen", "common"],
    # the sensing core: sensor specs, range images, the ray caster
    ["sensors", "rangeimage", "raycast"],
    # recordings: the KITTI folder, bags, scan folders, one source for all, LiDAR odometry
    ["datasets"],
    # the map the localizer reads
    ["maps"],
    # the map builder
    ["mapping"],
    # the localizer
    ["localization"],
    # evaluation and pictures
    ["evaluation", "viz"],
    # a localization run over a recording
    ["localization.pipeline"],
    # the command line
    ["cli"],
]  # fmt: skip


def _modules(package: str) -> dict[str, Path]:
    out = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = path
    return out


MODULES = {**_modules("rangemcl"), **_modules("simbed")}


def _imports(path: Path) -> list[tuple[str, str | None, int]]:
    """``(module, imported name or None, line)`` of every absolute import in the file."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.module, a.name, node.lineno) for a in node.names]
    return out


def _target(module: str, name: str | None) -> str | None:
    """The module of ours that an import reaches (a submodule imported by name counts as that one)."""
    if name is not None and f"{module}.{name}" in MODULES:
        return f"{module}.{name}"
    return module if module in MODULES else None


def _graph() -> dict[str, set[str]]:
    return {
        name: {t for m, n, _ in _imports(path) if (t := _target(m, n)) is not None and t != name}
        for name, path in MODULES.items()
    }


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "rangemcl" or len(parts) == 1:
        return None
    rest = parts[1:]
    for n in range(len(rest), 0, -1):  # the longest listed prefix
        for k, layer in enumerate(LAYERS):
            if ".".join(rest[:n]) in layer:
                return k
    raise AssertionError(f"{module}: in no layer of LAYERS (add it where it belongs)")


def test_rangemcl_needs_no_simulator():
    bad = [
        f"{MODULES[name].relative_to(ROOT)}:{line} imports {module}"
        for name in MODULES
        if name.startswith("rangemcl")
        for module, _, line in _imports(MODULES[name])
        if module.split(".")[0] in ("simbed", "mujoco", "gymnasium")
    ]
    assert not bad, "\n".join(bad)


def test_no_circle_of_imports():
    graph = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                circles.append(sorted(part))

    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, f"modules that import each other: {circles}"


def test_no_arrow_back_up():
    graph = _graph()
    bad = [
        f"{a} ({LAYERS[_layer(a)][0]}...) imports {b} ({LAYERS[_layer(b)][0]}...)"
        for a, targets in graph.items()
        if _layer(a) is not None
        for b in targets
        if _layer(b) is not None and _layer(b) > _layer(a)
    ]
    assert not bad, "\n".join(sorted(bad))


@pytest.mark.parametrize("folder", ["rangemcl", "simbed", "tools"])
def test_no_private_name_from_another_module(folder):
    bad = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        here = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for module, name, line in _imports(path):
            ours = module.split(".")[0] in ("rangemcl", "simbed")
            if ours and name and name.startswith("_") and not name.startswith("__") and module != here:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name} from {module}")
    assert not bad, "\n".join(bad)
