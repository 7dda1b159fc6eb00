"""One responsibility per module, kept: no module of the stack over 400 lines, no function over
60 (as Python's ``ast`` counts them), and ruff's complexity and size checks switched on."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from .conftest import REPO

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

PACKAGES = ("motor_driver", "virtual_can", "rovercan", "nodes", "can_config")
MODULE_MAX_LINES = 400
FUNCTION_MAX_LINES = 60
SOURCES = sorted(path for package in PACKAGES for path in (REPO / package).rglob("*.py"))


def test_the_packages_have_sources() -> None:
    assert all(REPO / package / "__init__.py" in SOURCES for package in PACKAGES)


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_module_and_function_sizes(path: Path) -> None:
    source = path.read_text()
    lines = len(source.splitlines())
    assert lines <= MODULE_MAX_LINES, f"{path.relative_to(REPO)}: {lines} lines (at most {MODULE_MAX_LINES}); split it"
    too_long = [f"{node.name} ({node.end_lineno - node.lineno + 1} lines, line {node.lineno})"
                for node in ast.walk(ast.parse(source))
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                and node.end_lineno is not None and node.end_lineno - node.lineno + 1 > FUNCTION_MAX_LINES]
    assert not too_long, f"{path.relative_to(REPO)}: functions over {FUNCTION_MAX_LINES} lines: {too_long}"


def test_ruff_checks_complexity_and_size() -> None:
    lint = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]
    assert "C901" in lint["select"] and "PL" in lint["select"]
    switched_off = {"C901", "PLR0911", "PLR0912", "PLR0913", "PLR0915"} & set(lint.get("ignore", []))
    assert not switched_off, f"switched off for the whole project: {sorted(switched_off)}"
    for pattern, rules in lint.get("per-file-ignores", {}).items():
        assert not any(p in pattern for p in PACKAGES), f"{pattern}: the stack's own packages get no exemption"
        assert "C901" not in rules and "PLR0912" not in rules, f"{pattern}: complexity is checked everywhere"
