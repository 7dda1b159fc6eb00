"""No module writes another module's attributes: each part owns its state, and others reach it
through what it offers (issues 38, 53). An AST scan of the production code, the whole of
``motor_driver/`` and ``nodes/`` at once (not one file, not one package at a time):

- the attributes a module declares are those it assigns as ``self.<name>``;
- anywhere in the production code, an assignment to ``<x>.<name>`` (``x`` not ``self``, or
  ``self.<part>.<name>``) of a name that only other modules declare is a violation;
- the ledger's records (:mod:`motor_driver.drive.ledger`: lost, booted, another master, reconnect and
  back-off) has one writer, the supervisor (its two modules, one thread); nobody else assigns it.

The checker is tried on broken snippets too, so the test can fail.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterator
from pathlib import Path

from .conftest import REPO

DRIVE = REPO / "motor_driver" / "drive"
DECLARING = [REPO / "motor_driver", REPO / "nodes"]
PRODUCTION = [*DECLARING, REPO / "rovercan", REPO / "can_config", REPO / "virtual_can"]
#: The modules of the one writer of each module's state, where it is not the module itself.
WRITERS = {"motor_driver/drive/ledger.py": {"motor_driver/runtime/supervisor.py", "motor_driver/runtime/supervise_bus.py"}}
#: Every part keeps a read-only copy of the drive's identity; messages and others have fields of
#: these names too (MotorState.name), so they say nothing about ownership.
IDENTITY = frozenset({"name", "node_id", "config"})
#: Writes the scan cannot tell from a violation, each with its reason: (module, attribute).
KNOWN: dict[tuple[str, str], str] = {}


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
    """The attributes a module declares: assigned as self.<name>, or fields of its classes
    (a dataclass's, a NamedTuple's)."""
    tree = ast.parse(source)
    fields = {s.target.id for c in ast.walk(tree) if isinstance(c, ast.ClassDef) and not _value(c) for s in c.body
              if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)}
    return fields | {t.attr for t in _stores(tree) if _is_self(t.value)}


def _value(cls: ast.ClassDef) -> bool:
    """An immutable value (a frozen dataclass, a NamedTuple): its fields are nobody's state."""
    text = " ".join(ast.unparse(n) for n in (*cls.decorator_list, *cls.bases))
    return "frozen=True" in text or "NamedTuple" in text


def _module_file(module: str) -> str | None:
    base = REPO / module.replace(".", "/")
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.exists():
            return _name(path)
    return None


def reach(path: Path) -> set[str]:
    """The project's modules whose objects ``path`` can hold: its imports, and theirs (a write
    needs a reference; a module that reaches none of another's objects cannot write them, and
    the same name there is another thing: a ROS message's field, a Thread's ``daemon``)."""
    seen: set[str] = set()
    todo = [_name(path)]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        todo += [f for f in _imports(current) if f not in seen]
    return seen


@functools.cache
def _imports(module: str) -> tuple[str, ...]:
    """The project's files that ``module`` (a file) imports."""
    found = []
    for node in ast.walk(ast.parse((REPO / module).read_text())):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
            [f"{node.module}.{a.name}" for a in node.names] + [node.module] \
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else []
        found += [f for f in map(_module_file, names) if f is not None]
    return tuple(found)


def violations(source: str, own: set[str], others: dict[str, set[str]], module: str = "") -> list[str]:
    """Writes in ``source`` (the module ``module``) to attributes only other modules declare,
    unless ``module`` is their declared writer (WRITERS)."""
    found = []
    for target in _stores(ast.parse(source)):
        if _is_self(target.value) or target.attr in own:
            continue
        owners = sorted(m for m, names in others.items() if target.attr in names and module not in WRITERS.get(m, ()))
        if owners:
            found.append(f"line {target.lineno}: writes .{target.attr}, declared by {', '.join(owners)}")
    return found


def _name(path: Path) -> str:
    return str(path.relative_to(REPO))


def declarations() -> dict[str, set[str]]:
    return {_name(p): declared(p.read_text()) - IDENTITY for root in DECLARING for p in sorted(root.rglob("*.py"))}


def scan() -> list[str]:
    decl = declarations()
    problems = []
    for root in PRODUCTION:
        for path in sorted(root.rglob("*.py")):
            name, source = _name(path), path.read_text()
            own = decl[name] if name in decl else declared(source)
            reached = reach(path)
            others = {m: names for m, names in decl.items() if m != name and m in reached}
            for found in violations(source, own, others, name):
                attribute = found.split(".", 1)[1].split(",")[0]
                if (name, attribute) not in KNOWN:
                    problems.append(f"{name} {found}")
    return problems


def test_no_module_writes_another_modules_attributes() -> None:
    assert scan() == []


def test_the_check_finds_a_write_into_another_part() -> None:
    decl = declarations()
    broken = "def f(drive):\n    drive.cache.tpdo_count = 0\n    drive.channel.cw = 0\n"
    found = violations(broken, set(), decl)
    assert len(found) == 2 and "state.py" in found[0] and "channel.py" in found[1], found
    inside = "class Boot:\n    def f(self):\n        self._cache.guarding = True\n"
    assert violations(inside, declared(inside), decl), "a part writing another's field through its port"


def test_only_the_supervisor_writes_the_runtime_state() -> None:
    decl = declarations()
    writes = "def f(runtime, bus):\n    runtime.lost = True\n    bus.backoff_s = 1.0\n"
    for module in ("motor_driver/drive/received/state.py", "motor_driver/drive/setup/boot.py", "motor_driver/drive/setup/hostwatch.py",
                   "nodes/rover_driver.py"):
        others = {m: n for m, n in decl.items() if m != module and m in reach(REPO / module)}
        assert len(violations(writes, set(), others, module)) == 2, module
    module = "motor_driver/runtime/supervisor.py"
    others = {m: n for m, n in decl.items() if m != module and m in reach(REPO / module)}
    assert violations(writes, set(), others, module) == []


def test_a_write_across_packages_is_found() -> None:
    """nodes/ writing into motor_driver/ (and back) is a violation like any other."""
    decl = declarations()
    broken = "def f(node):\n    node.driver.supervisor._running = False\n"
    assert violations(broken, set(), decl, "nodes/rover_driver.py")


def test_the_parts_are_composed_not_stacked() -> None:
    """Every class of the drive package stands alone (no base class of the package)."""
    for path in sorted(DRIVE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                bases = [ast.unparse(b) for b in node.bases]
                assert not [b for b in bases if b not in {"NamedTuple", "Protocol", "Exception", "Enum"}], (path.name,
                                                                                                   node.name, bases)
