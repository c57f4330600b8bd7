"""The house's floors, read from the source: what each part of the package may import, and
no import circle among its modules (type-only and late imports count: a circle of types is
one too)."""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "src" / "repetrel_host"

# Low floors, and what they must not reach up to: the session and its users.
UPPER = ("session", "cli", "console", "terminal", "display", "server", "pytest_plugin")
LOW = ("protocol", "fakes", "links", "gcode", "pump")


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


def modules(floor: str) -> list[Path]:
    where = PACKAGE / floor
    return sorted(where.rglob("*.py")) if where.is_dir() else [PACKAGE / f"{floor}.py"]


def test_the_low_floors_do_not_import_the_session_or_its_users() -> None:
    upward = [
        f"{path.relative_to(PACKAGE)} imports {name}"
        for floor in LOW
        for path in modules(floor)
        for name in imports(path)
        if name.startswith("repetrel_host.") and name.split(".")[1] in UPPER
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
