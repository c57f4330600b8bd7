from pathlib import Path
from typing import Any

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


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--slow",
        action="store_true",
        help="also run the tests marked slow (a plain `pytest` leaves them out; naming a path "
        "or giving -m or -k runs what they select)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "slow: a test of more than about 3 s here, or of a heavy real peer (a soak, a bench, a "
        "real browser or client, PostgreSQL, a package build): left out of a plain `pytest`, "
        "run by `pytest --slow`, `pytest -m slow` and CI",
    )
    # The controller decides: pytest-xdist's workers see other arguments, and get its choice.
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:
        config.option.quick_only = workerinput["quick_only"]
    else:
        config.option.quick_only = (
            not config.option.slow
            and not config.option.markexpr
            and not config.option.keyword
            and config.args_source == pytest.Config.ArgsSource.TESTPATHS
        )


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    """pytest-xdist's hook: a worker's input carries the controller's choice."""
    node.workerinput["quick_only"] = node.config.option.quick_only


# A test that drives a real browser (tests/page, the browser fixture) or starts a PostgreSQL
# cluster is slow by what it uses.
SLOW_FIXTURES = {"browser", "postgres"}
PAGE = Path(__file__).parent / "page"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())) or item.path.is_relative_to(PAGE):
            item.add_marker(pytest.mark.slow)
    if not getattr(config.option, "quick_only", False):
        return
    slow = [item for item in items if item.get_closest_marker("slow")]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if not item.get_closest_marker("slow")]


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if getattr(terminalreporter.config.option, "quick_only", False):
        terminalreporter.write_line(
            "the tests marked slow were left out: `pytest --slow` runs them too (CI does)"
        )


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
