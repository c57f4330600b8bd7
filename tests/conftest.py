from pathlib import Path

import pytest

from tests.support.helpers import CONE, job_commands

# pytester: the plugin's own tests; a server and its fakes; the page's fixtures; the farm's
# PostgreSQL and nodes.
pytest_plugins = [
    "pytester",
    "tests.support.server",
    "tests.support.page",
    "tests.support.pg",
    "tests.support.farm",
]


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


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> object:
    """Each phase's report on the test (``item.rep_call``): the page's tests keep a
    screenshot when theirs failed."""
    report = yield
    setattr(item, f"rep_{report.when}", report)
    browser = getattr(item, "funcargs", {}).get("browser")
    if report.when == "call" and report.failed and browser is not None:
        browser.keep_screenshot(item.name)  # now: the server is still up, as it failed
    return report
