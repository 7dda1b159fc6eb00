"""The largest modules and classes of the stack, for review (information, not a verdict: a
module's size is judged by whether it keeps one responsibility, which its docstring names).

    python scripts/module_sizes.py [N]
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGES = ("motor_driver", "virtual_can", "rovercan", "nodes", "can_config")


def main(top: int = 15) -> None:
    repo = Path(__file__).resolve().parent.parent
    modules, classes = [], []
    for package in PACKAGES:
        for path in sorted((repo / package).rglob("*.py")):
            source = path.read_text()
            name = str(path.relative_to(repo))
            modules.append((len(source.splitlines()), name))
            for node in ast.walk(ast.parse(source)):
                if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
                    methods = sum(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) for n in node.body)
                    classes.append((node.end_lineno - node.lineno + 1, methods, f"{name}:{node.name}"))
    print(f"modules, {len(modules)} in all, largest first:")
    for lines, name in sorted(modules, reverse=True)[:top]:
        print(f"  {lines:5d} lines  {name}")
    print("classes, largest first:")
    for lines, methods, name in sorted(classes, reverse=True)[:top]:
        print(f"  {lines:5d} lines  {methods:3d} methods  {name}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 15)
