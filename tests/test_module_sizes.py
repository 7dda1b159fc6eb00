"""One responsibility per module, kept: each module's docstring says what it is for (its first
sentence) and which thread owns its state (or that it keeps none), no function over 60 lines (as
Python's ``ast`` counts them), and ruff's complexity and size checks switched on. A module's
length is no verdict: ``python scripts/module_sizes.py`` reports the largest modules and classes,
for review."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

from .conftest import REPO

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

PACKAGES = ("motor_driver", "virtual_can", "rovercan", "nodes", "can_config")
FUNCTION_MAX_LINES = 60
SOURCES = sorted(path for package in PACKAGES for path in (REPO / package).rglob("*.py"))


def test_the_packages_have_sources() -> None:
    assert all(REPO / package / "__init__.py" in SOURCES for package in PACKAGES)


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_function_sizes(path: Path) -> None:
    source = path.read_text()
    too_long = [f"{node.name} ({node.end_lineno - node.lineno + 1} lines, line {node.lineno})"
                for node in ast.walk(ast.parse(source))
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                and node.end_lineno is not None and node.end_lineno - node.lineno + 1 > FUNCTION_MAX_LINES]
    assert not too_long, f"{path.relative_to(REPO)}: functions over {FUNCTION_MAX_LINES} lines: {too_long}"


#: An owner statement: a line "Owner: ..." / "Threads: ...", or prose that names the owning thread
#: or says the module keeps no state.
OWNER = re.compile(r"(?im)^(owner|owners|threads?)\b[^\n]*:|\bowns\b|\bowned by\b|\bno state\b|\bstateless\b"
                   r"|\bpure\b|\bvalues? only\b|\bthread\b")


def responsibility_problems(source: str) -> list[str]:
    """What a module's docstring lacks: a first sentence saying what it is for, an owner."""
    doc = ast.get_docstring(ast.parse(source)) or ""
    problems = []
    first = doc.split("\n\n")[0].strip()
    if len(first.split()) < 4:
        problems.append("no first sentence saying what the module is for")
    if not OWNER.search(doc):
        problems.append("no owner: say which thread owns its state ('Owner: ...'), or that it keeps none")
    return problems


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_each_module_names_its_responsibility_and_owner(path: Path) -> None:
    problems = responsibility_problems(path.read_text())
    assert not problems, f"{path.relative_to(REPO)}'s docstring: {'; '.join(problems)}"


def test_the_docstring_check_can_fail() -> None:
    assert len(responsibility_problems("x = 1\n")) == 2
    assert responsibility_problems('"""Reads the wheels of the rover."""\n') == [
        "no owner: say which thread owns its state ('Owner: ...'), or that it keeps none"]
    assert responsibility_problems('"""Reads the wheels of the rover.\n\nOwner: the receive thread.\n"""\n') == []


def test_ruff_checks_complexity_and_size() -> None:
    lint = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]
    assert "C901" in lint["select"] and "PL" in lint["select"]
    switched_off = {"C901", "PLR0911", "PLR0912", "PLR0913", "PLR0915"} & set(lint.get("ignore", []))
    assert not switched_off, f"switched off for the whole project: {sorted(switched_off)}"
    for pattern, rules in lint.get("per-file-ignores", {}).items():
        assert not any(p in pattern for p in PACKAGES), f"{pattern}: the stack's own packages get no exemption"
        assert "C901" not in rules and "PLR0912" not in rules, f"{pattern}: complexity is checked everywhere"
