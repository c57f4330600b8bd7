"""The printer session: one long-lived connection to one controller.

``connect`` opens the port, greets the controller (M110 and a probe on the RepRap
link, a ping on Hyrel's), asks M115 who it is, and hands back a READY
:class:`Printer`. The session then keeps reading: controller messages and
temperatures become events, commands get their replies, jobs stream one after
another on the same numbering, and a vanished port is reopened (with backoff) and
greeted again. It never resumes a job by itself.

All I/O is here: bytes go between a link (``repetrel_host.links``) and the one
pump (``repetrel_host.session.pump``), which drives the dialect. Models: zigpy-znp's
``api.py`` (connect, request and wait for the response, reconnect), Klipper's
``serialhdl.py`` (connect with retry, ``send_with_response``), h11's
``start_next_cycle`` (one connection, many exchanges).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import re
import weakref
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine, Generator, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Generic, TypeVar

from repetrel_host.config import UserConfig, load_user_config
from repetrel_host.errors import (
    ControllerError,
    HostError,
    JobError,
    LinkError,
    SafeStopError,
    UsageError,
)
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import Heater, HeaterLog, complete_safe_stop
from repetrel_host.links import Link, make_link
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects import create_dialect, release_bytes
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.events import Failed as DialectFailed
from repetrel_host.protocol.events import FailureKind, GreetingRetry, ProbeKind
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import clean_line
from repetrel_host.protocol.reports import Firmware, JobReport, ReportReader, parse_temperatures
from repetrel_host.session import history as print_history
from repetrel_host.session.events import (
    Action,
    Done,
    Failed,
    JobEvent,
    Message,
    NoAnswerYet,
    Notice,
    Paused,
    PauseReason,
    PrinterEvent,
    Progress,
    Report,
    Resend,
    Resumed,
    State,
    StateChanged,
    StopDelayed,
    Temperatures,
)
from repetrel_host.session.job import MAX_COMMAND_LENGTH, ActionKind, HostAction, JobItem, JobLine
from repetrel_host.session.planning import (
    JobPlan,
    JobRequest,
    LinkRequest,
    Profile,
    controller_profile,
    explicit_machine,
    history_file,
    link_settings,
    plan_job,
    resolve_port,
    resumed,
)
from repetrel_host.session.planning import safe_stop as safe_stop_for
from repetrel_host.session.pump import (
    CANCEL_DRAIN_TIMEOUT,
    Listener,
    Outcome,
    Pump,
    Run,
    Summary,
    failure_error,
)
from repetrel_host.session.resume import KEEPS_THE_JOB_STATE, HomeAxes, MachineState, back_to_job

if TYPE_CHECKING:
    from repetrel_host.fakes.simulator import ControllerSettings

log = logging.getLogger(__name__)

# M115 is asked again when its answer names no firmware (garbled), and waited for this
# long in all: a slow controller's answer decides the profile (and so its safe stop), not
# a short timeout. An answer that comes later still does.
FIRMWARE_TIMEOUT = 2.0  # for the M155 that follows it
FIRMWARE_PATIENCE = 12.0
FIRMWARE_ATTEMPTS = 3
# Temperatures are asked for this often while idle (M105), unless the firmware reports them.
POLL_INTERVAL = 5.0
# After an unplug, the port is tried again after this long, doubling up to the maximum.
RECONNECT_FIRST = 0.25
RECONNECT_MAX = 5.0
# After a failure, the line must be this quiet (or this long, at most) before a new
# greeting: answers to the old lines still on their way must not be taken for its own.
QUIET = 0.3
QUIET_MAX = 5.0
# How long each line of an owed safe stop may take to be answered after a reconnect.
SAFE_STOP_TIMEOUT = 30.0
# A job whose link failed before its safe stop was confirmed ends once the safe stop went
# after a reconnect, or after this long without one (connect's reconnect_wait).
RECONNECT_WAIT = 30.0
# Closing waits this long for the snapshots a job's markers asked for (M790, M791).
MARKER_TIMEOUT = 30.0
# A job's progress goes to its event subscribers at most this often.
PROGRESS_INTERVAL = 0.1
# Events a late subscriber to a job still gets.
JOB_EVENT_BACKLOG = 1000
LINK_LOST = "the serial link was lost (printer unplugged, or its port closed)"
# Sent before a job when its report is asked for: reset the metrics, and have M30 send
# the M773 report (Hyrel's diagnostic codes, M772: bit 0 of S).
REPORT_COMMAND = "M772 S1"
_FRAMED = re.compile(r"^\s*N-?\d|\*", re.IGNORECASE)

E = TypeVar("E")
_END = object()


BACK_TO_JOB_TIMEOUT = 60.0  # s: each command that brings a paused job's machine back


def _state_at(plan: JobPlan, line: int) -> MachineState:
    """The state the file's lines up to source ``line`` leave the machine in."""
    state = MachineState()
    for number, command, _, _ in plan.job.commands():
        if number > line:
            break
        state.apply(number, command)
    return state


@dataclass(frozen=True, slots=True)
class Reply:
    """The controller's answer to one command: its lines, then its ok."""

    command: str
    lines: list[str]  # the controller's lines for it, before its ok
    ok_line: str  # the ok line itself ("ok T:200.0 /200.0 B:60.0 /60.0"); "" when none came

    @property
    def ok(self) -> bool:
        """The controller acknowledged the command. False for M112 and M108, which go out
        at once (the firmware's emergency parser reads them) and get no ok."""
        return bool(self.ok_line)


@dataclass(frozen=True, slots=True)
class SessionSettings:
    """What a session was opened with."""

    port: str
    baud: int
    flow: FlowControl
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT
    reconnect: bool = True
    poll_interval: float | None = POLL_INTERVAL
    protocol: str = "reprap"
    user: UserConfig = field(default_factory=UserConfig)
    request: JobRequest = field(default_factory=JobRequest)
    checksum: bool = False  # Hyrel's link: the additive checksum on every line
    poll_while_printing: bool = False  # M105 between a job's lines, as OctoPrint does
    reconnect_wait: float = RECONNECT_WAIT


class _Hub(Generic[E]):
    """Hands every event to every subscriber, each at its own pace."""

    def __init__(self, backlog: int = 0) -> None:
        self._queues: list[asyncio.Queue[object]] = []
        self._backlog: deque[E] | None = deque(maxlen=backlog) if backlog else None
        self._closed = False
        # Called at once with each event, on the session's path (connect()'s on_event).
        self.callbacks: list[Callable[[E], None]] = []

    def publish(self, event: E) -> None:
        if self._backlog is not None:
            self._backlog.append(event)
        for queue in self._queues:
            queue.put_nowait(event)
        for callback in self.callbacks:
            try:
                callback(event)
            except Exception:  # a listener's bug must not break the session
                log.exception("an on_event callback failed on %r", event)

    def close(self) -> None:
        self._closed = True
        for queue in self._queues:
            queue.put_nowait(_END)

    def stream(self, first: Iterable[E] = ()) -> AsyncIterator[E]:
        """A subscription from now on (not from the first ``anext``), after ``first``."""
        queue: asyncio.Queue[object] = asyncio.Queue()
        for event in (*first, *(self._backlog or ())):
            queue.put_nowait(event)
        if self._closed:
            queue.put_nowait(_END)
        self._queues.append(queue)
        return self._drain(queue)

    async def _drain(self, queue: asyncio.Queue[object]) -> AsyncIterator[E]:
        try:
            while (event := await queue.get()) is not _END:
                yield event  # type: ignore[misc]
        finally:
            self._queues.remove(queue)


class _Command:
    """A command on its way: the lines that come for it, and the reply it awaits."""

    __slots__ = ("command", "future", "lines", "own")

    def __init__(self, command: str, future: asyncio.Future[Reply], own: bool = False) -> None:
        self.command = command
        self.lines: list[str] = []
        self.future = future
        self.own = own  # the session's own (the greeting's M115, a poll), not the caller's


class _Connection(asyncio.Protocol):
    """The asyncio side of one opened link; a stale one (after an unplug) is ignored."""

    def __init__(self, printer: Printer) -> None:
        self.printer = printer
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.printer._made(self)

    def data_received(self, data: bytes) -> None:
        self.printer._received(self, data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.printer._lost(self, exc)


ActionHandler = Callable[[HostAction], Awaitable[bool]]


class PrintJob:
    """One job streaming on a session: its progress, events and end."""

    def __init__(
        self,
        printer: Printer,
        plan: JobPlan,
        run: Run,
        on_action: ActionHandler | None,
        history: Path | None,
    ) -> None:
        self.printer = printer
        self.plan = plan
        self.name = plan.job.name
        self.size = plan.job.size
        self.history = history  # the stream as transmitted, or None
        self.on_action = on_action
        self._run = run
        self._done: asyncio.Future[Summary] = asyncio.get_running_loop().create_future()
        self._hub: _Hub[JobEvent] = _Hub(JOB_EVENT_BACKLOG)
        self._ticking = False  # progress goes out while someone listens
        self._reported = -1
        self._m0: asyncio.Future[None] | None = None  # an M0 waiting for resume()
        self._reports = ReportReader()
        self.started = datetime.now()
        self._keeper: print_history.ProgressKeeper | None = None  # the progress record

    @property
    def report(self) -> JobReport | None:
        """The M773 report the controller sent (at M30, after M772 S1), or None."""
        return self._reports.report

    # --- progress -------------------------------------------------------------

    @property
    def lines(self) -> int:
        """Job lines the controller acknowledged (the header's and safe stop's not counted)."""
        return self._run.lines

    @property
    def offset(self) -> int:
        """Bytes of the file up to the last acknowledged line."""
        return self._run.offset

    @property
    def last(self) -> JobLine | None:
        """The last job line the controller acknowledged."""
        return self._run.last

    @property
    def header_lines(self) -> int:
        """Lines of the header (the plan's) the controller acknowledged."""
        return self._run.header_acknowledged

    @property
    def done(self) -> bool:
        return self._done.done()

    @property
    def report_path(self) -> Path | None:
        """Where the M773 report is kept: beside the history, ``<run>-report.txt``."""
        history = self.history
        return history.with_name(f"{history.stem}-report.txt") if history else None

    def where(self) -> str:
        """The last line the controller acknowledged, as error messages name it."""
        return self._run.where()

    @property
    def resume_line(self) -> int | None:
        """The source line a resumed run would start from (``print(path, from_line=...)``):
        the one after the last job line known to have run. On Hyrel's link, where an ACK
        says only *received*, that is what the controller's answers confirmed (what it held
        when a stop aborted counts as not run); elsewhere the last acknowledged. None when
        no job line ran, or every one did."""
        return self._run.resume_line

    @property
    def sent_through(self) -> int | None:
        """The source line of the last job line on the wire when the job ended (None while
        it runs, or when none went): from :attr:`resume_line` to it, lines were sent and
        not confirmed, and some may have run (a lost link takes their oks with it)."""
        sent = self._run.last_sent
        return sent.source_line if sent is not None else None

    @property
    def resume_known_to_run(self) -> bool:
        """:attr:`resume_line` follows a line known to have run (Hyrel's link), not one
        acknowledged (an ok: taken to run, as its firmware took it)."""
        return self._run.acks_say_received

    @property
    def all_sent(self) -> bool:
        """The job was read to its end: what is left is the controller's to run."""
        run = self._run
        return run.exhausted and not run.stopping and not run.pause_requested

    @property
    def stopping(self) -> bool:
        """A stop was asked for (the safe stop is going, or went)."""
        return self._run.stop_requests > 0

    @property
    def reconnecting_for_safe_stop(self) -> bool:
        """The link failed before the safe stop went: the job ends once it went after a
        reconnect (or after ``reconnect_wait``); :meth:`stop` gives up waiting."""
        owing = self.printer._owing
        return owing is not None and owing[0] is self

    @property
    def safe_stop_missing(self) -> list[str]:
        """Safe-stop commands the controller did not confirm (after an abandoned stop)."""
        return self._run.safe_stop_missing

    def events(self) -> AsyncIterator[JobEvent]:
        """Progress, messages, resends, pauses, then Done or Failed (the last event)."""
        if not self._ticking and not self.done:
            self._ticking = True
            asyncio.get_running_loop().call_later(PROGRESS_INTERVAL, self._tick)
        return self._hub.stream()

    async def wait(self) -> Summary:
        """The summary once the job ended; raises what ended it (the errors hyrel-send shows)."""
        return await asyncio.shield(self._done)

    # --- control ----------------------------------------------------------------

    async def pause(self, at_layer_end: bool = False) -> None:
        await self.printer.pause(at_layer_end)

    async def resume(self) -> None:
        await self.printer.resume()

    async def cancel(self) -> None:
        await self.printer.cancel()

    def stop(self, error: HostError | None = None) -> bool:
        """Stop without waiting: the safe-stop sequence goes ahead of anything not sent,
        and :meth:`wait` raises ``error`` once it went (a cancel, without one).

        A second call abandons the safe stop and ends the job at once; it returns True
        then (:attr:`safe_stop_missing` says what was not confirmed)."""
        return self.printer._stop_job(self, error)

    # --- from the session ---------------------------------------------------------

    def _publish(self, event: JobEvent) -> None:
        self._hub.publish(event)

    def _drop_m0(self) -> None:
        """An M0's wait ends without a resume (the job stops, or ended)."""
        if self._m0 is not None:
            self._m0.cancel()
            self._m0 = None

    def _tick(self) -> None:
        # Polled, not pushed per line: a line's acknowledgement costs nothing here.
        if self.done:
            return
        if self.lines != self._reported:
            self._reported = self.lines
            self._publish(self._progress())
        asyncio.get_running_loop().call_later(PROGRESS_INTERVAL, self._tick)

    def _progress(self) -> Progress:
        last = self._run.last
        return Progress(self.lines, self.offset, self.size, last.position if last else "")

    def _keep_progress(self) -> None:
        """The progress in the run's record as the job streams, every PROGRESS_INTERVAL
        (written when it moved): a killed run resumes from it (``--history-list``)."""
        keeper = self._keeper
        if keeper is None or self.done:
            return
        last = self._run.last
        acknowledged = last.source_line if last else 0
        keeper.update(
            self.lines,
            self.where(),
            acknowledged,
            self.resume_line,
            self.resume_known_to_run,
            self.all_sent,
            self.printer._pump.dialect.last_sent if self.printer._pump else None,
        )
        asyncio.get_running_loop().call_later(print_history.PROGRESS_INTERVAL, self._keep_progress)

    def _finish(self, run: Run, error: HostError | None, summary: Summary | None) -> None:
        if self._done.done():
            return
        self._publish(self._progress())
        report, path = self.report, self.report_path
        if report is not None:
            self._publish(Report(report))
            if path is not None:  # beside the stream, under the same run's name
                with contextlib.suppress(OSError):
                    path.write_text(report.text + "\n")
        history = self.history
        if history is not None and print_history.parse_run(history) is not None:
            # How it ended, beside a stream in a history folder (--history-list); not
            # beside a file of the caller's own naming (history=Path("/dev/null")...).
            print_history.write_record(history, self._record(error, summary))
        if error is not None:
            self._publish(Failed(error))
            self._done.set_exception(error)
            self._done.exception()  # retrieved: a job nobody waits for is no error
        else:
            assert summary is not None
            self._publish(Done(summary))
            self._done.set_result(summary)
        self._hub.close()

    def _record(self, error: HostError | None, summary: Summary | None) -> print_history.Record:
        if error is not None:
            outcome = print_history.FAILED
        elif summary is not None and summary.outcome is Outcome.CANCELLED:
            outcome = print_history.CANCELLED
        else:
            outcome = print_history.COMPLETED
        ended = datetime.now()
        seconds = summary.seconds if summary else (ended - self.started).total_seconds()
        return print_history.Record(
            job=self.name,
            outcome=outcome,
            lines=self.lines,
            seconds=round(seconds, 3),
            where=self.where(),
            port=self.printer.port,
            started=self.started.isoformat(timespec="seconds"),
            ended=ended.isoformat(timespec="seconds"),
            error=str(error) if error is not None else "",
            error_kind=print_history.error_kind(error) if error is not None else "",
        )


class Printer:
    """One long-lived connection to one controller (see the module's docstring)."""

    def __init__(self, link: Link, settings: SessionSettings) -> None:
        self._loop = asyncio.get_running_loop()
        self.link = link
        self.settings = settings
        self.state = State.CONNECTING
        self.state_reason = ""  # why it came to its state, where the session said (a lost port)
        self.firmware: Firmware | None = None
        self.probe: ProbeKind | None = None
        self.temperatures: dict[str, tuple[float, float | None]] = {}
        self._connection: _Connection | None = None
        self._pump: Pump | None = None
        self._listener = _PumpListener(self)
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self._ready: asyncio.Future[ProbeKind] | None = None
        self._commands: deque[_Command] = deque()
        self._lock = asyncio.Lock()
        self._job: PrintJob | None = None
        self._last_job: PrintJob | None = None
        # The words of the commands sent during the job's pause that may have moved the
        # machine or changed a mode (jog, home, extrude, T...): resume() comes back first.
        self._paused_words: set[str] = set()
        self._wire_log: BinaryIO | None = None
        self._hub: _Hub[PrinterEvent] = _Hub()
        self._state_waiters: list[tuple[Callable[[], bool], asyncio.Future[None]]] = []
        self._tasks: set[asyncio.Task[Any]] = set()
        self._markers: weakref.WeakSet[asyncio.Task[None]] = weakref.WeakSet()  # snapshots
        self._reconnecting: asyncio.Task[None] | None = None
        self._polling: asyncio.Task[None] | None = None
        self._autoreport = False  # the controller reports temperatures itself (M155 took)
        self._autoreport_asked: asyncio.Future[Reply] | None = None  # this connection's M155
        self._greeting = ""  # what the controller said of itself as it was greeted
        self._signs: list[str] = []  # its M115 lines, whatever command they came with
        self._signed = asyncio.Event()
        self._closing = False
        self._last_data_at = 0.0
        # The safe stop a job that failed (the link, the controller) could not send, and
        # the job that waits for it to go (after a reconnect) before it ends.
        self._owed_safe_stop: list[str] = []
        # A safe stop owed from before this session (a server's restart): the whole of it,
        # made once the controller said who it is, for the heaters kept from before.
        self._owe_whole_safe_stop = False
        self._owing: tuple[PrintJob, Run] | None = None
        self._owing_timer: asyncio.TimerHandle | None = None
        self._heaters = HeaterLog()  # every heater the session's commands set
        self._wire_taps: list[Callable[[bool, bytes], None]] = []
        self._line_taps: list[Callable[[str, bool], None]] = []
        # The wire's latest pieces, (sent, data), while a log reads them now and then (the
        # push socket's terminal): one append a write or read, nothing more, and nothing at
        # all while it is None. Bounded: a reader that falls behind loses the oldest.
        self.wire_tail: deque[tuple[bool, bytes]] | None = None
        self._watchers: list[Callable[[], None]] = []

    @property
    def port(self) -> str:
        return self.link.port

    @property
    def job(self) -> PrintJob | None:
        """The job streaming now, if any."""
        return self._job

    @property
    def last_job(self) -> PrintJob | None:
        """The job started last, streaming or ended (after a failure: its resume_line)."""
        return self._last_job

    @property
    def profile(self) -> Profile:
        """The machine profile of what is not a job (commands, a safe stop): the one asked
        for, else the firmware's (M115), as :func:`plan_job` chooses without a slicer."""
        return controller_profile(self.settings.request, self.settings.user, self.firmware)

    @property
    def safe_stop(self) -> list[str]:
        """The profile's safe-stop sequence (fans, heaters, motors off; a lift), turning
        off every hotend by its index where the controller has several or the session
        heated several (and a chamber it heated)."""
        profile = self.profile
        commands = safe_stop_for(profile.machine, self.settings.user, both=profile.fallback)
        return complete_safe_stop(commands, self._heaters, self._hotends())

    @property
    def owed_safe_stop(self) -> list[str]:
        """Safe-stop commands a job could not send (its link failed), or owed from before
        the session (``connect(owe_safe_stop=...)``), still to go: they go first once the
        controller answers again, after what it still holds or waits for is dropped or
        ended where the link can (Hyrel's abort and end-wait, Marlin's M108)."""
        return self.safe_stop if self._owe_whole_safe_stop else list(self._owed_safe_stop)

    @property
    def heater_log(self) -> HeaterLog:
        """Every heater (and fan) the session's commands set: what a safe stop turns off."""
        return self._heaters

    def heaters_on(self) -> list[str]:
        """The heaters that may be on: set above zero by a command the session sent (and
        not turned off since, as far as the controller confirmed), or reported with a
        target above zero."""
        log = self._heaters
        named = {_heater_name(h.kind, h.index): h.describe() for h in log.on()}
        for sensor, (current, target) in self.temperatures.items():
            kind = {"T": "hotend", "B": "bed", "C": "chamber"}.get(sensor[:1])
            if not target or kind is None:
                continue
            index = int(sensor[1:]) if sensor[1:].isdigit() else None
            if kind == "hotend" and index is None:
                index = log.tool
            name = _heater_name(kind, index)
            named.setdefault(name, f"{name} (reported {current:g} °C, target {target:g} °C)")
        return list(named.values())

    def _hotends(self) -> int:
        count = self.firmware.fields.get("EXTRUDER_COUNT", "1") if self.firmware else "1"
        return int(count) if count.isdigit() and int(count) > 0 else 1

    def events(self) -> AsyncIterator[PrinterEvent]:
        """State changes (the current state first), temperatures, controller messages."""
        return self._hub.stream([StateChanged(self.state, None)])

    async def wait_for(self, *states: State, timeout: float | None = None) -> None:
        """Wait until the session is in one of ``states``."""
        await asyncio.wait_for(self._until(lambda: self.state in states), timeout)

    def tap_lines(self, callback: Callable[[str, bool], None]) -> Callable[[], None]:
        """Call ``callback(command, own)`` for each line as it first goes on the wire, in
        order; ``own``: the host's own line (the greeting, a temperature poll, a sync on
        Hyrel's link), not the caller's nor a job's. Returns what removes the tap. For
        tests that read what the controller ran (a fake's log) without the host's lines."""
        self._line_taps.append(callback)
        if self._pump is not None:
            self._pump.dialect.on_first_send = self._first_send
        return lambda: self._line_taps.remove(callback)

    def _first_send(self, command: str, tag: object, own: bool) -> None:
        own = own or (isinstance(tag, _Command) and tag.own)
        for tap in self._line_taps:
            tap(command, own)

    def tap_wire(self, callback: Callable[[bool, bytes], None]) -> Callable[[], None]:
        """Call ``callback(sent, data)`` with every piece of data written (``sent``) or
        received, as it goes; returns what removes the tap. For logs and test reports."""
        self._wire_taps.append(callback)
        return lambda: self._wire_taps.remove(callback)

    def watch(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback()`` whenever the state changes or the job's phase does (read to
        its end, stopping), at once: for a view that must not miss a short phase. It runs
        on the session's path, so it must only take note (no I/O, no await). Returns what
        removes it."""
        self._watchers.append(callback)
        return lambda: self._watchers.remove(callback)

    def _changed(self) -> None:
        for watcher in self._watchers:
            watcher()

    @property
    def link_stats(self) -> Statistics | None:
        """The link's counts (lines sent, resends asked for...), or None while unlinked."""
        pump = self._pump
        return pump.dialect.stats if pump is not None else None

    # --- commands ---------------------------------------------------------------

    async def command(self, line: str, *, timeout: float | None = None) -> Reply:
        """Send one command through the numbered, checksummed, resend-safe path and
        return the controller's reply. M112 goes out at once, unnumbered, and stops a job;
        M108 goes out at once too (Marlin's emergency parser ends a heat wait with it)."""
        command = _clean_command(line)
        word = command_word(command)
        if word == "M112":
            self.emergency_stop()
            return Reply(command, [], "")
        if word == "M108":
            if self._pump is not None and self._pump.controller_holds:
                # On Hyrel's link it is end-wait, which would end the hold behind the
                # session's back (and the later resume() a heat-up's wait).
                raise UsageError("the job is paused: resume() ends the pause, not M108")
            self._urgent(command)
            return Reply(command, [], "")
        self._check_can_command()
        async with self._lock:
            self._check_can_command()
            if self.state is State.PAUSED and word not in KEEPS_THE_JOB_STATE:
                self._paused_words.add(word)
            return await self._command(command, timeout)

    async def _command(self, command: str, timeout: float | None, own: bool = False) -> Reply:
        pending = self._send_command(command, own)
        # Shielded: a timeout leaves it pending, so that its late lines are still its own.
        return await asyncio.wait_for(asyncio.shield(pending.future), timeout)

    def _send_command(self, command: str, own: bool = False) -> _Command:
        pump = self._pump
        if pump is None:
            raise LinkError(f"{self.port} is not connected")
        pending = _Command(command, self._loop.create_future(), own)
        self._commands.append(pending)
        pump.command(command, pending)
        self._poke()
        return pending

    def _sign(self, text: str) -> None:
        """A line that says which firmware this is (M115's ``FIRMWARE_NAME:`` and ``Cap:``
        lines), whichever command it came with or after: a slow controller's answer still
        decides, once it comes."""
        self._signs.append(text)
        found = Firmware.parse(self._signs)
        known = self.firmware
        if found is None or (
            known is not None
            and (known.fields, known.capabilities) == (found.fields, found.capabilities)
        ):
            return
        late = self.state is not State.CONNECTING and (
            self.firmware is None or self.firmware.name != found.name
        )
        self.firmware = found
        self._signed.set()
        self._use_firmware()
        # Its M155, if it has one, also when it said who it is only once a job was under
        # way: after this dispatch (not inside it), on this connection only.
        self._loop.call_soon(self._late_autoreport, self._pump)
        if late:
            self._hub.publish(Notice(f"the controller said who it is: {found.name}"))

    def _use_firmware(self) -> None:
        """What the pump takes from the firmware: its hotends, whether M108 ends a wait."""
        pump, firmware = self._pump, self.firmware
        if pump is not None:
            pump.hotends = self._hotends()
            pump.breaks_waits = (
                firmware is not None
                and firmware.can("EMERGENCY_PARSER")
                and not pump.dialect.acks_say_received  # Hyrel's link aborts instead
            )

    def _ask_autoreport(self) -> asyncio.Future[Reply] | None:
        """M155 once a connection, where the firmware reports temperatures itself (and the
        session polls at all): the polls stop once the controller took it, whenever that
        is (mid-job too: it goes among the job's lines as a poll does, none of them)."""
        interval = self.settings.poll_interval
        firmware = self.firmware
        if (
            self._autoreport_asked is not None
            or not interval
            or firmware is None
            or not firmware.can("AUTOREPORT_TEMP")
            or self._pump is None
        ):
            return self._autoreport_asked
        pending = self._send_command(f"M155 S{max(1, math.ceil(interval))}", own=True)
        pending.future.add_done_callback(self._autoreporting)
        self._autoreport_asked = pending.future
        return pending.future

    def _late_autoreport(self, pump: Pump | None) -> None:
        if pump is not None and pump is self._pump:
            self._ask_autoreport()

    def _autoreporting(self, future: asyncio.Future[Reply]) -> None:
        if future.cancelled() or future.exception() is not None:
            return  # refused, or the connection ended: polled instead
        if future is not self._autoreport_asked:
            return  # an earlier connection's
        self._autoreport = True
        if self.state is not State.CONNECTING:
            # What came while it waited is the job's (messages), not the M155's.
            for line in future.result().lines:
                if not parse_temperatures(line):
                    self._broadcast(Message(line))

    def _check_can_command(self) -> None:
        state = self.state
        if state is State.PRINTING:
            raise UsageError(
                "a job is printing: commands wait until it ends or is paused (pause() first)"
            )
        if state is not State.READY and state is not State.PAUSED:
            raise LinkError(f"{self.port} is not connected (the session is {state.value})")
        if state is State.PAUSED and self._pump is not None and self._pump.controller_holds:
            raise UsageError(
                "the controller holds the paused job's lines (Hyrel's link): a command "
                "would wait behind them; it can go after resume() or cancel()"
            )

    @property
    def pending(self) -> list[str]:
        """Commands sent or queued that still wait for their reply (an M109 heating...)."""
        return [pending.command for pending in self._commands]

    def _urgent(self, command: str) -> None:
        pump = self._pump
        if pump is None:
            raise LinkError(f"{self.port} is not connected")
        pump.dialect.send_urgent(command_word(command))  # as emergency parsers read it
        self._poke()

    def emergency_stop(self) -> None:
        """M112 at once, unnumbered: the controller halts (its heaters off) until reset; a
        job ends with a ControllerError, and no safe stop is owed."""
        self._urgent("M112")
        self._owed_safe_stop = []  # the controller halted: its heaters are off
        self._owe_whole_safe_stop = False
        if self._pump is not None:
            error = ControllerError(
                "stopped by an emergency stop (M112): the controller halted (heaters off) "
                "and needs a reset"
            )
            self._pump.emergency_stop(self._loop.time(), error)
            self._poke()

    # --- jobs -------------------------------------------------------------------

    def plan(
        self,
        path: Path | str,
        *,
        header: bool = True,
        from_line: int | None = None,
        resume_home: HomeAxes = HomeAxes.XY,
    ) -> JobPlan:
        """What :meth:`print` would stream for ``path``: profile, header, safe stop; with
        ``from_line``, resumed there (the preamble first: :func:`planning.resumed`)."""
        request = JobRequest(self.settings.request.loadout, self.settings.request.machine, header)
        plan = plan_job(Path(path), request, self.settings.user, self.firmware)
        return plan if from_line is None else resumed(plan, from_line, resume_home)

    async def print(
        self,
        job: Path | str | JobPlan,
        *,
        header: bool = True,
        force: bool = False,
        history: Path | str | bool = True,
        on_action: ActionHandler | None = None,
        on_warning: Callable[[str], None] | None = None,
        report: bool = False,
        from_line: int | None = None,
        command_line: Iterable[str] = (),
    ) -> PrintJob:
        """Start streaming ``job`` (a path, or a plan from :meth:`plan`); returns at once.

        A path gets the loadout's header (unless ``header=False``) and is checked first
        (over 4 MB, as it streams): an error refuses the job unless ``force``; a plan was
        checked by whoever made it (a big one is still checked as it streams).
        ``history``: keep the stream as transmitted (True, the default: in the configured
        history folder; a path: that file; False: none), and how the job ended beside it
        (``<run>.json``); the oldest runs in that folder go, down to ``history_max_mb``.
        ``on_action`` performs M792's SAY, BEEP, SHELL... and an M0's; M0 pauses the job
        until :meth:`resume`. Warnings go to ``on_warning``, else to the events.
        ``report``: send ``M772 S1`` first, so that a Hyrel controller sends its M773 job
        report at M30 (:attr:`PrintJob.report`, kept beside the history).
        ``from_line``: resume a failed print there (see :meth:`plan`; a failed job's
        :attr:`PrintJob.resume_line` says where). ``command_line``: hyrel-send's arguments,
        kept with the progress so that ``--history-list`` offers a killed run's resume.
        """
        if self._job is not None or self.state is State.PRINTING or self.state is State.PAUSED:
            raise UsageError("a job is already running on this printer")
        self._check_can_command()
        # Planning (a resume reads up to its line) and the check before the first line
        # read the file: a thread's work, not the event loop's (every printer's stream).
        if isinstance(job, JobPlan):
            plan = job if from_line is None else await asyncio.to_thread(resumed, job, from_line)
        else:
            plan = await asyncio.to_thread(
                functools.partial(self.plan, job, header=header, from_line=from_line)
            )
        warn = on_warning or self._warn
        checker = None
        if plan.checked_as_it_streams:
            checker = plan.streaming_checker(warn, force)
        elif not isinstance(job, JobPlan):
            findings = await asyncio.to_thread(plan.check)
            for finding in findings:
                warn(finding.format(plan.job.name))
            plan.refuse(findings, force, "force=True")
        async with self._lock:
            if self._job is not None:  # another print() got here first
                raise UsageError("a job is already running on this printer")
            self._check_can_command()
            pump = self._pump
            assert pump is not None
            path = self._open_history(plan, history)
            items: Iterable[JobItem] = plan.items(checker, pump.dialect.pause_command)
            if report:
                items = chain([JobLine(0, 0, REPORT_COMMAND, 0, "report")], items)
            run = Run(items, plan.safe_stop, started_at=self._loop.time())
            if plan.resume is not None:  # progress by bytes goes on from the skipped part
                run.offset = plan.resume.start_offset
            print_job = PrintJob(self, plan, run, on_action, path)
            if path is not None and print_history.parse_run(path) is not None:
                # Its progress in the run's record, written before the first line goes.
                print_job._keeper = print_history.ProgressKeeper(
                    path,
                    plan.job.path,
                    command_line,
                    self.port,
                    print_job.started,
                    pump.dialect.last_sent,
                )
                print_job._keep_progress()
            self._job = self._last_job = print_job
            self._paused_words.clear()  # an earlier job's pause is not this one's
            pump.begin(run)
            self._set_state(State.PRINTING, plan.job.name)
            self._poke()
        if path is not None and print_history.parse_run(path) is not None:
            self._prune_history(path)  # a history folder's: never a folder of other files
        return print_job

    def _warn(self, text: str) -> None:
        self._broadcast(Notice(text))

    def _broadcast(self, event: Notice | Message) -> None:
        """To the session's subscribers and the running job's."""
        self._hub.publish(event)
        if self._job is not None:
            self._job._publish(event)

    def _prune_history(self, started: Path) -> None:
        """The oldest runs beside ``started`` go, down to ``history_max_mb``: in a thread,
        as the first lines stream."""
        limit = self.settings.user.host.history_max_mb
        if limit > 0:
            prune = functools.partial(print_history.prune, started.parent, limit, started)
            self._loop.run_in_executor(None, prune)

    def _open_history(self, plan: JobPlan, history: Path | str | bool) -> Path | None:
        if history is False:
            return None
        if history is True:
            path = history_file(None, self.settings.user, plan.job)
        else:
            path = Path(history)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # Unbuffered: what is written reaches the OS at once (_write), so that a killed
            # host leaves every byte the port got in the stream.
            self._wire_log = path.open("wb", buffering=0)
        except OSError as exc:
            raise JobError(f"cannot write the print history {path}: {exc.strerror}") from None
        return path

    async def pause(self, at_layer_end: bool = False) -> None:
        """Stop feeding the job; returns once it is PAUSED: on Hyrel's link once the
        controller was told to hold it at the end of the move (or of the layer:
        ``at_layer_end``), on the RepRap link once every line sent is confirmed."""
        job = self._job
        if job is None:
            raise UsageError("no job is printing")
        if self.state is State.PAUSED:
            return
        if self._pump is not None:
            self._pump.pause(at_layer_end)
            self._poke()
        await self._until(lambda: self.state is not State.PRINTING or job.done)
        if self.state not in (State.PAUSED,):  # (a tuple: the await changed it)
            raise UsageError(f"{job.name} ended before the pause could hold it")

    async def resume(self) -> None:
        """Go on with a paused job (paused by :meth:`pause` or by an M0)."""
        job = self._job
        if job is None or self.state is not State.PAUSED:
            raise UsageError("no job is paused")
        if self._paused_words:
            await self._back_to_job(job)
            if self._job is not job or self.state is not State.PAUSED:
                raise UsageError(f"{job.name} ended before it could resume")
        self._set_state(State.PRINTING, "resumed")
        job._publish(Resumed())
        if job._m0 is not None:
            m0, job._m0 = job._m0, None
            m0.set_result(None)
        elif self._pump is not None:
            self._pump.resume()
            self._poke()

    async def _back_to_job(self, job: PrintJob) -> None:
        """Commands moved the machine during the pause (or changed its modes): back to where
        the job stood, in its modes, before its next line (:func:`resume.back_to_job`). The
        state is read from the file's lines up to the last one sent, in a thread."""
        last = job.last
        line = last.source_line if last is not None else 0
        words = self._paused_words
        tool_changed = any(word.startswith("T") for word in words)
        motors_off = bool(words & {"M84", "M18"})
        state = await asyncio.to_thread(_state_at, job.plan, line)
        for entry in back_to_job(state, tool_changed, motors_off):
            await self.command(entry.command, timeout=BACK_TO_JOB_TIMEOUT)
        self._paused_words.clear()

    async def cancel(self) -> None:
        """Stop the job with the safe-stop sequence; returns once it went."""
        job = self._job
        if job is None:
            return
        if not job.stopping:
            job.stop()
        with contextlib.suppress(HostError):
            await job.wait()

    def _stop_job(self, job: PrintJob, error: HostError | None) -> bool:
        if self._owing is not None and self._owing[0] is job:
            self._give_up_owed("given up before the controller answered again")
            return True
        if job is not self._job or self._pump is None:
            return False
        job._drop_m0()
        if self.state is State.PAUSED:
            self._set_state(State.PRINTING, "stopping")
        abandoned = self._pump.stop(self._loop.time(), error)
        self._changed()  # stopping
        self._poke()
        return abandoned

    # --- opening, greeting, reconnecting -------------------------------------

    async def _open(self) -> None:
        """Open the link and greet the controller: READY, or a HostError."""
        self._set_state(State.CONNECTING, f"opening {self.port}")
        self._ready = self._loop.create_future()
        await self.link.open(lambda: _Connection(self))
        await self._greet()

    async def _greet(self) -> None:
        ready = self._ready
        assert ready is not None
        try:
            self.probe = await ready
            await self._identify()
        except BaseException as exc:
            # Nothing of this connection may outlive it: its pump, its commands (the
            # next connection's replies must not be taken for theirs).
            error = exc if isinstance(exc, HostError) else LinkError("the greeting stopped")
            self._end_connection(error)
            self._drop_connection()
            raise
        await self._send_owed_safe_stop()
        self._set_state(State.READY, "greeted")
        interval = self.settings.poll_interval
        if interval and self._polling is None:
            self._polling = self._spawn(self._poll(interval))

    async def _send_owed_safe_stop(self) -> None:
        """What a failed job could not send: heaters off before anything else. Each line
        is owed until the controller confirms it; the job that waits for them ends then."""
        if self._owe_whole_safe_stop:  # the profile is known now: made whole once
            self._owed_safe_stop = self.safe_stop
            self._owe_whole_safe_stop = False
        owed = list(self._owed_safe_stop)
        if not owed:
            return
        self._tell_owing(Notice(f"sending the safe stop the interrupted job missed: {owed}"))
        for command in owed:
            try:
                await self._command(command, SAFE_STOP_TIMEOUT)
            except (HostError, TimeoutError):
                return  # the rest goes at the next greeting
            with contextlib.suppress(ValueError):
                self._owed_safe_stop.remove(command)
        if self._owing is not None:
            job, run = self._owing
            ended = self._delivered(run)
            self._stop_owing()
            job._finish(run, *ended)

    def _tell_owing(self, event: Notice) -> None:
        self._hub.publish(event)
        if self._owing is not None:
            self._owing[0]._publish(event)

    def _owe(self, job: PrintJob, run: Run) -> None:
        """The job's link failed before its safe stop was confirmed: it ends once the safe
        stop went after a reconnect, or after ``reconnect_wait`` seconds without one."""
        wait = self.settings.reconnect_wait
        self._owing = (job, run)
        self._owing_timer = self._loop.call_later(
            wait, self._give_up_owed, f"the controller did not answer again within {wait:g} s"
        )
        self._tell_owing(
            Notice(
                f"{run.error}. The safe stop did not go: trying to reach the controller again "
                f"to send it (for up to {wait:g} s)"
            )
        )

    def _stop_owing(self) -> None:
        self._owing = None
        if self._owing_timer is not None:
            self._owing_timer.cancel()
            self._owing_timer = None

    def _give_up_owed(self, why: str) -> None:
        """The job waiting for its safe stop ends without it (it stays owed: it goes at
        the session's next greeting, should there be one)."""
        if self._owing is None:
            return
        job, run = self._owing
        self._stop_owing()
        job._finish(
            run, self._unsafe(f"{run.error}; the safe stop could not be sent ({why})"), None
        )

    def _delivered(self, run: Run) -> tuple[HostError | None, Summary | None]:
        """How a job whose safe stop went after a reconnect ended: cancelled, if that is
        how it was stopping; else its failure, saying the safe stop went."""
        if run.cancelled_stop:
            self._tell_owing(Notice("the safe stop completed once the controller answered again"))
            stats = run.resends_before, run.retransmissions_before
            seconds = self._loop.time() - run.started_at
            return None, Summary(Outcome.CANCELLED, run.lines, seconds, *stats)
        assert run.error is not None
        went = "the safe stop went once the controller answered again"
        return type(run.error)(f"{run.error}; {went}"), None

    def _unsafe(self, cause: str) -> SafeStopError:
        """The sentence for a stop not confirmed: what may be on, and what to do."""
        heaters = self.heaters_on()
        on = f"; heaters that may be on: {', '.join(heaters)}" if heaters else ""
        return SafeStopError(f"{cause}{on}; check the machine (its power switch stops it)")

    def _ended(self, run: Run, connection_ends: bool) -> tuple[HostError | None, Summary | None]:
        """How a run that just ended is reported (a reconnect aside)."""
        error = run.error
        if error is None or run.emergency:
            return error, run.summary
        if isinstance(error, SafeStopError):  # abandoned by the caller
            going = "; they still go as the controller takes them, while the session is open"
            going = "" if connection_ends else going
            return self._unsafe(f"{error}{going}"), None
        if self._owed_safe_stop and connection_ends:
            return self._unsafe(f"{error}; the safe stop was not sent"), None
        return error, None

    async def _identify(self) -> None:
        self.firmware = None
        self._autoreport = False
        self._autoreport_asked = None
        self._signs = []
        self._signed.clear()
        # Without an answer to M115, the greeting's own (Hyrel's ping: ">Hy: ...").
        greeting = Firmware.parse([f"FIRMWARE_NAME:{self._greeting}"] if self._greeting else [])
        deadline = self._loop.time() + FIRMWARE_PATIENCE
        for _ in range(FIRMWARE_ATTEMPTS):
            pending = self._send_command("M115", own=True)
            with contextlib.suppress(TimeoutError):
                reply = await asyncio.wait_for(
                    asyncio.shield(pending.future), max(0.0, deadline - self._loop.time())
                )
                self.firmware = Firmware.parse([*reply.lines, reply.ok_line]) or self.firmware
                if self.firmware is not None:
                    break
                # Confirmed, its answer perhaps still to come (a probe found the line taken
                # before it ran), or garbled: a while for it, then ask again.
                left = min(FIRMWARE_TIMEOUT, deadline - self._loop.time())
                await asyncio.wait_for(self._signed.wait(), max(0.0, left))
            if self.firmware is not None or self._loop.time() >= deadline:
                break
        if self.firmware is None:
            # Not yet: an answer that comes later still decides (see _sign).
            self.firmware = greeting  # or none: it does not say who it is
        self._use_firmware()
        asked = self._ask_autoreport()
        if asked is not None:
            with contextlib.suppress(TimeoutError):  # polled until it took (if ever)
                await asyncio.wait_for(asyncio.shield(asked), FIRMWARE_TIMEOUT)

    def _no_answer(self, reason: str) -> str:
        """The greeting went unanswered: one sentence with the port, the baud rate, and
        what most likely stands in the way."""
        causes = "the wrong port, the wrong baud rate, or the board still booting"
        if self.settings.protocol == "hyrel":
            causes = (
                "the wrong port, the wrong baud rate, the board still booting, or a "
                "controller that does not speak Hyrel's own link"
            )
        return f"{self.port} at {self.settings.baud} baud: {reason}; likely {causes}"

    def _made(self, connection: _Connection) -> None:
        if self._closing:
            if connection.transport is not None:
                connection.transport.close()
            return
        self._connection = connection
        if self._clear_for_safe_stop():
            self._spawn(self._start_pump_when_quiet())
        else:
            self._start_pump()

    def _clear_for_safe_stop(self) -> bool:
        """With a safe stop owed, before the greeting: what the controller still holds or
        waits for must not hold the safe stop (nor the greeting) up (:func:`release_bytes`).
        True when it wrote."""
        if not (self._owed_safe_stop or self._owe_whole_safe_stop):
            return False
        self._tell_owing(Notice("a safe stop is owed: ending what the controller holds first"))
        self._write(release_bytes(self.settings.protocol))
        return True

    async def _until_quiet(self) -> None:
        """Until the controller has said nothing for QUIET s (at most QUIET_MAX): late
        answers to what went before must not be taken for the greeting's."""
        quiet_since = self._loop.time()
        while self._loop.time() - quiet_since < QUIET_MAX:
            wait = self._last_data_at + QUIET - self._loop.time()
            if wait <= 0:
                break
            await asyncio.sleep(wait)

    async def _start_pump_when_quiet(self) -> None:
        self._last_data_at = self._loop.time()
        await self._until_quiet()
        if self._connection is not None and not self._closing and self._pump is None:
            self._start_pump()

    def _start_pump(self) -> None:
        settings = self.settings
        dialect = create_dialect(
            settings.protocol,
            settings.flow,
            reply_timeout=settings.reply_timeout,
            checksum=settings.checksum,
        )
        if self._line_taps:
            dialect.on_first_send = self._first_send
        self._pump = Pump(dialect, self._listener, self._heaters)
        self._write(self._pump.start(self._loop.time()))
        self._arm_timer(self._pump.deadline)

    async def _regreet(self, reason: str) -> None:
        """Greet again on the same port (after a reset, or a failure)."""
        if self._connection is None or self._closing:
            return
        self._set_state(State.CONNECTING, reason)
        # Late answers to what went before must not be taken for the new greeting's.
        await self._until_quiet()
        if self._connection is None or self._closing:
            return
        if self._clear_for_safe_stop():
            self._last_data_at = self._loop.time()
            await self._until_quiet()
            if self._connection is None or self._closing:
                return
        self._ready = self._loop.create_future()
        self._start_pump()
        try:
            await self._greet()
        except HostError as exc:
            self._set_state(State.DISCONNECTED, str(exc))
            if self.settings.reconnect and self._reconnecting is None and not self._closing:
                self._reconnecting = self._spawn(self._reconnect())

    async def _reconnect(self) -> None:
        delay = RECONNECT_FIRST
        while not self._closing:
            await asyncio.sleep(delay)
            try:
                await self._open()
            except Exception as exc:  # whatever the port did, try again later
                log.debug("reconnect: %r", exc)
                self._set_state(State.DISCONNECTED, str(exc))
                delay = min(delay * 2, RECONNECT_MAX)
                continue
            break
        self._reconnecting = None

    async def _poll(self, interval: float) -> None:
        """Temperatures every ``interval`` seconds, unless the controller reports them
        itself (M155): while idle, and while a job prints or is paused when the session was
        opened with ``poll_while_printing``. Where the link has a status request that the
        controller answers at once, whatever it holds (Hyrel's 0x05), that; else M105,
        while no command waits: among a job's lines it is numbered as they are, but none of
        them (the job's count and resume point never include it; a resend sends it again as
        itself; a stop drops it unsent)."""
        while True:
            await asyncio.sleep(interval)
            pump = self._pump
            if self._autoreport or pump is None or not self._polls_now():
                continue
            if pump.dialect.request_status():
                self._poke()
                continue
            if self._lock.locked() or self._commands or pump.controller_holds:
                continue
            with contextlib.suppress(HostError, TimeoutError):
                async with self._lock:
                    reply = await self._command("M105", interval * 2, own=True)
                # What came while it waited is the job's (messages), not the poll's.
                for line in reply.lines:
                    if not parse_temperatures(line):
                        self._broadcast(Message(line))

    def _polls_now(self) -> bool:
        state = self.state
        if state is State.READY:
            return True
        job = state is State.PRINTING or state is State.PAUSED
        return job and self.settings.poll_while_printing

    # --- I/O ------------------------------------------------------------------

    def _received(self, connection: _Connection, data: bytes) -> None:
        if connection is not self._connection:
            return
        log.debug("received %r", data)
        for tap in self._wire_taps:
            tap(False, data)
        tail = self.wire_tail
        if tail is not None:
            tail.append((False, data))
        self._last_data_at = now = self._loop.time()
        pump = self._pump
        if pump is not None:  # none between a failure and the next greeting: let it drain
            pump.receive(data, now)
            self._poke()

    def _lost(self, connection: _Connection, exc: Exception | None) -> None:
        if connection is not self._connection:
            return
        log.debug("connection lost: %s", exc)
        self._connection = None
        self._end_connection(LinkError(LINK_LOST))
        if self._closing:
            return
        self._set_state(State.DISCONNECTED, LINK_LOST)
        if self.settings.reconnect and self._reconnecting is None:
            self._reconnecting = self._spawn(self._reconnect())

    def _end_connection(self, error: HostError) -> None:
        """The pump is gone: the job fails naming its last line, commands fail."""
        pump, self._pump = self._pump, None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = self._timer_at = None
        if pump is not None and pump.run is not None:
            pump.abort(self._loop.time(), pump.run.naming_where(error))
        self._fail_waiters(error)

    def _fail_waiters(self, error: HostError) -> None:
        """The greeting under way and every command awaiting its reply fail with ``error``."""
        ready = self._ready
        if ready is not None and not ready.done():
            ready.set_exception(error)
            ready.exception()  # retrieved: nobody may be awaiting it
        self._fail_commands(self._commands, error)

    def _drop_connection(self) -> None:
        connection, self._connection = self._connection, None
        if connection is not None and connection.transport is not None:
            connection.transport.close()

    def _fail_commands(self, commands: Iterable[_Command], error: HostError) -> None:
        for pending in list(commands):
            if not pending.future.done():
                pending.future.set_exception(error)
                pending.future.exception()
            with contextlib.suppress(ValueError):
                self._commands.remove(pending)

    def _write(self, data: bytes) -> None:
        connection = self._connection
        if not data or connection is None or connection.transport is None:
            return
        log.debug("sending %r", data)
        for tap in self._wire_taps:
            tap(True, data)
        tail = self.wire_tail
        if tail is not None:
            tail.append((True, data))
        wire_log = self._wire_log
        if wire_log is not None:  # first: the history is never behind the wire
            written = wire_log.write(data)  # one write(2) a call (unbuffered)
            while written < len(data):  # a short one (a signal): the rest, or ENOSPC raised
                written += wire_log.write(data[written:]) or len(data) - written
        connection.transport.write(data)

    def _poke(self) -> None:
        pump = self._pump
        if pump is None:
            return
        self._write(pump.poke(self._loop.time()))
        if self._pump is pump:
            self._arm_timer(pump.deadline)

    def _arm_timer(self, deadline: float | None) -> None:
        # A timer already due no later stays: firing early is harmless (the pump checks
        # its own deadline and is poked again), and most lines only push it back.
        armed = self._timer_at
        if armed is not None and (deadline is None or armed <= deadline):
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_at = deadline
        if deadline is not None:
            self._timer = self._loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = self._timer_at = None
        pump = self._pump
        if pump is not None:
            pump.timeout(self._loop.time())
            self._poke()

    # --- state and events ----------------------------------------------------

    def _set_state(self, state: State, reason: str = "") -> None:
        if state is self.state:
            return
        previous, self.state = self.state, state
        self.state_reason = reason
        self._hub.publish(StateChanged(state, previous, reason))
        self._changed()
        waiters, self._state_waiters = self._state_waiters, []
        for ready, future in waiters:
            if future.done():
                continue
            if ready():
                future.set_result(None)
            elif state is State.CLOSED:
                future.set_exception(LinkError("the session is closed"))
            else:
                self._state_waiters.append((ready, future))

    async def _until(self, ready: Callable[[], bool]) -> None:
        if ready():
            return
        future: asyncio.Future[None] = self._loop.create_future()
        self._state_waiters.append((ready, future))
        await future

    def _spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = self._loop.create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # --- closing ----------------------------------------------------------------

    async def close(self) -> None:
        """Stop a running job with the safe stop first, then close the port."""
        if self.state is State.CLOSED:
            return
        job = self._job
        if job is not None and self._pump is not None:
            if not job.stopping:
                job.stop()  # a stop under way goes on: a second one would abandon it
            with contextlib.suppress(HostError, TimeoutError):
                await asyncio.wait_for(job.wait(), CANCEL_DRAIN_TIMEOUT + 5)
        self._give_up_owed("the session was closed")
        markers = {task for task in self._markers if not task.done()}
        if markers:  # a snapshot the job's last lines asked for is still taken
            await asyncio.wait(markers, timeout=MARKER_TIMEOUT)
        self._closing = True
        for task in list(self._tasks):
            task.cancel()
        self._end_connection(LinkError("the session is closed"))
        self._drop_connection()
        await self._loop.run_in_executor(None, self.link.close)
        self._set_state(State.CLOSED, "closed")
        self._hub.close()

    async def __aenter__(self) -> Printer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _PumpListener(Listener):
    """What the pump tells the session, kept off the public Printer."""

    def __init__(self, printer: Printer) -> None:
        self.printer = printer

    def greeting_retry(self, retry: GreetingRetry) -> None:
        printer = self.printer
        baud = printer.settings.baud
        event = NoAnswerYet(printer.port, baud, retry.attempt, retry.attempts, retry.waited)
        log.debug("%s at %d baud: %s", printer.port, baud, event.text)
        printer._hub.publish(event)

    def ready(self, probe: ProbeKind, identity: str) -> None:
        self.printer._greeting = identity
        ready = self.printer._ready
        if ready is not None and not ready.done():
            ready.set_result(probe)

    def command_done(self, tag: object, data: str) -> None:
        if not isinstance(tag, _Command):
            return
        printer = self.printer
        with contextlib.suppress(ValueError):
            printer._commands.remove(tag)
        if data:
            self._temperatures(data, f"ok {data}")
        if not tag.future.done():
            tag.future.set_result(Reply(tag.command, tag.lines, f"ok {data}" if data else "ok"))

    def commands_dropped(self, tags: list[object]) -> None:
        error = UsageError("the command was not sent: the job it waited behind was stopped")
        self.printer._fail_commands((t for t in tags if isinstance(t, _Command)), error)

    def command_refused(self, tag: object, reason: str) -> None:
        if isinstance(tag, _Command):
            self.printer._fail_commands([tag], ControllerError(reason))

    def read_to_end(self) -> None:
        self.printer._changed()  # what is left is the controller's to run: finishing

    def resend(self, line: JobLine) -> None:
        job = self.printer._job
        if job is not None:
            job._publish(Resend(line.position))

    def message(self, text: str, reply: replies.Reply) -> None:
        printer = self.printer
        if isinstance(reply, replies.Busy | replies.Wait):
            return  # keepalives
        job = printer._job
        if job is not None and isinstance(reply, replies.HyrelReport):
            for line in job._reports.feed(text):  # the M773 report is the job's
                self._message(line, replies.classify(line))
            return
        self._message(text, reply)

    def _message(self, text: str, reply: replies.Reply) -> None:
        printer = self.printer
        if text.startswith("Cap:") or "FIRMWARE_NAME:" in text:
            printer._sign(text)
        reported = self._temperatures(text, text)
        if printer._commands and not (reported and self._unasked(reply, printer._commands[0])):
            printer._commands[0].lines.append(text)
            return
        # A Hyrel notice (an M-code ran) tells what ran; it is no message for the user.
        notice = isinstance(reply, replies.HyrelReport) and reply.tag == "MC"
        if not reported and not notice:
            printer._broadcast(Message(text))

    def _unasked(self, reply: replies.Reply, command: _Command) -> bool:
        """Whether a temperature report is no part of ``command``'s reply: the firmware's
        own reports, or Hyrel's status report (0x05, which the host asks for between its
        syncs' answers and for the temperatures) while a command other than M105 runs."""
        if self.printer._autoreport:
            return True
        status = isinstance(reply, replies.HyrelReport) and reply.tag == "ST"
        return status and command_word(command.command) != "M105"

    def _temperatures(self, text: str, line: str) -> bool:
        readings = parse_temperatures(text)
        if not readings:
            return False
        self.printer.temperatures = readings
        self.printer._hub.publish(Temperatures(readings, line))
        return True

    def notice(self, text: str) -> None:
        self.printer._broadcast(Notice(text))

    def action_due(self, action: HostAction) -> None:
        printer = self.printer
        job = printer._job
        if job is not None:
            printer._spawn(_perform(printer, job, action))

    def marker_reached(self, action: HostAction) -> None:
        printer = self.printer
        job = printer._job
        if job is not None:
            # Told at once: a marker reached in the job's last exchange comes before Done.
            job._publish(Action(action.kind, action.message, action.actions, action.position))
            if job.on_action is not None:
                printer._markers.add(printer._spawn(_mark(job, job.on_action, action)))

    def paused(self) -> None:
        printer = self.printer
        job = printer._job
        if job is not None:
            last = job.last
            job._publish(Paused(PauseReason.REQUEST, "", last.position if last else ""))
            printer._set_state(State.PAUSED, "paused")

    def stop_delayed(self, run: Run, reason: str) -> None:
        printer = self.printer
        job = printer._job
        if job is not None:
            pump = printer._pump
            urgent = pump is not None and (pump.breaks_waits or pump.dialect.acks_say_received)
            job._publish(StopDelayed(reason, tuple(printer.heaters_on()), urgent))

    def safe_stop_confirmed(self, command: str) -> None:
        with contextlib.suppress(ValueError):
            self.printer._owed_safe_stop.remove(command)

    def finished(self, run: Run) -> None:
        printer = self.printer
        job, printer._job = printer._job, None
        if printer._wire_log is not None:
            printer._wire_log.close()
            printer._wire_log = None
        pump = printer._pump
        connection_ends = pump is None or pump.dialect.failure is not None
        if run.error is not None:
            # What of the safe stop was not confirmed is owed: it goes first at the next
            # greeting (or, on a link that goes on, as the controller takes it).
            printer._owed_safe_stop = run.owed_safe_stop
        if job is not None:
            job._drop_m0()
            owes = bool(printer._owed_safe_stop) and connection_ends and not run.emergency
            if owes and printer.settings.reconnect and not printer._closing:
                printer._owe(job, run)
            else:
                job._finish(run, *printer._ended(run, connection_ends))
        healthy = pump is not None and pump.dialect.failure is None
        if healthy and (printer.state is State.PRINTING or printer.state is State.PAUSED):
            printer._set_state(State.READY, "the job ended")

    def failed(self, failure: DialectFailed) -> None:
        printer = self.printer
        error = failure_error(failure)
        if failure.kind is FailureKind.NO_ANSWER:
            error = LinkError(printer._no_answer(failure.reason))
        if printer.state is State.CONNECTING:
            # The greeting (or its M115) failed: whoever greets says why.
            printer._fail_waiters(error)
            return
        if failure.kind is FailureKind.RESET:
            printer._hub.publish(Notice("the controller reset; greeting it again"))
        printer._end_connection(error)
        if printer.settings.reconnect and not printer._closing:
            printer._spawn(printer._regreet(failure.reason))
        else:
            # Once what the pump has yet to write (an abort) went: it writes after this.
            printer._loop.call_soon(printer._drop_connection)
            printer._set_state(State.DISCONNECTED, failure.reason)


async def _perform(printer: Printer, job: PrintJob, action: HostAction) -> None:
    """Carry out a host action once everything before it is confirmed."""
    job._publish(Action(action.kind, action.message, action.actions, action.position))
    result: bool | HostError
    try:
        proceed = await job.on_action(action) if job.on_action is not None else True
        if proceed and action.kind is ActionKind.PAUSE:
            job._m0 = printer._loop.create_future()
            job._publish(Paused(PauseReason.M0, action.message, action.position))
            printer._set_state(State.PAUSED, f"M0 at {action.position}")
            await job._m0
        result = proceed
    except HostError as exc:
        result = exc
    except asyncio.CancelledError:
        return  # the job was stopped meanwhile
    except Exception as exc:  # a handler's own failure stops the job, safely
        result = JobError(f"{action.position}: the host action failed ({exc!r})")
    pump = printer._pump
    if pump is not None and printer._job is job:
        pump.action_done(result)
        printer._poke()


async def _mark(job: PrintJob, on_action: ActionHandler, action: HostAction) -> None:
    """Carry out a marker (a snapshot) beside the stream: its failure stops nothing."""
    try:
        await on_action(action)
    except asyncio.CancelledError:
        return
    except Exception as exc:
        job._publish(Notice(f"{action.position}: the host action failed ({exc!r})"))


def _heater_name(kind: str, index: int | None) -> str:
    return kind if index is None else f"{kind} T{index}"


def _clean_command(line: str) -> str:
    if _FRAMED.search(line.split(";", 1)[0]):
        raise UsageError(
            "line numbers and checksums are the host's: send the command alone, "
            "without N<number> and *<checksum>"
        )
    command = clean_line(line, "command")
    if not command:
        raise UsageError("the command is empty")
    if len(command) > MAX_COMMAND_LENGTH:  # Marlin drops the rest: its checksum fails
        raise UsageError(
            f"the command is {len(command)} characters long; "
            f"controllers take at most {MAX_COMMAND_LENGTH}"
        )
    if command_word(command) == "M110":
        raise UsageError("M110 sets line numbers, which the host owns; it cannot be sent")
    return command


class _Connect:
    """``connect(...)``: awaited, a READY printer; with ``async with``, closed at the end."""

    def __init__(self, opening: Callable[[], Coroutine[Any, Any, Printer]]) -> None:
        self._opening = opening
        self._printer: Printer | None = None

    def __await__(self) -> Generator[Any, None, Printer]:
        return self._opening().__await__()

    async def __aenter__(self) -> Printer:
        self._printer = await self._opening()
        return self._printer

    async def __aexit__(self, *exc: object) -> None:
        if self._printer is not None:
            await self._printer.close()


def connect(
    port: str | None = None,
    machine: str | None = None,
    loadout: Path | str | None = None,
    flow: FlowControl | FlowMode | str | None = None,
    config: Path | UserConfig | None = None,
    *,
    baud: int | None = None,
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    reconnect: bool = True,
    reconnect_wait: float = RECONNECT_WAIT,
    poll_interval: float | None = POLL_INTERVAL,
    poll_while_printing: bool = False,
    protocol: str | None = None,
    checksum: bool | None = None,
    fake_log: Path | None = None,
    fake_args: Iterable[str] = (),
    sim: ControllerSettings | None = None,
    line_tap: Callable[[str, bool], None] | None = None,
    on_event: Callable[[PrinterEvent], None] | None = None,
    owe_safe_stop: Iterable[Heater] | None = None,
) -> _Connect:
    """Open a printer session on ``port`` and greet the controller.

    ``port``: a device path, a pyserial URL (``socket://``, ``rfc2217://``), ``auto``
    (the only serial port that looks like a printer board, else a LinkError naming
    them), ``fake`` (the built-in fake on a fresh pty, started and stopped with the
    session) or ``sim`` (the simulator in this process); None: ``$HYREL_PORT``, then the
    configuration's ``[printer] port``, else the fake. ``machine`` and ``loadout``
    choose the profile (else the firmware's M115 answer does), ``flow`` the flow
    control (else the profile's), ``protocol`` the line protocol: ``reprap`` or
    ``hyrel`` (Hyrel's own link; else the profile's, else ``reprap``; the fake and the
    simulator speak it too); ``checksum``: Hyrel's link sends the additive checksum on
    every line (else as the profile says; without it). ``poll_interval``: seconds between
    temperature polls while idle (``poll_while_printing``: while a job prints too), None
    for silence. ``reconnect=False``: a lost port stays
    lost. ``reconnect_wait``: a job whose link failed before its safe stop was confirmed
    ends once the safe stop went after a reconnect, or after this many seconds.
    ``line_tap``: :meth:`Printer.tap_lines` from the greeting's first line on.
    ``on_event``: called at once with each of the session's events (what
    :meth:`Printer.events` yields) from the port's opening on, for the session's life:
    before ``connect()`` returns, an :class:`~repetrel_host.session.events.NoAnswerYet` for each
    greeting that goes again unanswered. It runs on the session's path: it must only take
    note (print a line, set a flag), never block. ``owe_safe_stop``: a safe stop is owed
    from before (a server's restart after its job was cut), for these heaters besides
    those the profile names: it goes first, made whole, once the controller answers
    (:attr:`Printer.owed_safe_stop`).
    """

    async def opening() -> Printer:
        user = config if isinstance(config, UserConfig) else load_user_config(config)
        request = JobRequest(Path(loadout) if loadout is not None else None, machine)
        mode = FlowMode(flow) if isinstance(flow, str) else flow
        link = LinkRequest(
            baud=baud, flow=mode if isinstance(mode, FlowMode) else None, protocol=protocol
        )
        chosen = link_settings(link, explicit_machine(request, user))
        flow_control = flow if isinstance(flow, FlowControl) else chosen.flow
        name = resolve_port(port, user)
        opened = make_link(
            name,
            chosen.baud,
            fake_log=fake_log,
            fake_args=tuple(fake_args),
            sim=sim,
            protocol=chosen.protocol,
        )
        settings = SessionSettings(
            name,
            chosen.baud,
            flow_control,
            reply_timeout,
            reconnect,
            poll_interval,
            chosen.protocol,
            user,
            request,
            chosen.checksum if checksum is None else checksum,
            poll_while_printing,
            reconnect_wait,
        )
        printer = Printer(opened, settings)
        if line_tap is not None:
            printer.tap_lines(line_tap)
        if on_event is not None:
            printer._hub.callbacks.append(on_event)
        if owe_safe_stop is not None:
            printer._heaters.restore(owe_safe_stop)
            printer._owe_whole_safe_stop = True
        try:
            await printer._open()
        except BaseException:
            await printer.close()
            raise
        return printer

    return _Connect(opening)
