"""The house's floors: what each part of the package may import (see ../shared/DESIGN.md),
read from the source, and the old import paths that still work."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "src" / "repetrel_host"

# Low floors, and what they must not reach up to: the session and its users.
UPPER = ("session", "cli", "console", "terminal", "display", "server", "pytest_plugin")
LOW = ("protocol", "fakes", "links", "gcode", "pump")


def imports(path: Path) -> set[str]:
    """The modules that ``path`` imports by absolute name, anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
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


def test_the_old_import_paths_still_work() -> None:
    from repetrel_host.fakes.fake_controller import BuiltInFake
    from repetrel_host.fakes.simulator import ControllerSimulator
    from repetrel_host.pytest_plugin import HyrelPrinter
    from repetrel_host.testing.fake_controller import BuiltInFake as OldFake
    from repetrel_host.testing.pytest_plugin import HyrelPrinter as OldPrinter
    from repetrel_host.testing.simulator import ControllerSimulator as OldSimulator

    assert (OldFake, OldSimulator, OldPrinter) == (BuiltInFake, ControllerSimulator, HyrelPrinter)
