"""Where the tests find the project's files, wherever their own file sits."""

import fcntl
import os
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

TESTS = Path(__file__).resolve().parent.parent
ROOT = TESTS.parent
DATA = TESTS / "data"
SUPPORT = TESTS / "support"

# Real peers installed once for the tests (Moonraker, FDM Monster), in the user's cache.
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "repetrel-host"


def install_once(
    folder: Path,
    what: str,
    *commands: list[str],
    first: Callable[[], None] | None = None,
    **run: Any,
) -> None:
    """Run ``first`` then ``commands`` (each must succeed) to install ``what`` into
    ``folder`` of the cache, once: a later call finds it installed. The test workers
    (pytest-xdist) run side by side, so one of them installs while the others wait. A
    failed install skips the test, saying why."""
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / f"{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (folder / "installed").exists():
            return
        try:
            if first is not None:
                first()
            for command in commands:
                subprocess.run(command, check=True, capture_output=True, **run)
        except (subprocess.SubprocessError, OSError) as exc:
            pytest.skip(f"{what} could not be installed here: {exc}")
        (folder / "installed").touch()
