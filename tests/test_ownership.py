"""No module writes another module's attributes: each part of a drive owns its state, and
others reach it through what it offers (issue 38). An AST scan of the production code:

- the attributes a module of ``motor_driver/drive`` declares are those it assigns as
  ``self.<name>``;
- anywhere in the production code, an assignment to ``<x>.<name>`` (``x`` not ``self``, or
  ``self.<part>.<name>``) of a name declared only by other drive modules is a violation.

The checker is tried on a broken snippet too, so the test can fail.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator

from .conftest import REPO

DRIVE = REPO / "motor_driver" / "drive"
PRODUCTION = [REPO / "motor_driver", REPO / "nodes", REPO / "rovercan", REPO / "can_config", REPO / "virtual_can"]


def _stores(tree: ast.AST) -> Iterator[ast.Attribute]:
    for node in ast.walk(tree):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = list(node.targets)
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        for target in targets:
            stack = [target]
            while stack:
                t = stack.pop()
                if isinstance(t, (ast.Tuple, ast.List)):
                    stack += t.elts
                elif isinstance(t, ast.Attribute):
                    yield t


def _is_self(node: ast.expr) -> bool:
    return isinstance(node, ast.Name) and node.id == "self"


def declared(source: str) -> set[str]:
    """The attributes a module declares: assigned as self.<name>."""
    return {t.attr for t in _stores(ast.parse(source)) if _is_self(t.value)}


def violations(source: str, own: set[str], others: dict[str, set[str]]) -> list[str]:
    """Writes in ``source`` to attributes only other drive modules declare."""
    found = []
    for target in _stores(ast.parse(source)):
        if _is_self(target.value) or target.attr in own:
            continue
        owners = sorted(m for m, names in others.items() if target.attr in names)
        if owners:
            found.append(f"line {target.lineno}: writes .{target.attr}, declared by {', '.join(owners)}")
    return found


#: Every part keeps a read-only copy of the drive's identity; messages and others have fields of
#: these names too (MotorState.name), so they say nothing about ownership.
IDENTITY = frozenset({"name", "node_id", "config"})


def drive_declarations() -> dict[str, set[str]]:
    return {p.name: declared(p.read_text()) - IDENTITY for p in sorted(DRIVE.glob("*.py"))}


def scan() -> list[str]:
    decl = drive_declarations()
    problems = []
    for root in PRODUCTION:
        for path in sorted(root.rglob("*.py")):
            own = decl.get(path.name, set()) if path.parent == DRIVE else declared(path.read_text())
            others = {m: names for m, names in decl.items() if not (path.parent == DRIVE and m == path.name)}
            problems += [f"{path.relative_to(REPO)} {v}" for v in violations(path.read_text(), own, others)]
    return problems


def test_no_module_writes_a_drive_parts_attributes() -> None:
    assert scan() == []


def test_the_check_finds_a_write_into_another_part() -> None:
    decl = drive_declarations()
    broken = "def f(drive):\n    drive.cache._lost = True\n    drive.channel.cw = 0\n"
    found = violations(broken, set(), decl)
    assert len(found) == 2 and "state.py" in found[0] and "channel.py" in found[1], found
    inside = "class Boot:\n    def f(self):\n        self._cache._booted = True\n"
    assert violations(inside, declared(inside), decl), "a part writing another's field through its port"


def test_the_parts_are_composed_not_stacked() -> None:
    """Every class of the drive package stands alone (no base class of the package)."""
    for path in sorted(DRIVE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                bases = [ast.unparse(b) for b in node.bases]
                assert not [b for b in bases if b not in {"NamedTuple", "Protocol", "Exception"}], (path.name,
                                                                                                   node.name, bases)
