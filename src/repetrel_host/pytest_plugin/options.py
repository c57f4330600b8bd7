"""The plugin's options and markers: the command line, the environment, the ini file."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from repetrel_host.session.planning import LinkSettings


FAKE = "fake"
# Each option: its name after --hyrel-, and its help (with the default it has without it).
_OPTIONS = {
    "port": "serial port of a real printer (also HYREL_PORT); default: the built-in fake "
    "controller, fresh for each test",
    "machine": "machine profile, e.g. hydra-16a (also HYREL_MACHINE); default: the loadout's, "
    "else what the controller's M115 says (hyrel or marlin)",
    "loadout": "loadout file or shipped name, whose header jobs get (also HYREL_LOADOUT); "
    "default: none",
    "flow": "flow control, buffered or unbuffered (also HYREL_FLOW); default: the machine "
    "profile's",
    "baud": "baud rate (also HYREL_BAUD); default: the machine profile's (115200)",
    "protocol": "line protocol, reprap or hyrel (Hyrel's own link; also HYREL_PROTOCOL); "
    "default: the machine profile's (reprap); the fake speaks it too",
}
OPTIONS_KEY = pytest.StashKey["HyrelOptions"]()


# pytest-asyncio warns in every run where this is unset, which a lab writing its first
# async printer test has not met yet; the plugin gives it the default pytest-asyncio
# announces. A value set in the ini file or with -o still wins.
ASYNCIO_LOOP_SCOPE = "asyncio_default_fixture_loop_scope"
_parser: pytest.Parser | None = None  # this run's, for the default above


def pytest_addoption(parser: pytest.Parser) -> None:
    global _parser
    _parser = parser
    group = parser.getgroup("hyrel", "Hyrel printers (repetrel-host)")
    for name, text in _OPTIONS.items():
        group.addoption(f"--hyrel-{name}", dest=f"hyrel_{name}", metavar=name.upper(), help=text)
        parser.addini(f"hyrel_{name}", f"--hyrel-{name}: {text}", default="")


@pytest.hookimpl(tryfirst=True)  # before pytest-asyncio reads its settings
def pytest_configure(config: pytest.Config) -> None:
    if config.pluginmanager.hasplugin("asyncio") and _parser is not None:
        help = "default scope of the event loop of async fixtures (repetrel-host: function)"
        _parser.addini(ASYNCIO_LOOP_SCOPE, help, default="function")
    for line in (
        "hyrel_hardware: runs only on a real printer (--hyrel-port)",
        "hyrel_fake_only: runs only on the fake controller (it needs fault injection)",
        "hyrel_machine(*names): runs only when the machine profile is one of names",
        "hyrel_fake(**settings): settings for the fake controller (heat_rate=20, "
        "faults='drop_ok=0.05', advanced_ok=True...); ignored on a real printer",
    ):
        config.addinivalue_line("markers", line)
    if config.option.help:
        return  # help is given whatever the options say
    # Bad values stop the run here, in one sentence, not in every test.
    options = config.stash[OPTIONS_KEY] = HyrelOptions.from_config(config)
    try:
        link_for(options)
        if options.machine or options.loadout:
            known_machine(options)  # reads the loadout too, and checks it fits the machine
    except Exception as exc:  # ConfigError, and whatever a loadout file holds
        raise pytest.UsageError(f"hyrel: {exc}") from None
    args = list(config.invocation_params.args)
    port = options.port
    if port in args[1:] and args[args.index(port) - 1] == "--hyrel-port" and Path(port).exists():
        # pytest looks for the project's configuration from the paths among its arguments
        # before it knows which are option values.
        config.issue_config_time_warning(
            pytest.PytestConfigWarning(
                f"--hyrel-port {port} made pytest look for its configuration from "
                f"{Path(port).parent} (rootdir {config.rootpath}); write --hyrel-port={port}"
            ),
            stacklevel=2,
        )


@dataclass(frozen=True)
class HyrelOptions:
    """The plugin's options, each from the command line, else the environment
    (``HYREL_PORT``...), else ``[tool.pytest.ini_options]`` (``hyrel_port``...)."""

    port: str = FAKE
    machine: str | None = None
    loadout: str | None = None
    flow: str | None = None
    baud: int | None = None
    protocol: str | None = None

    @property
    def hardware(self) -> bool:
        """A real port was given: one session serves the whole run."""
        return self.port != FAKE

    @classmethod
    def from_config(cls, config: pytest.Config) -> HyrelOptions:
        values: dict[str, tuple[str, str] | None] = {}  # name: (value, where it came from)
        for name in _OPTIONS:
            option = config.getoption(f"hyrel_{name}")
            variable = os.environ.get(f"HYREL_{name.upper()}")
            ini = str(config.getini(f"hyrel_{name}"))
            values[name] = (
                (option, f"--hyrel-{name}")
                if option is not None
                else (variable, f"HYREL_{name.upper()}")
                if variable
                else (ini, f"hyrel_{name} in {config.inipath}")
                if ini
                else None
            )
        flow, baud, protocol = values["flow"], values["baud"], values["protocol"]
        if flow is not None and flow[0] not in ("buffered", "unbuffered"):
            raise pytest.UsageError(f"{flow[1]}: '{flow[0]}' is not buffered or unbuffered")
        if protocol is not None and protocol[0] not in ("reprap", "hyrel"):
            raise pytest.UsageError(f"{protocol[1]}: '{protocol[0]}' is not reprap or hyrel")
        if baud is not None and not (baud[0].isdigit() and int(baud[0]) > 0):
            raise pytest.UsageError(f"{baud[1]}: '{baud[0]}' is not a baud rate")

        def value(name: str) -> str | None:
            given = values[name]
            return given[0] if given is not None else None

        return cls(
            port=value("port") or FAKE,
            machine=value("machine"),
            loadout=value("loadout"),
            flow=value("flow"),
            baud=int(baud[0]) if baud is not None else None,
            protocol=value("protocol"),
        )


def plugin_options(config: pytest.Config) -> HyrelOptions:
    return config.stash[OPTIONS_KEY]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip what this run cannot do (before any fixture starts a fake or opens a port)."""
    options = config.stash.get(OPTIONS_KEY, None)
    if options is None:
        return
    machine = known_machine(options) if options.machine or options.loadout else None
    known = _known_machines() if machine is not None else set()
    for item in items:
        if item.get_closest_marker("hyrel_hardware") and not options.hardware:
            reason = "needs a real printer: give --hyrel-port=PORT (or HYREL_PORT)"
            item.add_marker(pytest.mark.skip(reason=reason))
        if item.get_closest_marker("hyrel_fake_only") and options.hardware:
            reason = f"needs the fake controller's fault injection; this run drives {options.port}"
            item.add_marker(pytest.mark.skip(reason=reason))
        wanted = _marker_machines(item)
        if machine and wanted and set(wanted) <= known and machine.split()[0] not in wanted:
            reason = f"for machine {' or '.join(wanted)}; this run's machine is {machine}"
            item.add_marker(pytest.mark.skip(reason=reason))


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    wanted = wanted_machines(item)
    options = plugin_options(item.config)
    uses_session = {"hyrel_printer", "hyrel_aprinter"} & set(getattr(item, "fixturenames", ()))
    if wanted and not (options.machine or options.loadout or uses_session):
        pytest.fail(
            "hyrel_machine: this test's machine is known from --hyrel-machine or "
            "--hyrel-loadout, or from the controller once the test uses hyrel_printer",
            pytrace=False,
        )


def _known_machines() -> set[str]:
    from repetrel_host.config import load_library, load_user_config

    return set(load_library(load_user_config(None)).machines)


def _marker_machines(item: pytest.Item) -> list[str]:
    marker = item.get_closest_marker("hyrel_machine")
    return [str(name) for name in marker.args] if marker is not None else []


def wanted_machines(item: pytest.Item) -> list[str]:
    """The machine profiles a ``hyrel_machine`` marker names (a mistyped one fails)."""
    if item.get_closest_marker("hyrel_machine") is None:
        return []
    names, known = _marker_machines(item), _known_machines()
    if not names or any(name not in known for name in names):
        pytest.fail(
            f"hyrel_machine({', '.join(map(repr, names))}): name known machine profiles "
            f"({', '.join(sorted(known))})",
            pytrace=False,
        )
    return names


def known_machine(options: HyrelOptions) -> str:
    from repetrel_host.config import load_user_config
    from repetrel_host.session.planning import JobRequest, controller_profile

    loadout = Path(options.loadout) if options.loadout else None
    request = JobRequest(loadout, options.machine)
    profile = controller_profile(request, load_user_config(None), None)
    return profile.describe()


def link_for(options: HyrelOptions) -> LinkSettings:
    from repetrel_host.config import load_user_config
    from repetrel_host.protocol.flow import FlowMode
    from repetrel_host.session.planning import (
        JobRequest,
        LinkRequest,
        explicit_machine,
        link_settings,
    )

    loadout = Path(options.loadout) if options.loadout else None
    machine = explicit_machine(JobRequest(loadout, options.machine), load_user_config(None))
    flow = FlowMode(options.flow) if options.flow else None
    request = LinkRequest(baud=options.baud, flow=flow, protocol=options.protocol)
    return link_settings(request, machine)
