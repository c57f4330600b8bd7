"""The house's floors, read from the source: what each part of the package may import, and
no import circle among its modules (type-only and late imports count: a circle of types is
one too)."""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "src" / "repetrel_host"

# The floors, lowest first: a room imports only rooms on its own floor or below.
FLOORS = (
    ("errors", "config", "protocol", "gcode", "fakes", "links"),
    ("session",),
    ("cli", "server", "pytest_plugin"),
)
FLOOR = {room: level for level, rooms in enumerate(FLOORS) for room in rooms}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path) for path in PACKAGE.rglob("*.py")}


def imports(path: Path) -> set[str]:
    """The modules that ``path`` imports, anywhere in it (ruff refuses relative imports, so
    each has its absolute name): ``from a.b import c`` is ``a.b.c`` where that is one of the
    package's modules, else ``a.b``."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                member = f"{node.module}.{alias.name}"
                found.add(member if member in MODULES else node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found


def room(path: Path) -> str:
    return path.relative_to(PACKAGE).parts[0].removesuffix(".py")


def test_every_module_is_in_a_room_on_a_floor() -> None:
    # A module loose at the package's top, or a new room, is placed on a floor here first.
    loose = {room(path) for path in PACKAGE.rglob("*.py")} - set(FLOOR) - {"__init__"}
    assert loose == set()


def test_no_room_imports_one_on_a_higher_floor() -> None:
    upward = [
        f"{path.relative_to(PACKAGE)} imports {name}"
        for path in PACKAGE.rglob("*.py")
        if room(path) in FLOOR
        for name in imports(path)
        if name.startswith("repetrel_host.")
        and FLOOR.get(name.split(".")[1], 0) > FLOOR[room(path)]
    ]
    assert upward == []


def test_only_the_plugin_imports_pytest() -> None:
    # pytest is in the [hil] extra: anything else importing it breaks a print server.
    users = [
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if "pytest" in {name.split(".")[0] for name in imports(path)}
        and path.parent.name != "pytest_plugin"
    ]
    assert users == []


def test_no_module_imports_one_that_imports_it_back() -> None:
    graph = {
        module_name(path): (imports(path) & MODULES) - {module_name(path)}
        for path in PACKAGE.rglob("*.py")
    }
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as exc:
        raise AssertionError(f"an import circle: {' -> '.join(exc.args[1])}") from None
