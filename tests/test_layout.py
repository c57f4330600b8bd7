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


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


# The standard library's own private names the package calls on purpose.
LIBRARY_PRIVATES = {"os._exit"}  # a worker that must die at once, as a killed one would
# A pytest fixture that users are not to ask for (its name says so), which the plugin's
# module must hold for pytest to find it.
PRIVATE_IMPORTS = {"pytest_plugin/__init__.py": {"_hyrel_session"}}


def test_no_module_uses_another_modules_private_names() -> None:
    """A ``_name`` belongs to its module: another module neither imports it nor reaches it
    through an object (``job._hub``); it asks for a public name or a Protocol instead. A
    subclass's own ``self._name`` is its base's too (the fakes' Hyrel controller, the
    serial transport over pyserial-asyncio's)."""
    reaches = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        own = (
            {
                node.attr
                for node in ast.walk(tree)
                if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
            }
            | {
                node.name
                for node in ast.walk(tree)
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
            }
            | {
                node.id
                for node in ast.walk(tree)
                if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store)
            }
        )
        where = path.relative_to(PACKAGE)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("repetrel_host"):
                allowed = PRIVATE_IMPORTS.get(str(where), set())
                reaches += [
                    f"{where}: imports {alias.name}"
                    for alias in node.names
                    if _private(alias.name) and alias.name not in allowed
                ]
            elif isinstance(node, ast.Attribute) and _private(node.attr):
                if ast.unparse(node.value) in ("self", "cls", "super()"):
                    continue
                named = ast.unparse(node)
                if node.attr not in own and named not in LIBRARY_PRIVATES:
                    reaches.append(f"{where}:{node.lineno}: {named}")
    assert reaches == [], "\n".join(reaches)


def test_no_two_classes_of_the_package_share_a_name() -> None:
    """A class name says which thing it is, wherever a reader meets it (in a traceback, a
    log, an OpenAPI schema): two rooms never use one name for two classes."""
    where: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ClassDef):
                where.setdefault(node.name, []).append(str(path.relative_to(PACKAGE)))
    shared = {name: paths for name, paths in where.items() if len(paths) > 1}
    assert shared == {}, shared
