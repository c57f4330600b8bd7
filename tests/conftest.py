from pathlib import Path

import pytest

from tests.helpers import CONE, job_commands

pytest_plugins = ["pytester"]  # the pytest plugin's own tests run pytest inside


@pytest.fixture(scope="session")
def cone_commands() -> list[str]:
    commands = job_commands(CONE)
    assert len(commands) > 20_000
    return commands


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Keep configuration and print history of every run (and subprocess) inside tmp_path."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config-home"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data-home"))
    return tmp_path
