"""The pytest plugin: the same test on the fake controller and on the printer on the bench.

Installed with the package (the ``pytest11`` entry point ``hyrel``; ``-p no:hyrel``
turns it off). Without ``--hyrel-port`` every test gets the built-in fake controller on a
fresh pty, started for that test alone; with it, one session on the real port serves the
whole test run, as a printer is one physical thing. Fixtures:

- ``hyrel_printer``: a READY printer session behind a synchronous facade
  (:class:`HyrelPrinter`); ``hyrel_aprinter``: the same, awaitable (:class:`AsyncHyrelPrinter`),
  from any asyncio event loop (pytest-asyncio, anyio on asyncio, ``asyncio.run``);
- ``hyrel_controller``: what the test talks to (:class:`HyrelController`): its port, and
  on the fake its executed commands, fault switches and heaters;
- ``hyrel_job``: jobs from text or a file (:class:`HyrelJob`).

Markers: ``hyrel_hardware``, ``hyrel_fake_only``, ``hyrel_machine(NAME...)``,
``hyrel_fake(heat_rate=..., faults=...)``. A failed test's report gets the last lines
exchanged on the wire and the controller's messages. Teardown leaves the machine safe:
a job still running is cancelled (the safe stop first); after a failed test and at the
end of a bench run the safe-stop sequence is sent (a heat wait ended first with M108),
and a safe stop not confirmed in time fails the teardown.

Models: pytest-embedded (options in a group, a DUT fixture, its log in the report),
labgrid's pytest plugin (the same test on a board or on an emulator).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import shlex
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine, Generator, Iterator
from dataclasses import dataclass
from functools import cached_property
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import pytest

if TYPE_CHECKING:
    import repetrel_host as rh
    from repetrel_host.events import PrinterEvent
    from repetrel_host.planning import LinkSettings
    from repetrel_host.testing.fake_controller import BuiltInFake

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
# Seconds a session on real hardware may take to be READY again before a test.
READY_TIMEOUT = 30.0
# Seconds the safe stop may take to be confirmed after a test, before M112 (where the
# firmware reads it at once) and an error: on the bench, and on the fake.
SAFE_STOP_DEADLINE = 60.0
FAKE_SAFE_STOP_DEADLINE = 10.0
# Temperatures are asked for (or reported) this often, so that tests see them move.
POLL_INTERVAL = 1.0
WIRE_LINES = 2000  # kept for the report of a failed test
REPORT_LINES = 100  # shown in it
WIRE_LINE_MAX = 4096
T = TypeVar("T")

_options_key = pytest.StashKey["HyrelOptions"]()
_reports = pytest.StashKey[dict[str, pytest.TestReport]]()
_recorders = pytest.StashKey["WireRecorder"]()


# --- options and markers --------------------------------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("hyrel", "Hyrel printers (repetrel-host)")
    for name, text in _OPTIONS.items():
        group.addoption(f"--hyrel-{name}", dest=f"hyrel_{name}", metavar=name.upper(), help=text)
        parser.addini(f"hyrel_{name}", f"--hyrel-{name}: {text}", default="")


def pytest_configure(config: pytest.Config) -> None:
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
    options = config.stash[_options_key] = HyrelOptions.from_config(config)
    try:
        _link(options)
        if options.machine or options.loadout:
            _known_machine(options)  # reads the loadout too, and checks it fits the machine
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


def _options(config: pytest.Config) -> HyrelOptions:
    return config.stash[_options_key]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip what this run cannot do (before any fixture starts a fake or opens a port)."""
    options = config.stash.get(_options_key, None)
    if options is None:
        return
    machine = _known_machine(options) if options.machine or options.loadout else None
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
    wanted = _wanted_machines(item)
    options = _options(item.config)
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


def _wanted_machines(item: pytest.Item) -> list[str]:
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


def _known_machine(options: HyrelOptions) -> str:
    from repetrel_host.config import load_user_config
    from repetrel_host.planning import JobRequest, controller_profile

    loadout = Path(options.loadout) if options.loadout else None
    request = JobRequest(loadout, options.machine)
    profile = controller_profile(request, load_user_config(None), None)
    return profile.describe()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    item.stash.setdefault(_reports, {})[report.when] = report
    recorder = item.stash.get(_recorders, None)
    if report.failed and recorder is not None:
        for title, text in recorder.sections(item):
            report.sections.append((title, text))
    return report


def _failed(item: pytest.Item) -> bool:
    """The test failed (an expected failure too: the machine may be in any state)."""
    reports = item.stash.get(_reports, {}).values()
    return any(r.failed or hasattr(r, "wasxfail") for r in reports)


# --- the event loop the session lives on ----------------------------------------


class Portal:
    """An event loop in its own thread, which the session lives on, so that plain
    synchronous tests can use it and async tests on any loop can await it."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self.loop.run_forever, name="hyrel-session", daemon=True
        )
        self._thread.start()

    def call(self, coroutine: Coroutine[Any, Any, T], timeout: float | None = None) -> T:
        """Run ``coroutine`` on the portal's loop and wait for its result."""
        future = asyncio.run_coroutine_threadsafe(coroutine, self.loop)
        try:
            return future.result(timeout)
        except BaseException:  # a timeout, Ctrl-C: it stops there too
            future.cancel()
            raise

    async def acall(self, coroutine: Coroutine[Any, Any, T]) -> T:
        """The same, awaited from another event loop."""
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coroutine, self.loop))

    def close(self) -> None:
        async def cancel_the_rest() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        with contextlib.suppress(Exception):
            self.call(cancel_the_rest(), 10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        if not self._thread.is_alive():
            self.loop.close()


# --- what was said ----------------------------------------------------------------


class WireRecorder:
    """The last lines each way on the wire, and the session's messages and state changes,
    for the report of a failed test."""

    def __init__(self) -> None:
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._partial = {True: bytearray(), False: bytearray()}
        self.wire: deque[tuple[int, str]] = deque(maxlen=WIRE_LINES)
        self.messages: deque[tuple[int, str]] = deque(maxlen=WIRE_LINES)
        self._count = 0  # lines and messages so far, to tell what came during a test

    def tap(self, sent: bool, data: bytes) -> None:
        partial = self._partial[sent]
        partial += data
        *lines, rest = partial.split(b"\n")
        if len(rest) > WIRE_LINE_MAX:  # noise without line ends: shown, not hoarded
            lines.append(rest[:])
            rest.clear()
        partial[:] = rest
        for raw in lines:
            text = raw.rstrip(b"\r").decode("ascii", errors="backslashreplace")
            self._add(self.wire, f"{'>' if sent else '<'} {text}")

    def note(self, text: str) -> None:
        self._add(self.messages, text)

    def _add(self, kept: deque[tuple[int, str]], text: str) -> None:
        with self._lock:
            self._count += 1
            kept.append((self._count, f"{time.monotonic() - self._started:9.3f} {text}"))

    def mark(self) -> int:
        with self._lock:
            return self._count

    def since(self, kept: deque[tuple[int, str]], mark: int) -> list[str]:
        with self._lock:
            return [text for count, text in kept if count > mark]

    def sections(self, item: pytest.Item) -> list[tuple[str, str]]:
        mark = item.stash.get(_marks, 0)
        wire = self.since(self.wire, mark)
        shown = wire[-REPORT_LINES:]
        skipped = (
            f"({len(wire) - len(shown)} earlier lines not shown)\n" if wire[:-REPORT_LINES] else ""
        )
        messages = self.since(self.messages, mark)
        return [
            (
                "hyrel: last lines on the wire (> sent, < received)",
                skipped + "\n".join(shown) or "(none)",
            ),
            ("hyrel: controller messages and session states", "\n".join(messages) or "(none)"),
        ]


_marks = pytest.StashKey[int]()


async def _record_events(printer: rh.Printer, recorder: WireRecorder) -> None:
    import repetrel_host as rh

    async for event in printer.events():
        if isinstance(event, rh.StateChanged):
            why = f" ({event.reason})" if event.reason else ""
            recorder.note(f"state: {event.state.value}{why}")
        elif isinstance(event, rh.Message | rh.Notice):
            recorder.note(f"{type(event).__name__.lower()}: {event.text}")


# --- jobs -------------------------------------------------------------------------

_FILE_SUFFIXES = (".gcode", ".gco", ".g", ".nc")


@dataclass(frozen=True)
class HyrelJob:
    """A job for :meth:`HyrelPrinter.print`: a G-code file, with the loadout's header or not."""

    path: Path
    header: bool = True
    history: Path | None = None  # where the stream as transmitted is kept


def _as_job(job: HyrelJob | Path | str) -> HyrelJob:
    if isinstance(job, HyrelJob):
        return job
    if isinstance(job, str) and "\n" in job:
        raise ValueError(
            "print() takes hyrel_job(...) or a file's path; for G-code text, use hyrel_job(text)"
        )
    return HyrelJob(Path(job))


class PrintResult:
    """How a job went: which of its lines the controller acknowledged, and how it ended."""

    def __init__(
        self,
        job: HyrelJob,
        running: rh.PrintJob,
        summary: rh.Summary | None,
        error: rh.HostError | None,
    ) -> None:
        self.job = job
        self.summary = summary  # None when it failed
        self.error = error
        plan = running.plan
        self.header = [line.command for line in plan.header]  # the header it was sent with
        self.header_acknowledged = self.header[: running.header_lines]
        last = running.last
        self.last_line = last.source_line if last is not None else 0  # file line; 0: none
        # Safe-stop commands not confirmed, when the job was stopped.
        self.safe_stop_missing = running.safe_stop_missing if running.stopping else []
        self._file = plan.job  # read with the machine's own pause command for M0
        self._count = running.lines

    @property
    def completed(self) -> bool:
        """Every line was acknowledged and the job was not cancelled."""
        from repetrel_host.pump import Outcome

        return self.summary is not None and self.summary.outcome is Outcome.COMPLETED

    @cached_property
    def commands(self) -> list[str]:
        """The job's lines as sent (an M0 becomes the machine's pause command)."""
        return [line.command for line in self._file.lines()]

    @cached_property
    def acknowledged(self) -> list[str]:
        """Those the controller acknowledged, in order (they go and are confirmed in order)."""
        return [line.command for line in islice(self._file.lines(), self._count)]

    def __repr__(self) -> str:
        how = "completed" if self.completed else f"ended ({self.error or 'cancelled'})"
        return f"<PrintResult {self.job.path.name}: {how}; {self._count} lines acknowledged>"


# --- the session, as tests use it -------------------------------------------------


class _Session:
    """One printer session on the portal, and how to leave the machine safe."""

    def __init__(
        self, portal: Portal, printer: rh.Printer, recorder: WireRecorder, deadline: float
    ) -> None:
        self.portal = portal
        self.printer = printer
        self.recorder = recorder
        self.deadline = deadline  # for the safe stop after a test

    async def start(self, job: HyrelJob, force: bool) -> rh.PrintJob:
        history: Path | bool = job.history if job.history is not None else False
        return await self.printer.print(job.path, header=job.header, force=force, history=history)

    async def finish(self, job: HyrelJob, running: rh.PrintJob, check: bool) -> PrintResult:
        import repetrel_host as rh

        try:
            return PrintResult(job, running, await running.wait(), None)
        except rh.HostError as exc:
            if check:
                raise
            return PrintResult(job, running, None, exc)

    async def cancel(self, job: HyrelJob, running: rh.PrintJob) -> PrintResult:
        if not running.done and not running.stopping:
            running.stop()  # this job only, should another be running
        return await self.finish(job, running, check=False)

    async def command(self, line: str, timeout: float | None) -> rh.Reply:
        try:
            return await self.printer.command(line, timeout=timeout)
        except TimeoutError:
            raise TimeoutError(f"{line}: no reply within {timeout:g} s") from None

    async def wait_for_temperature(
        self, sensor: str, target: float, tolerance: float, timeout: float
    ) -> float:
        import repetrel_host as rh

        last: float | None = self.printer.temperatures.get(sensor, (None, None))[0]
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                async for event in self.printer.events():
                    if isinstance(event, rh.Temperatures) and sensor in event.readings:
                        last = event.readings[sensor][0]
                        if abs(last - target) <= tolerance:
                            return last
        raise AssertionError(
            f"{sensor} did not reach {target:g} (within {tolerance:g}) in {timeout:g} s; "
            f"last reading: {'none' if last is None else f'{last:g}'}"
        )

    async def subscribe(self) -> AsyncIterator[PrinterEvent]:
        """The session's events, subscribed to on its own loop (for another thread's use)."""
        return self.printer.events()

    async def leave_safe(self, failed: bool) -> str | None:
        """Cancel a running job (its safe stop first); after a failure, send the safe stop.
        Returns what went wrong, or None once the machine is safe."""
        import repetrel_host as rh

        printer = self.printer
        job = printer.job
        if job is None and not failed:
            return None
        firmware = printer.firmware
        emergency = firmware is not None and firmware.can("EMERGENCY_PARSER")
        connected = printer.state in (rh.State.READY, rh.State.PAUSED, rh.State.PRINTING)
        if emergency and connected and (job is not None or printer.pending):
            await printer.command("M108")  # a heat wait must not hold the safe stop back
        missing: list[str] = []
        if job is not None:
            if not job.stopping:
                job.stop()
            try:
                await asyncio.wait_for(job.wait(), self.deadline)
            except TimeoutError:
                job.stop()  # abandoned: what was not confirmed is missing
            except rh.HostError:
                pass
            missing = job.safe_stop_missing if job.stopping else []
        if failed and (job is None or not job.stopping):
            missing = await self._send_safe_stop()
        if not missing:
            return None
        problem = f"the safe stop was not confirmed within {self.deadline:g} s (missing: "
        problem += f"{', '.join(missing)})"
        if emergency and printer.state is not rh.State.CLOSED:
            with contextlib.suppress(rh.HostError):
                await printer.command("M112")
                problem += "; sent M112 (emergency stop)"
        return problem + ": check the machine"

    async def _send_safe_stop(self) -> list[str]:
        """Send the machine's safe-stop sequence; returns the commands not confirmed."""
        import repetrel_host as rh

        printer = self.printer
        commands = printer.safe_stop
        loop = asyncio.get_running_loop()
        end = loop.time() + self.deadline
        try:
            await printer.wait_for(rh.State.READY, rh.State.PAUSED, timeout=self.deadline)
            for done, command in enumerate(commands):
                try:
                    await printer.command(command, timeout=max(0.001, end - loop.time()))
                except (rh.HostError, TimeoutError):
                    return commands[done:]
        except TimeoutError:
            return commands
        return []

    async def close(self, safe_stop: bool) -> str | None:
        """Close the session; with ``safe_stop``, send the safe-stop sequence first."""
        problem = await self.leave_safe(failed=safe_stop)
        await self.printer.close()
        return problem


class HyrelPrinter:
    """A READY printer session for synchronous tests: each call returns when done.

    ``session`` is the :class:`repetrel_host.Printer` itself. It lives on the plugin's
    own event loop, in another thread: run its coroutines with :meth:`run`."""

    def __init__(self, session: _Session) -> None:
        self._session = session
        self._portal = session.portal
        self.session = session.printer

    @property
    def state(self) -> rh.State:
        return self.session.state

    @property
    def firmware(self) -> rh.Firmware | None:
        """What the controller said to M115, if it answered."""
        return self.session.firmware

    @property
    def temperatures(self) -> dict[str, tuple[float, float | None]]:
        """The last reading of each sensor: (current, target)."""
        return dict(self.session.temperatures)

    @property
    def port(self) -> str:
        return self.session.port

    def run(self, work: Callable[[rh.Printer], Awaitable[T]], timeout: float | None = None) -> T:
        """``await work(session)`` on the session's event loop, and return its result."""

        async def call() -> T:
            return await work(self.session)

        return self._portal.call(call(), timeout)

    def command(self, line: str, *, timeout: float | None = None) -> rh.Reply:
        """Send one command and return the controller's reply (``reply.lines``, ``reply.ok``)."""
        return self._portal.call(self._session.command(line, timeout))

    def print(
        self,
        job: HyrelJob | Path | str,
        *,
        force: bool = False,
        check: bool = True,
        timeout: float | None = None,
    ) -> PrintResult:
        """Stream ``job`` and return once the controller acknowledged all of it; raises
        what ended it if it failed (``check=False``: the result tells, in ``error``)."""
        return self.start(job, force=force).wait(check=check, timeout=timeout)

    def start(self, job: HyrelJob | Path | str, *, force: bool = False) -> RunningJob:
        """Start streaming ``job`` and return at once (to pause, cancel, watch it)."""
        job = _as_job(job)
        running = self._portal.call(self._session.start(job, force))
        return RunningJob(self._session, job, running)

    def pause(self) -> None:
        """Pause the running job; returns once every line sent is confirmed."""
        self._portal.call(self.session.pause())

    def resume(self) -> None:
        self._portal.call(self.session.resume())

    def cancel(self) -> None:
        """Stop the running job with the safe-stop sequence; returns once it went."""
        self._portal.call(self.session.cancel())

    def wait_for(self, *states: rh.State, timeout: float | None = None) -> None:
        """Wait until the session is in one of ``states`` (READY after a reset, an unplug)."""
        self._portal.call(self.session.wait_for(*states, timeout=timeout))

    def wait_for_temperature(
        self, sensor: str, target: float, *, tolerance: float = 2.0, timeout: float = 60.0
    ) -> float:
        """Wait until ``sensor`` (``T``, ``B``...) reads within ``tolerance`` of ``target``;
        returns the reading, or fails the test after ``timeout`` seconds."""
        work = self._session.wait_for_temperature(sensor, target, tolerance, timeout)
        return self._portal.call(work)

    def events(self, timeout: float) -> Iterator[PrinterEvent]:
        """State changes (the current one first), temperatures and controller messages,
        for ``timeout`` seconds (or until the session closes)."""
        portal = self._portal
        stream = portal.call(self._session.subscribe())
        deadline = time.monotonic() + timeout
        try:
            while (left := deadline - time.monotonic()) > 0:
                try:
                    yield portal.call(anext(stream), left)  # type: ignore[arg-type]
                except (StopAsyncIteration, TimeoutError):
                    return
        finally:
            with contextlib.suppress(Exception):
                portal.call(stream.aclose(), 5)  # type: ignore[attr-defined]


class RunningJob:
    """A job streaming from :meth:`HyrelPrinter.start`."""

    def __init__(self, session: _Session, job: HyrelJob, running: rh.PrintJob) -> None:
        self._session = session
        self.job = job
        self.print_job = running  # the session's rh.PrintJob

    @property
    def lines(self) -> int:
        """Job lines the controller acknowledged so far."""
        return self.print_job.lines

    @property
    def done(self) -> bool:
        return self.print_job.done

    def wait(self, *, check: bool = True, timeout: float | None = None) -> PrintResult:
        """Wait for the end (see :meth:`HyrelPrinter.print`)."""
        work = self._session.finish(self.job, self.print_job, check)
        return self._session.portal.call(work, timeout)

    def pause(self) -> None:
        self._session.portal.call(self.print_job.pause())

    def resume(self) -> None:
        self._session.portal.call(self.print_job.resume())

    def cancel(self) -> PrintResult:
        """Stop this job with the safe-stop sequence first; returns how far it got."""
        return self._session.portal.call(self._session.cancel(self.job, self.print_job))


class AsyncHyrelPrinter:
    """:class:`HyrelPrinter` for async tests: the same calls, awaited, from any asyncio loop."""

    def __init__(self, session: _Session) -> None:
        self._session = session
        self._portal = session.portal
        self.session = session.printer

    state = HyrelPrinter.state
    firmware = HyrelPrinter.firmware
    temperatures = HyrelPrinter.temperatures
    port = HyrelPrinter.port

    async def run(self, work: Callable[[rh.Printer], Awaitable[T]]) -> T:
        async def call() -> T:
            return await work(self.session)

        return await self._portal.acall(call())

    async def command(self, line: str, *, timeout: float | None = None) -> rh.Reply:
        return await self._portal.acall(self._session.command(line, timeout))

    async def print(
        self, job: HyrelJob | Path | str, *, force: bool = False, check: bool = True
    ) -> PrintResult:
        return await (await self.start(job, force=force)).wait(check=check)

    async def start(self, job: HyrelJob | Path | str, *, force: bool = False) -> AsyncRunningJob:
        job = _as_job(job)
        running = await self._portal.acall(self._session.start(job, force))
        return AsyncRunningJob(self._session, job, running)

    async def pause(self) -> None:
        await self._portal.acall(self.session.pause())

    async def resume(self) -> None:
        await self._portal.acall(self.session.resume())

    async def cancel(self) -> None:
        await self._portal.acall(self.session.cancel())

    async def wait_for(self, *states: rh.State, timeout: float | None = None) -> None:
        await self._portal.acall(self.session.wait_for(*states, timeout=timeout))

    async def wait_for_temperature(
        self, sensor: str, target: float, *, tolerance: float = 2.0, timeout: float = 60.0
    ) -> float:
        work = self._session.wait_for_temperature(sensor, target, tolerance, timeout)
        return await self._portal.acall(work)

    async def events(self) -> AsyncIterator[PrinterEvent]:
        """State changes (the current one first), temperatures and controller messages."""
        portal = self._portal
        stream = await portal.acall(self._session.subscribe())
        try:
            while True:
                try:
                    yield await portal.acall(anext(stream))  # type: ignore[arg-type]
                except StopAsyncIteration:
                    return
        finally:
            with contextlib.suppress(Exception):
                await portal.acall(stream.aclose())  # type: ignore[attr-defined]


class AsyncRunningJob(RunningJob):
    """A job streaming from :meth:`AsyncHyrelPrinter.start`: the same calls, awaited."""

    async def wait(  # type: ignore[override]
        self, *, check: bool = True
    ) -> PrintResult:
        return await self._session.portal.acall(
            self._session.finish(self.job, self.print_job, check)
        )

    async def pause(self) -> None:  # type: ignore[override]
        await self._session.portal.acall(self.print_job.pause())

    async def resume(self) -> None:  # type: ignore[override]
        await self._session.portal.acall(self.print_job.resume())

    async def cancel(self) -> PrintResult:  # type: ignore[override]
        return await self._session.portal.acall(self._session.cancel(self.job, self.print_job))


# --- the controller -----------------------------------------------------------------


class HyrelController:
    """What the tests talk to: a real printer's port, or the fake controller.

    The fake-only parts (executed commands, faults, heaters) skip the test on real
    hardware. After :meth:`reset` or :meth:`unplug` the session greets the controller
    again: ``hyrel_printer.wait_for(rh.State.READY)`` before the next command."""

    def __init__(self, port: str, fake: BuiltInFake | None = None) -> None:
        self.port = port
        self.fake = fake

    @property
    def is_fake(self) -> bool:
        return self.fake is not None

    def _fake(self, what: str) -> BuiltInFake:
        if self.fake is None:
            pytest.skip(f"{what} needs the fake controller; this run drives {self.port}")
        return self.fake

    def _request(self, what: str, text: str) -> dict[str, Any]:
        answer = self._fake(what).request(text)
        if not answer.get("ok"):
            raise ValueError(f"the fake controller refused '{text}': {answer.get('error')}")
        return answer

    @property
    def log_path(self) -> Path:
        """The fake's log of executed commands (kept after the test)."""
        log = self._fake("the executed-command log").log_path
        assert log is not None  # the plugin gives its fakes a log
        return log

    @property
    def executed(self) -> list[str]:
        """Every command the fake executed, in order (the session's greeting included)."""
        self._request("the executed-command log", "status")  # flushes the log first
        return self.log_path.read_text(encoding="ascii", errors="replace").splitlines()

    @property
    def temperatures(self) -> dict[str, tuple[float, float]]:
        """The fake's heaters: (current, target) of ``T`` and ``B``."""
        readings = self._request("simulated temperatures", "status")["temperatures"]
        return {name: (float(now), float(target)) for name, (now, target) in readings.items()}

    @property
    def fault_counts(self) -> dict[str, int]:
        """How many of each fault the fake injected (corrupted_lines, dropped_oks...)."""
        counts: dict[str, int] = self._request("fault counts", "status")["counts"]
        return counts

    def set_faults(self, faults: str) -> None:
        """Switch faults from now on: ``"corrupt=0.02 drop_ok=0.05 seed=3"`` (the fake's
        ``--faults``: corrupt, garble, drop_ok, duplicate_ok, spurious_resend,
        resend_without_ok, flush_on_error, drop_duplicates, counted_resend,
        drop_with_error, busy_interval, seed)."""
        self._request("fault injection", f"set {faults}")

    def set_heat_rate(self, degrees_per_second: float | None) -> None:
        """How fast the fake's heaters move (None: at once, the default)."""
        rate = "none" if degrees_per_second is None else str(degrees_per_second)
        self._request("simulated heaters", f"heat_rate {rate}")

    def reset(self) -> None:
        """Reboot the fake: it says ``start``, as a controller does after a reset."""
        self._request("a controller reset", "reset")

    def hang(self) -> None:
        """The fake stops answering for good."""
        self._request("a hung controller", "hang")

    def unplug(self, seconds: float = 1.0) -> None:
        """Pull the cable: the pty vanishes, and comes back at the same path after ``seconds``."""
        self._request("an unplug", f"link_drop {seconds}")


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
    from repetrel_host.testing.fake_controller import build_parser, settings_from_args

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
    return "session" if _options(config).hardware else "function"


@pytest.fixture(scope="session")
def hyrel_options(pytestconfig: pytest.Config) -> HyrelOptions:
    """The plugin's options for this run."""
    return _options(pytestconfig)


@pytest.fixture(scope=_scope)
def hyrel_controller(
    request: pytest.FixtureRequest,
    hyrel_options: HyrelOptions,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[HyrelController]:
    """The controller under test: the real port, or a fake started for this test."""
    if hyrel_options.hardware:
        yield HyrelController(hyrel_options.port)
        return
    from repetrel_host.testing.fake_controller import BuiltInFake

    link = _link(hyrel_options)
    arguments = ["--bandwidth", str(link.baud / 10), "--latency", "0.001"]
    arguments += ["--protocol", link.protocol, *_fake_arguments(request.node)]
    log = tmp_path_factory.mktemp("hyrel-fake") / "executed.log"
    fake = BuiltInFake(log, arguments, control=True)
    fake.start()
    try:
        yield HyrelController(fake.port, fake)
    finally:
        fake.stop()


def _link(options: HyrelOptions) -> LinkSettings:
    from repetrel_host.config import load_user_config
    from repetrel_host.planning import JobRequest, LinkRequest, explicit_machine, link_settings
    from repetrel_host.protocol.flow import FlowMode

    loadout = Path(options.loadout) if options.loadout else None
    machine = explicit_machine(JobRequest(loadout, options.machine), load_user_config(None))
    flow = FlowMode(options.flow) if options.flow else None
    request = LinkRequest(baud=options.baud, flow=flow, protocol=options.protocol)
    return link_settings(request, machine)


@pytest.fixture(scope=_scope)
def _hyrel_session(
    hyrel_options: HyrelOptions, hyrel_controller: HyrelController
) -> Iterator[_Session]:
    import repetrel_host as rh

    options = hyrel_options
    portal = Portal()
    recorder = WireRecorder()
    deadline = SAFE_STOP_DEADLINE if options.hardware else FAKE_SAFE_STOP_DEADLINE

    async def open_session() -> _Session:
        link = _link(options)
        printer = await rh.connect(
            hyrel_controller.port,
            machine=options.machine,
            loadout=options.loadout,
            flow=link.flow,
            baud=link.baud,
            protocol=link.protocol,
            poll_interval=POLL_INTERVAL,
        )
        printer.tap_wire(recorder.tap)
        asyncio.get_running_loop().create_task(_record_events(printer, recorder))
        return _Session(portal, printer, recorder, deadline)

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
    request: pytest.FixtureRequest, session: _Session, facade: Callable[[_Session], T]
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
    wanted = _wanted_machines(item)
    if wanted:
        profile = printer.profile
        if profile.name not in wanted:
            machine = profile.describe()
            pytest.skip(f"for machine {' or '.join(wanted)}; this run's machine is {machine}")
    item.stash[_recorders] = session.recorder
    item.stash[_marks] = session.recorder.mark()
    yield facade(session)
    problem = session.portal.call(session.leave_safe(_failed(item)), 4 * session.deadline)
    if problem is not None:
        pytest.fail(f"hyrel: after the test, {problem}", pytrace=False)


@pytest.fixture
def hyrel_printer(
    request: pytest.FixtureRequest, _hyrel_session: _Session
) -> Iterator[HyrelPrinter]:
    """A READY printer session, for synchronous tests (see :class:`HyrelPrinter`)."""
    yield from _facade(request, _hyrel_session, HyrelPrinter)


@pytest.fixture
def hyrel_aprinter(
    request: pytest.FixtureRequest, _hyrel_session: _Session
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
            if "\n" not in source and source.lower().endswith(_FILE_SUFFIXES):
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
