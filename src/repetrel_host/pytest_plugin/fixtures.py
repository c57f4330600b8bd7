"""The fixtures: the controller (a fresh fake, or the bench's port) and the printer."""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import shlex
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal, TypeVar

import pytest

from repetrel_host.pytest_plugin.facade import AsyncHyrelPrinter, HyrelController, HyrelPrinter
from repetrel_host.pytest_plugin.jobs import FILE_SUFFIXES, HyrelJob
from repetrel_host.pytest_plugin.options import (
    HyrelOptions,
    link_for,
    plugin_options,
    wanted_machines,
)
from repetrel_host.pytest_plugin.portal import Portal
from repetrel_host.pytest_plugin.report import (
    MARK_KEY,
    RECORDER_KEY,
    WireRecorder,
    failed,
    record_events,
)
from repetrel_host.pytest_plugin.teardown import PluginSession

# Seconds a session on real hardware may take to be READY again before a test.
READY_TIMEOUT = 30.0
# Seconds the safe stop may take to be confirmed after a test, before M112 (where the
# firmware reads it at once) and an error: on the bench, and on the fake.
SAFE_STOP_DEADLINE = 60.0
FAKE_SAFE_STOP_DEADLINE = 10.0
# Temperatures are asked for (or reported) this often, so that tests see them move.
POLL_INTERVAL = 1.0
T = TypeVar("T")


# The fake's options a test may not set: the plugin sets them itself.
_PLUGIN_OWNED = frozenset({"link", "log", "received", "stats", "control", "protocol"})


def _fake_arguments(item: pytest.Item) -> list[str]:
    """The fake's command-line settings from the test's ``hyrel_fake`` markers."""
    arguments: list[str] = []
    for marker in reversed(list(item.iter_markers("hyrel_fake"))):
        owned = _PLUGIN_OWNED & set(marker.kwargs)
        if "protocol" in owned:
            pytest.fail(
                "hyrel_fake: protocol is the plugin's: give --hyrel-protocol (the session "
                "speaks it too)",
                pytrace=False,
            )
        if marker.args or owned:
            what = f"{', '.join(sorted(owned))} is the plugin's" if owned else "name each setting"
            pytest.fail(f"hyrel_fake: {what} (as in hyrel_fake(heat_rate=20))", pytrace=False)
        for name, value in marker.kwargs.items():
            option = "--" + name.replace("_", "-")
            if value is True:
                arguments.append(option)
            elif value is not False and value is not None:
                arguments += [option, str(value)]
    from repetrel_host.fakes.fake_controller import build_parser, settings_from_args

    parser = build_parser()
    parser.allow_abbrev = False  # heat_rat=5 is a typo, not --heat-rate
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors):
            settings_from_args(parser.parse_args(arguments))
    except SystemExit as exc:
        message = errors.getvalue().strip().splitlines()[-1:] or [str(exc.code)]
        pytest.fail(f"hyrel_fake({shlex.join(arguments)}): {message[0]}", pytrace=False)
    return arguments


# --- fixtures ---------------------------------------------------------------------


def _scope(fixture_name: str, config: pytest.Config) -> Literal["session", "function"]:
    """A real printer is opened once for the whole run; the fake is fresh for each test."""
    return "session" if plugin_options(config).hardware else "function"


@pytest.fixture(scope="session")
def hyrel_options(pytestconfig: pytest.Config) -> HyrelOptions:
    """The plugin's options for this run."""
    return plugin_options(pytestconfig)


@pytest.fixture(scope=_scope)
def hyrel_controller(
    request: pytest.FixtureRequest,
    hyrel_options: HyrelOptions,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[HyrelController]:
    """The controller under test: the real port, or a fake started for this test."""
    if not request.config.pluginmanager.hasplugin("timeout"):
        pytest.fail(
            "hyrel: the plugin needs pytest-timeout, so that a printer that stops answering "
            "fails its test instead of hanging the run: pip install -e '.[hil]' in "
            "repetrel-host's clone",
            pytrace=False,
        )
    if hyrel_options.hardware:
        yield HyrelController(hyrel_options.port)
        return
    from repetrel_host.fakes.fake_controller import BuiltInFake

    link = link_for(hyrel_options)
    arguments = ["--bandwidth", str(link.baud / 10), "--latency", "0.001"]
    arguments += ["--protocol", link.protocol, *_fake_arguments(request.node)]
    log = tmp_path_factory.mktemp("hyrel-fake") / "executed.log"
    fake = BuiltInFake(log, arguments, control=True)
    fake.start()
    try:
        yield HyrelController(fake.port, fake)
    finally:
        fake.stop()


@pytest.fixture(scope=_scope)
def _hyrel_session(
    hyrel_options: HyrelOptions, hyrel_controller: HyrelController
) -> Iterator[PluginSession]:
    import repetrel_host as rh

    options = hyrel_options
    portal = Portal()
    recorder = WireRecorder()
    deadline = SAFE_STOP_DEADLINE if options.hardware else FAKE_SAFE_STOP_DEADLINE

    async def open_session() -> PluginSession:
        link = link_for(options)
        printer = await rh.connect(
            hyrel_controller.port,
            machine=options.machine,
            loadout=options.loadout,
            flow=link.flow,
            baud=link.baud,
            protocol=link.protocol,
            poll_interval=POLL_INTERVAL,
            line_tap=hyrel_controller.note_sent,  # from the greeting on
        )
        printer.tap_wire(recorder.tap)
        asyncio.get_running_loop().create_task(record_events(printer, recorder))
        return PluginSession(portal, printer, recorder, deadline)

    failure: str | None = None
    try:
        session = portal.call(open_session())
    except BaseException as exc:
        portal.close()
        if not isinstance(exc, rh.HostError):
            raise
        failure = f"hyrel: no printer session on {hyrel_controller.port}: {exc}"
    if failure is not None:
        pytest.fail(failure, pytrace=False)  # outside the except: no chained traceback
    try:
        yield session
    finally:
        try:
            # The bench's printer is left safe at the end of the run; the fake just goes.
            problem = portal.call(session.close(safe_stop=options.hardware), 4 * deadline)
        finally:
            portal.close()
    if problem is not None:
        pytest.fail(f"hyrel: at the end of the run, {problem}", pytrace=False)


def _facade(
    request: pytest.FixtureRequest, session: PluginSession, facade: Callable[[PluginSession], T]
) -> Iterator[T]:
    """Before the test: a READY session, the machine it needs, the report's starting
    point. After: the machine left safe."""
    import repetrel_host as rh

    item = request.node
    printer = session.printer
    try:
        session.portal.call(printer.wait_for(rh.State.READY, timeout=READY_TIMEOUT))
    except TimeoutError:
        state = printer.state.value
        pytest.fail(f"hyrel: the printer on {printer.port} is not ready ({state})", pytrace=False)
    wanted = wanted_machines(item)
    if wanted:
        profile = printer.profile
        if profile.name not in wanted:
            machine = profile.describe()
            pytest.skip(f"for machine {' or '.join(wanted)}; this run's machine is {machine}")
    item.stash[RECORDER_KEY] = session.recorder
    item.stash[MARK_KEY] = session.recorder.mark()
    yield facade(session)
    problem = session.portal.call(session.leave_safe(failed(item)), 4 * session.deadline)
    if problem is not None:
        pytest.fail(f"hyrel: after the test, {problem}", pytrace=False)


@pytest.fixture
def hyrel_printer(
    request: pytest.FixtureRequest, _hyrel_session: PluginSession
) -> Iterator[HyrelPrinter]:
    """A READY printer session, for synchronous tests (see :class:`HyrelPrinter`)."""
    yield from _facade(request, _hyrel_session, HyrelPrinter)


@pytest.fixture
def hyrel_aprinter(
    request: pytest.FixtureRequest, _hyrel_session: PluginSession
) -> Iterator[AsyncHyrelPrinter]:
    """A READY printer session, awaited from async tests on any asyncio event loop."""
    yield from _facade(request, _hyrel_session, AsyncHyrelPrinter)


@pytest.fixture
def hyrel_job(tmp_path: Path) -> Callable[..., HyrelJob]:
    """``hyrel_job("G28\\nG1 X10\\n")`` (G-code text) or ``hyrel_job(Path("part.gcode"))``:
    a job to print, with the loadout's header unless ``header=False``; the stream as
    transmitted is kept in the test's tmp_path."""
    count = 0

    def make(source: str | os.PathLike[str], *, header: bool = True) -> HyrelJob:
        nonlocal count
        count += 1
        if isinstance(source, str):
            if "\n" not in source and source.lower().endswith(FILE_SUFFIXES):
                raise ValueError(
                    f"hyrel_job({source!r}) takes G-code text; for a file, "
                    f"hyrel_job(Path({source!r}))"
                )
            path = tmp_path / f"job{count}.gcode"
            path.write_text(source)
        else:
            path = Path(source)
        return HyrelJob(path, header, tmp_path / f"job{count}-sent.gcode")

    return make
