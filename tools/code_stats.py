"""The size of the house: per package, the largest modules (lines) and the longest functions (lines from
``def`` to the end of the body), the number of modules, and the widest constructors (parameters).

    python tools/code_stats.py              # this checkout
    python tools/code_stats.py --root DIR   # another checkout (e.g. a git worktree of an older tag)
    python tools/code_stats.py --top 5
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path


def stats(root: Path, package: str, top: int) -> list[str]:
    modules, functions, inits = [], [], []
    for path in sorted((root / package).rglob("*.py")):
        text = path.read_text()
        rel = str(path.relative_to(root))
        modules.append((len(text.splitlines()), rel))
        for node in ast.walk(ast.parse(text, rel)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                functions.append((node.end_lineno - node.lineno + 1, f"{rel}:{node.lineno} {node.name}"))
                if node.name == "__init__":
                    args = node.args
                    n = len(args.args) + len(args.kwonlyargs) + len(args.posonlyargs) - 1  # not self
                    inits.append((n, f"{rel}:{node.lineno}"))
    out = [f"{package}: {len(modules)} modules, {sum(n for n, _ in modules):,} lines"]
    out += [f"  module   {n:5d} lines  {name}" for n, name in sorted(modules, reverse=True)[:top]]
    out += [f"  function {n:5d} lines  {name}" for n, name in sorted(functions, reverse=True)[:top]]
    out += [f"  __init__ {n:5d} params {name}" for n, name in sorted(inits, reverse=True)[:top]]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--top", type=int, default=3)
    args = ap.parse_args()
    for package in ("rangemcl", "simbed"):
        print("\n".join(stats(args.root, package, args.top)))


if __name__ == "__main__":
    main()
