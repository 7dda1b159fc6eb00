"""The module maps say what the tree holds: each package's ``__init__`` docstring names (as
``:mod:`` references, in backticks) every module and subpackage of its package and nothing that
does not exist; README's "Layers, and the rooms inside them" names no module that does not exist.
And the layers stay: the core never imports rclpy, the driver and the simulator never import
each other, the configuration imports neither."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from .conftest import REPO

PACKAGES = ("can_config", "motor_driver", "virtual_can", "nodes", "rovercan")
ALL_PACKAGES = sorted(path.parent for root in PACKAGES for path in (REPO / root).rglob("__init__.py"))
MOD_ROLE = re.compile(r":mod:`~?([\w.]+)`")
README_SECTION = "## Layers, and the rooms inside them"
#: What each core package must never import (by the first part of a name it imports).
FORBIDDEN = {"can_config": {"rclpy", "motor_driver", "virtual_can", "nodes", "rovercan"},
             "motor_driver": {"rclpy", "virtual_can", "nodes", "rovercan"},
             "virtual_can": {"rclpy", "motor_driver", "nodes", "rovercan"}}


def dotted(package: Path) -> str:
    return ".".join(package.relative_to(REPO).parts)


def exists(name: str) -> bool:
    """A module (``a/b.py``) or a package (``a/b/__init__.py``) of the repository."""
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def resolve(reference: str, package: str) -> str:
    """``:mod:`.state``` inside ``motor_driver.drive`` is ``motor_driver.drive.received.state``."""
    if not reference.startswith("."):
        return reference
    level = len(reference) - len(reference.lstrip("."))
    base = package.split(".")[: len(package.split(".")) - (level - 1)]
    return ".".join([*base, reference[level:]]) if reference[level:] else ".".join(base)


def children(package: Path) -> set[str]:
    """The package's own modules and subpackages (``__main__`` counts: it is a module)."""
    modules = {p.stem for p in package.glob("*.py") if p.name != "__init__.py"}
    return modules | {p.parent.name for p in package.glob("*/__init__.py")}


@pytest.mark.parametrize("package", ALL_PACKAGES, ids=dotted)
def test_each_package_docstring_maps_every_module_and_only_those(package: Path) -> None:
    name, where = dotted(package), package.relative_to(REPO) / "__init__.py"
    doc = ast.get_docstring(ast.parse((package / "__init__.py").read_text())) or ""
    named = {resolve(ref, name) for ref in MOD_ROLE.findall(doc)}
    stale = sorted(ref for ref in named if not exists(ref))
    assert not stale, f"{where} names modules that do not exist: {stale}"
    missing = sorted(child for child in children(package) if f"{name}.{child}" not in named)
    assert not missing, (f"{where} does not name its modules {missing}: add each as :mod:`.{missing[0]}`"
                         " with what it holds")


def readme_section() -> str:
    text = (REPO / "README.md").read_text()
    assert README_SECTION in text, f"README.md lost its section {README_SECTION!r}"
    return text.split(README_SECTION, 1)[1].split("\n## ", 1)[0]


def readme_bullets() -> list[str]:
    return re.split(r"\n(?=- )", readme_section().strip().split("\n\n", 1)[0])  # the list, not what follows it


def test_the_readme_map_names_only_modules_that_exist() -> None:
    bullets = [b for b in readme_bullets() if b.startswith("- `")]
    roots_seen: set[str] = set()
    for bullet in bullets:
        head, _, body = bullet.partition(":")
        roots = [REPO / r.rstrip("/") for r in re.findall(r"`([\w/]+/)`", head)]
        assert roots and all(root.is_dir() for root in roots), f"README map: {head!r} names no directory of the tree"
        roots_seen |= {root.name for root in roots}
        tree = {p.stem for root in roots for p in root.rglob("*.py")} | {
            p.name for root in roots for p in root.rglob("*") if p.is_dir() and not p.name.startswith((".", "_"))}
        names = [n.rstrip("/").rsplit("/", 1)[-1] for n in re.findall(r"`([a-z_][a-z0-9_/]*)`", body)]
        stale = sorted({n for n in names if n not in tree})
        assert not stale, f"README map under {head!r}: no module or folder {stale} in {[r.name for r in roots]}"
    assert set(PACKAGES) <= roots_seen, f"README map: no entry for {sorted(set(PACKAGES) - roots_seen)}"


def imported_roots(path: Path) -> set[str]:
    roots: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_the_core_keeps_its_layers(package: str) -> None:
    crossing = {str(path.relative_to(REPO)): sorted(imported_roots(path) & FORBIDDEN[package])
                for path in sorted((REPO / package).rglob("*.py"))}
    crossing = {path: names for path, names in crossing.items() if names}
    assert not crossing, f"{package} imports what its layer must not: {crossing}"


#: motor_driver's folders, lowest first: each imports only folders before it (rover/ stands alone).
FOLDER_ORDER = ("process", "protocol", "rover", "bus", "drive", "diagnostics", "follow", "recording", "runtime")


def folder_imports(root: Path) -> list[tuple[str, str, str]]:
    """(importing folder, imported folder, file) for every import of one motor_driver folder by another."""
    found = []
    for path in sorted((root / "motor_driver").rglob("*.py")):
        parts = path.relative_to(root).parts
        if len(parts) < 3:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            for name in names:
                target = name.split(".")
                if target[0] == "motor_driver" and len(target) > 1 and target[1] != parts[1] and target[1] in FOLDER_ORDER:
                    found.append((parts[1], target[1], str(path.relative_to(root))))
    return found


def test_motor_driver_is_folders_in_layers() -> None:
    """Every module of motor_driver sits in a named folder but its ``__init__``, and no folder
    imports one above it (FOLDER_ORDER)."""
    loose = sorted(p.name for p in (REPO / "motor_driver").glob("*.py") if p.name != "__init__.py")
    assert not loose, f"motor_driver/ modules outside a named folder: {loose}"
    folders = sorted(p.parent.name for p in (REPO / "motor_driver").glob("*/__init__.py"))
    assert folders == sorted(FOLDER_ORDER), f"motor_driver's folders {folders} against FOLDER_ORDER {FOLDER_ORDER}"
    upward = [f"{file}: {low} imports {high}" for low, high, file in folder_imports(REPO)
              if FOLDER_ORDER.index(high) > FOLDER_ORDER.index(low)]
    assert not upward, "imports from a lower folder to a higher one:\n" + "\n".join(upward)



def test_the_readme_tour_lists_each_folder_of_motor_driver() -> None:
    """README's "Layers" gives each folder of motor_driver a line of its own, in FOLDER_ORDER."""
    listed = [m.group(1) for m in re.finditer(r"^  - `motor_driver/(\w+)/`:", readme_section(), re.M)]
    assert listed == list(FOLDER_ORDER), f"README's tour lists {listed}; the tree's layers are {list(FOLDER_ORDER)}"


def import_graph(root: Path) -> dict[str, set[str]]:
    """Every module of the product and the product modules it imports (anywhere in it, a
    type-checking import included: a circle there is still a circle)."""
    modules = {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p
               for package in PACKAGES for p in (root / package).rglob("*.py")}

    def owner(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            for target in map(owner, targets):
                if target and target != name and not name.startswith(target + "."):
                    graph[name].add(target)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles (strongly connected components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = [stack.pop()]
            while component[-1] != node:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_no_import_circle_in_the_product() -> None:
    found = circles(import_graph(REPO))
    assert not found, f"import circles: {found}"


def test_the_circle_scan_finds_a_circle() -> None:
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def room_crossings(root: Path, package: str, floors: tuple[tuple[str, ...], ...], shared: tuple[str, ...],
                   allowed: dict[tuple[str, str], str]) -> list[str]:
    """Imports inside ``package`` that break its rooms' order: a room (a folder of ``floors``)
    imports only rooms on a floor below its own and the ``shared`` modules of the package's top; a
    shared module imports only shared modules; neither imports the package itself (its
    ``__init__`` composes everything). The rest of the top (the facade, the entry points)
    composes the rooms: it may import any. ``allowed``: crossings kept, each with its reason."""
    base = root.joinpath(*package.split("."))
    floor = {room: i for i, rooms in enumerate(floors) for room in rooms}
    found = []
    for path in sorted(base.rglob("*.py")):
        parts = path.relative_to(base).parts
        here = parts[0] if len(parts) > 1 else path.stem
        if here not in floor and here not in shared:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            for name in names:
                if name != package and not name.startswith(package + "."):
                    continue
                there = name[len(package) + 1:].split(".")[0] if name != package else "__init__"
                fits = there in shared if here in shared else (
                    there == here or there in shared or (there in floor and floor[there] < floor[here]))
                file = str(path.relative_to(root))
                if not fits and (file, name) not in allowed:
                    found.append(f"{file}: {here} imports {name}")
    return found


def test_the_room_scan_finds_a_crossing(tmp_path: Path) -> None:
    for name, text in {"pkg/__init__.py": "", "pkg/low/__init__.py": "", "pkg/low/a.py": "import pkg.high.b\n",
                       "pkg/high/__init__.py": "", "pkg/high/b.py": "from pkg.low import a\n",
                       "pkg/face.py": "from pkg.low.a import x\n"}.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    floors = (("low",), ("high",))
    assert room_crossings(tmp_path, "pkg", floors, (), {}) == ["pkg/low/a.py: low imports pkg.high.b"]
    assert room_crossings(tmp_path, "pkg", floors, ("face",), {}) == ["pkg/face.py: face imports pkg.low.a",
                                                                      "pkg/low/a.py: low imports pkg.high.b"]
    assert room_crossings(tmp_path, "pkg", floors, (), {("pkg/low/a.py", "pkg.high.b"): "why"}) == []


#: motor_driver/drive's rooms, named by the thread that owns their state, lowest first; the
#: shared modules of its top import no room; the facade (and __init__) composes them all.
DRIVE_FLOORS = (("received",), ("command",), ("setup",))
DRIVE_SHARED = ("constants", "verdict", "values", "ledger", "sdo")
#: The crossings the order keeps, each with its reason: (file, module it imports).
DRIVE_CROSSINGS = {("motor_driver/drive/command/power.py", "motor_driver.drive.setup.hostwatch"):
                   "power reads the host watch boot configured (whether the drive watches the host, another"
                   " master): reads of the bus worker's room, never a write"}


def test_drive_is_rooms_by_owner_in_one_order() -> None:
    rooms = sorted(p.parent.name for p in (REPO / "motor_driver" / "drive").glob("*/__init__.py"))
    assert rooms == sorted(r for floor in DRIVE_FLOORS for r in floor), f"drive's rooms {rooms} against DRIVE_FLOORS"
    found = room_crossings(REPO, "motor_driver.drive", DRIVE_FLOORS, DRIVE_SHARED, DRIVE_CROSSINGS)
    assert not found, "imports against drive's order of rooms:\n" + "\n".join(found)
    kept = {key for key in DRIVE_CROSSINGS if key[1] in (REPO / key[0]).read_text()}
    assert kept == set(DRIVE_CROSSINGS), f"crossings no longer made (drop them): {set(DRIVE_CROSSINGS) - kept}"


#: nodes' folders by role, lowest first (rover and actions on one floor: neither imports the
#: other); its top (the entry points and the assembly) puts them together.
NODES_FLOORS = (("process",), ("joints",), ("rover", "actions"))


def test_nodes_is_folders_by_role_in_one_order() -> None:
    rooms = sorted(p.parent.name for p in (REPO / "nodes").glob("*/__init__.py"))
    assert rooms == sorted(r for floor in NODES_FLOORS for r in floor), f"nodes' folders {rooms} against NODES_FLOORS"
    found = room_crossings(REPO, "nodes", NODES_FLOORS, (), {})
    assert not found, "imports against nodes' order of folders:\n" + "\n".join(found)
