"""The printer session: one long-lived connection to one controller.

``connect`` (``repetrel_host.session.connect``) opens the port and hands back a READY
:class:`Printer`, once :func:`open_printer` greeted the controller (M110 and a probe on the
RepRap link, a ping on Hyrel's) and asked M115 who it is. The session then keeps reading:
controller messages and temperatures become events, commands get their replies, jobs stream
one after another on the same numbering, and a vanished port is reopened (with backoff) and
greeted again. It never resumes a job by itself.

All I/O is here: bytes go between a link (``repetrel_host.links``) and the one
pump (``repetrel_host.session.pump``), which drives the dialect; what the pump sees comes
back through its listener (``repetrel_host.session.listener``). Models: zigpy-znp's
``api.py`` (connect, request and wait for the response, reconnect), Klipper's
``serialhdl.py`` (connect with retry, ``send_with_response``), h11's
``start_next_cycle`` (one connection, many exchanges).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import weakref
from collections import deque
from collections.abc import AsyncIterator, Callable, Coroutine, Iterable
from itertools import chain
from pathlib import Path
from typing import Any

from repetrel_host.errors import (
    ControllerError,
    HostError,
    JobError,
    LinkError,
    UsageError,
)
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import HEATING, Heater, HeaterLog, complete_safe_stop
from repetrel_host.links import Link
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects import create_dialect, release_bytes
from repetrel_host.protocol.events import DialectFailed, FailureKind, ProbeKind
from repetrel_host.protocol.reports import Firmware
from repetrel_host.session import history as print_history
from repetrel_host.session.commands import PendingCommand, Reply, clean_command
from repetrel_host.session.connection import (
    LINK_LOST,
    QUIET,
    QUIET_MAX,
    RECONNECT_FIRST,
    RECONNECT_MAX,
    LinkConnection,
)
from repetrel_host.session.events import (
    Message,
    Notice,
    PrinterEvent,
    Resumed,
    State,
    StateChanged,
    Temperatures,
)
from repetrel_host.session.hub import EventFanout
from repetrel_host.session.identify import FIRMWARE_TIMEOUT, Identity, hotend_count
from repetrel_host.session.job import JobItem, JobLine
from repetrel_host.session.listener import PumpListener
from repetrel_host.session.machine_state import (
    KEEPS_THE_JOB_STATE,
    HomeAxes,
    MachineState,
    back_to_job,
)
from repetrel_host.session.motion_state import MotionState
from repetrel_host.session.motion_state import after as motion_after
from repetrel_host.session.owed import OwedSafeStop, delivered, unsafe_stop_error
from repetrel_host.session.planning import (
    JobPlan,
    JobRequest,
    Profile,
    controller_profile,
    history_file,
    plan_job,
    recovery_plan,
)
from repetrel_host.session.planning import safe_stop as safe_stop_for
from repetrel_host.session.print_job import ActionHandler, PrintJob
from repetrel_host.session.pump import (
    CANCEL_DRAIN_TIMEOUT,
    JobRun,
    Pump,
    Summary,
    failure_error,
)
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.targets import with_target
from repetrel_host.session.temperature_watch import TemperatureWatch
from repetrel_host.session.wire import Wire

# The session's log, as before its parts had modules of their own.
log = logging.getLogger("repetrel_host.session.printer")

# How long each line of an owed safe stop may take to be answered after a reconnect.
SAFE_STOP_TIMEOUT = 30.0
# Closing waits this long for the snapshots a job's markers asked for (M790, M791).
MARKER_TIMEOUT = 30.0
# Sent before a job when its report is asked for: reset the metrics, and have M30 send
# the M773 report (Hyrel's diagnostic codes, M772: bit 0 of S).
REPORT_COMMAND = "M772 S1"
FIRST_REPORT_WAIT = 2.0  # s: for the answer to Hyrel's status request (it comes at once)
BACK_TO_JOB_TIMEOUT = 60.0  # s: each command that brings a paused job's machine back


def _state_at(plan: JobPlan, line: int) -> MachineState:
    """The state the file's lines up to source ``line`` leave the machine in."""
    state = MachineState()
    for number, command, _, _ in plan.job.commands():
        if number > line:
            break
        state.apply(number, command)
    return state


class Printer:
    """One long-lived connection to one controller (see the module's docstring)."""

    def __init__(self, link: Link, settings: SessionSettings) -> None:
        self._loop = asyncio.get_running_loop()
        self.link = link
        self.settings = settings
        self.state = State.CONNECTING
        self.state_reason = ""  # why it came to its state, where the session said (a lost port)
        self._identity = Identity()  # who the controller said it is (its firmware)
        self.probe: ProbeKind | None = None
        self.temperatures: dict[str, tuple[float, float | None]] = {}
        # The axes homed and the factors, as the commands the controller ran left them.
        self.motion = MotionState()
        self._wire = Wire(self._loop)
        self._side = _SessionSide(self)
        self._listener = PumpListener(self._side)
        self._temperature_watch = TemperatureWatch(self._side)
        self._ready: asyncio.Future[ProbeKind] | None = None
        self._commands: deque[PendingCommand] = deque()
        self._lock = asyncio.Lock()
        self._job: PrintJob | None = None
        self._last_job: PrintJob | None = None
        # The words of the commands sent during the job's pause that may have moved the
        # machine or changed a mode (jog, home, extrude, T...): resume() comes back first.
        self._paused_words: set[str] = set()
        self._hub: EventFanout[PrinterEvent] = EventFanout()
        self._state_waiters: list[tuple[Callable[[], bool], asyncio.Future[None]]] = []
        self._tasks: set[asyncio.Task[Any]] = set()
        self._markers: weakref.WeakSet[asyncio.Task[None]] = weakref.WeakSet()  # snapshots
        self._reconnecting: asyncio.Task[None] | None = None
        self._closing = False
        # The safe stop still owed (a failed job's, or from before this session), and the
        # job that waits for it to go (after a reconnect) before it ends.
        self._owed = OwedSafeStop()
        self._heaters = HeaterLog()  # every heater the session's commands set
        self._line_taps: list[Callable[[str, bool], None]] = []
        self._watchers: list[Callable[[], None]] = []

    @property
    def firmware(self) -> Firmware | None:
        """What the controller's M115 said it is (or its greeting), None when unknown."""
        return self._identity.firmware

    @property
    def port(self) -> str:
        return self.link.port

    @property
    def protocol(self) -> str:
        """The link's protocol: "reprap" or "hyrel"."""
        return self.settings.protocol

    @property
    def job(self) -> PrintJob | None:
        """The job streaming now, if any."""
        return self._job

    @property
    def last_job(self) -> PrintJob | None:
        """The job started last, streaming or ended (after a failure: its recovery_line)."""
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
        return complete_safe_stop(commands, self._heaters, hotend_count(self.firmware))

    @property
    def owed_safe_stop(self) -> list[str]:
        """Safe-stop commands a job could not send (its link failed), or owed from before
        the session (``connect(owe_safe_stop=...)``), still to go: they go first once the
        controller answers again, after what it still holds or waits for is dropped or
        ended where the link can (Hyrel's abort and end-wait, Marlin's M108)."""
        return self.safe_stop if self._owed.whole else list(self._owed.commands)

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
        pump = self._wire.pump
        if pump is not None:
            pump.dialect.on_first_send = self._first_send
        return lambda: self._line_taps.remove(callback)

    def _first_send(self, command: str, tag: object, own: bool, _number: int | None) -> None:
        own = own or (isinstance(tag, PendingCommand) and tag.own)
        for tap in self._line_taps:
            tap(command, own)

    def tap_wire(self, callback: Callable[[bool, bytes], None]) -> Callable[[], None]:
        """Call ``callback(sent, data)`` with every piece of data written (``sent``) or
        received, as it goes; returns what removes the tap. For logs and test reports."""
        self._wire.taps.append(callback)
        return lambda: self._wire.taps.remove(callback)

    @property
    def wire_tail(self) -> deque[tuple[bool, bytes]] | None:
        """The wire's latest pieces, ``(sent, data)``, while a reader sets a bounded deque
        here and takes it now and then (the push socket's terminal); None: none kept."""
        return self._wire.tail

    @wire_tail.setter
    def wire_tail(self, tail: deque[tuple[bool, bytes]] | None) -> None:
        self._wire.tail = tail

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
        pump = self._wire.pump
        return pump.dialect.stats if pump is not None else None

    # --- commands ---------------------------------------------------------------

    async def command(self, line: str, *, timeout: float | None = None) -> Reply:
        """Send one command through the numbered, checksummed, resend-safe path and
        return the controller's reply. M112 goes out at once, unnumbered, and stops a job;
        M108 goes out at once too (Marlin's emergency parser ends a heat wait with it)."""
        command = clean_command(line)
        word = command_word(command)
        if word == "M112":
            self.emergency_stop()
            return Reply(command, [], "")
        if word == "M108":
            pump = self._wire.pump
            if pump is not None and pump.controller_holds:
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
            reply = await self._command(command, timeout)
            if word in HEATING and reply.ok and not self.temperatures:
                # The target is set: a report that does not come only leaves it unread.
                with contextlib.suppress(HostError, TimeoutError):
                    await self._first_report(timeout)
            return reply

    async def _first_report(self, timeout: float | None) -> None:
        """Nothing reported yet to set a target in: a report now (Hyrel's status request,
        else M105), so that the target reads back as its command returns, as it does once
        there are readings."""
        pump = self._wire.pump
        wait = min(timeout or FIRST_REPORT_WAIT, FIRST_REPORT_WAIT)
        if pump is None or not pump.dialect.request_status():
            await self._command("M105", wait, own=True)
            return
        self._wire.drive()
        async with asyncio.timeout(wait):
            while not self.temperatures:
                await asyncio.sleep(0.02)

    async def _command(self, command: str, timeout: float | None, own: bool = False) -> Reply:
        pending = self._send_command(command, own)
        # Shielded: a timeout leaves it pending, so that its late lines are still its own.
        return await asyncio.wait_for(asyncio.shield(pending.future), timeout)

    def _send_command(self, command: str, own: bool = False) -> PendingCommand:
        pump = self._wire.pump
        if pump is None:
            raise LinkError(f"{self.port} is not connected")
        pending = PendingCommand(command, self._loop.create_future(), own)
        self._commands.append(pending)
        pump.command(command, pending)
        self._wire.drive()
        return pending

    def _take_identity_line(self, text: str) -> None:
        """A line that says which firmware this is (M115's ``FIRMWARE_NAME:`` and ``Cap:``
        lines), whichever command it came with or after: a slow controller's answer still
        decides, once it comes."""
        known = self.firmware
        found = self._identity.heard(text)
        if found is None:
            return
        late = self.state is not State.CONNECTING and (known is None or known.name != found.name)
        self._use_firmware()
        # Its M155, if it has one, also when it said who it is only once a job was under
        # way: after this dispatch (not inside it), on this connection only.
        self._loop.call_soon(self._temperature_watch.late_autoreport, self._wire.pump)
        if late:
            self._hub.publish(Notice(f"the controller said who it is: {found.name}"))

    def _use_firmware(self) -> None:
        """What the pump takes from the firmware: its hotends, whether M108 ends a wait."""
        pump, firmware = self._wire.pump, self.firmware
        if pump is not None:
            pump.hotends = hotend_count(firmware)
            pump.breaks_waits = (
                firmware is not None
                and firmware.can("EMERGENCY_PARSER")
                and not pump.dialect.acks_say_received  # Hyrel's link aborts instead
            )

    def _check_can_command(self) -> None:
        state = self.state
        if state is State.PRINTING:
            raise UsageError(
                "a job is printing: commands wait until it ends or is paused (pause() first)"
            )
        if state is not State.READY and state is not State.PAUSED:
            raise LinkError(f"{self.port} is not connected (the session is {state.value})")
        pump = self._wire.pump
        if state is State.PAUSED and pump is not None and pump.controller_holds:
            raise UsageError(
                "the controller holds the paused job's lines (Hyrel's link): a command "
                "would wait behind them; it can go after resume() or cancel()"
            )

    @property
    def pending(self) -> list[str]:
        """Commands sent or queued that still wait for their reply (an M109 heating...)."""
        return [pending.command for pending in self._commands]

    def _urgent(self, command: str) -> None:
        pump = self._wire.pump
        if pump is None:
            raise LinkError(f"{self.port} is not connected")
        pump.dialect.send_urgent(command_word(command))  # as emergency parsers read it
        self._wire.drive()

    def emergency_stop(self) -> None:
        """M112 at once, unnumbered: a job ends with a ControllerError. Then, where a
        heater may be on, the safe stop's heater-off lines go once the controller answers
        again (Marlin's halts until a reset; Hyrel's documents do not say what its M112
        does)."""
        pump = self._wire.pump
        if pump is not None:  # the job ends first: not a line of it may follow the M112
            error = ControllerError(
                "stopped by an emergency stop (M112): the controller may need a reset; its "
                "heaters are turned off once it answers again"
            )
            pump.emergency_stop(self._loop.time(), error)
        self._urgent("M112")
        self._owed.after_emergency(self.safe_stop if self.heaters_on() else [])
        self._spawn(self._send_owed_safe_stop())  # a halted one fails it: at the greeting

    # --- jobs -------------------------------------------------------------------

    def plan(
        self,
        path: Path | str,
        *,
        header: bool = True,
        from_line: int | None = None,
        recovery_home: HomeAxes = HomeAxes.XY,
    ) -> JobPlan:
        """What :meth:`print` would stream for ``path``: profile, header, safe stop; with
        ``from_line``, recovered there (the preamble first: :func:`planning.recovery_plan`)."""
        request = JobRequest(self.settings.request.loadout, self.settings.request.machine, header)
        plan = plan_job(Path(path), request, self.settings.user, self.firmware)
        return plan if from_line is None else recovery_plan(plan, from_line, recovery_home)

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
        ``from_line``: recover a failed print there (see :meth:`plan`; a failed job's
        :attr:`PrintJob.recovery_line` says where). ``command_line``: hyrel-send's arguments,
        kept with the progress so that ``--history-list`` offers a killed run's recovery.
        """
        if self._job is not None or self.state is State.PRINTING or self.state is State.PAUSED:
            raise UsageError("a job is already running on this printer")
        self._check_can_command()
        # Planning (a recovery reads up to its line) and the check before the first line
        # read the file: a thread's work, not the event loop's (every printer's stream).
        if isinstance(job, JobPlan):
            plan = (
                job if from_line is None else await asyncio.to_thread(recovery_plan, job, from_line)
            )
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
            pump = self._wire.pump
            assert pump is not None
            path = self._open_history(plan, history)
            items: Iterable[JobItem] = plan.items(checker, pump.dialect.pause_command)
            if report:
                items = chain([JobLine(0, 0, REPORT_COMMAND, 0, "report")], items)
            run = JobRun(items, plan.safe_stop, started_at=self._loop.time())
            if plan.recovery is not None:  # progress by bytes goes on from the skipped part
                run.offset = plan.recovery.start_offset
            print_job = PrintJob(self, self._side, plan, run, on_action, path)
            if path is not None and print_history.parse_run(path) is not None:
                # Its progress in the run's record, written before the first line goes.
                print_job.record_progress(
                    print_history.ProgressKeeper(
                        path,
                        plan.job.path,
                        command_line,
                        self.port,
                        print_job.started,
                        pump.dialect.last_sent,
                    )
                )
            self._job = self._last_job = print_job
            self._paused_words.clear()  # an earlier job's pause is not this one's
            pump.begin(run)
            self._set_state(State.PRINTING, plan.job.name)
            self._wire.drive()
        if path is not None and print_history.parse_run(path) is not None:
            self._prune_history(path)  # a history folder's: never a folder of other files
        return print_job

    def _warn(self, text: str) -> None:
        self._broadcast(Notice(text))

    def _broadcast(self, event: Notice | Message) -> None:
        """To the session's subscribers and the running job's."""
        self._hub.publish(event)
        if self._job is not None:
            self._job.publish(event)

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
            # Unbuffered: what is written reaches the OS at once (Wire.write), so that a killed
            # host leaves every byte the port got in the stream.
            self._wire.log = path.open("wb", buffering=0)
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
        pump = self._wire.pump
        if pump is not None:
            pump.pause(at_layer_end)
            self._wire.drive()
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
        job.publish(Resumed())
        if job.m0 is not None:
            m0, job.m0 = job.m0, None
            m0.set_result(None)
        elif (pump := self._wire.pump) is not None:
            pump.resume()
            self._wire.drive()

    async def _back_to_job(self, job: PrintJob) -> None:
        """Commands moved the machine during the pause (or changed its modes): back to where
        the job stood, in its modes, before its next line (:func:`machine_state.back_to_job`). The
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
        if self._owed.waits_for(job):
            self._give_up_owed("given up before the controller answered again")
            return True
        if job is not self._job or self._wire.pump is None:
            return False
        job.drop_m0()
        if self.state is State.PAUSED:
            self._set_state(State.PRINTING, "stopping")
        abandoned = self._wire.pump.stop(self._loop.time(), error)
        self._changed()  # stopping
        self._wire.drive()
        return abandoned

    # --- opening, greeting, reconnecting -------------------------------------

    async def _open(self) -> None:
        """Open the link and greet the controller: READY, or a HostError."""
        self._set_state(State.CONNECTING, f"opening {self.port}")
        self._ready = self._loop.create_future()
        await self.link.open(
            lambda: LinkConnection(self._connection_opened, self._wire.received, self._lost)
        )
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
            self._wire.drop_connection()
            raise
        await self._send_owed_safe_stop()
        self._set_state(State.READY, "greeted")
        self._temperature_watch.start_polling(self._spawn)

    async def _send_owed_safe_stop(self) -> None:
        """What a failed job could not send: heaters off before anything else. Each line
        is owed until the controller confirms it; the job that waits for them ends then."""
        if self._owed.whole:  # the profile is known now: made whole once
            self._owed.make_whole(self.safe_stop)
        owed = list(self._owed.commands)
        if not owed:
            return
        self._tell_owing(Notice(f"sending the safe stop the interrupted job missed: {owed}"))
        for command in owed:
            try:
                await self._command(command, SAFE_STOP_TIMEOUT)
            except (HostError, TimeoutError):
                return  # the rest goes at the next greeting
            self._owed.confirmed(command)
        if self._owed.waiting is not None:
            job, run = self._owed.waiting
            ended = self._delivered(run)
            self._owed.stop_waiting()
            job.finish(run, *ended)

    def _tell_owing(self, event: Notice) -> None:
        self._hub.publish(event)
        if self._owed.waiting is not None:
            self._owed.waiting[0].publish(event)

    def _wait_for_owed_safe_stop(self, job: PrintJob, run: JobRun) -> None:
        """The job's link failed before its safe stop was confirmed: it ends once the safe
        stop went after a reconnect, or after ``reconnect_wait`` seconds without one."""
        wait = self.settings.reconnect_wait
        timer = self._loop.call_later(
            wait, self._give_up_owed, f"the controller did not answer again within {wait:g} s"
        )
        self._owed.wait(job, run, timer)
        self._tell_owing(
            Notice(
                f"{run.error}. The safe stop did not go: trying to reach the controller again "
                f"to send it (for up to {wait:g} s)"
            )
        )

    def _give_up_owed(self, why: str) -> None:
        """The job waiting for its safe stop ends without it (it stays owed: it goes at
        the session's next greeting, should there be one)."""
        if self._owed.waiting is None:
            return
        job, run = self._owed.waiting
        self._owed.stop_waiting()
        error = unsafe_stop_error(
            f"{run.error}; the safe stop could not be sent ({why})", self.heaters_on()
        )
        job.finish(run, error, None)

    def _delivered(self, run: JobRun) -> tuple[HostError | None, Summary | None]:
        """How a job whose safe stop went after a reconnect ended (:func:`delivered`), told."""
        if run.cancelled_stop:
            self._tell_owing(Notice("the safe stop completed once the controller answered again"))
        return delivered(run, self._loop.time())

    async def _identify(self) -> None:
        self._temperature_watch.new_connection()
        await self._identity.ask(
            lambda command: self._send_command(command, own=True).future, self._loop
        )
        self._use_firmware()
        asked = self._temperature_watch.ask_autoreport()
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

    def _connection_opened(self, connection: LinkConnection) -> None:
        if self._closing:
            if connection.transport is not None:
                connection.transport.close()
            return
        self._wire.connection = connection
        if self._clear_for_safe_stop():
            self._spawn(self._start_pump_when_quiet())
        else:
            self._start_pump()

    def _clear_for_safe_stop(self) -> bool:
        """With a safe stop owed, before the greeting: what the controller still holds or
        waits for must not hold the safe stop (nor the greeting) up (:func:`release_bytes`).
        True when it wrote."""
        if not self._owed.any:
            return False
        self._tell_owing(Notice("a safe stop is owed: ending what the controller holds first"))
        self._wire.write(release_bytes(self.settings.protocol))
        return True

    async def _until_quiet(self) -> None:
        """Until the controller has said nothing for QUIET s (at most QUIET_MAX): late
        answers to what went before must not be taken for the greeting's."""
        quiet_since = self._loop.time()
        while self._loop.time() - quiet_since < QUIET_MAX:
            wait = self._wire.last_data_at + QUIET - self._loop.time()
            if wait <= 0:
                break
            await asyncio.sleep(wait)

    async def _start_pump_when_quiet(self) -> None:
        self._wire.last_data_at = self._loop.time()
        await self._until_quiet()
        if self._wire.connection is not None and not self._closing and self._wire.pump is None:
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
        self._wire.start(Pump(dialect, self._listener, self._heaters))

    async def _regreet(self, reason: str) -> None:
        """Greet again on the same port (after a reset, or a failure)."""
        if self._wire.connection is None or self._closing:
            return
        self._set_state(State.CONNECTING, reason)
        # Late answers to what went before must not be taken for the new greeting's.
        await self._until_quiet()
        if self._wire.connection is None or self._closing:
            return
        if self._clear_for_safe_stop():
            self._wire.last_data_at = self._loop.time()
            await self._until_quiet()
            if self._wire.connection is None or self._closing:
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

    # --- I/O ------------------------------------------------------------------

    def _lost(self, connection: LinkConnection, exc: Exception | None) -> None:
        if connection is not self._wire.connection:
            return
        log.debug("connection lost: %s", exc)
        self._wire.connection = None
        self._end_connection(LinkError(LINK_LOST))
        if self._closing:
            return
        self._set_state(State.DISCONNECTED, LINK_LOST)
        if self.settings.reconnect and self._reconnecting is None:
            self._reconnecting = self._spawn(self._reconnect())

    def _end_connection(self, error: HostError) -> None:
        """The pump is gone: the job fails naming its last line, commands fail."""
        pump = self._wire.stop()
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

    def _fail_commands(self, commands: Iterable[PendingCommand], error: HostError) -> None:
        for pending in list(commands):
            if not pending.future.done():
                pending.future.set_exception(error)
                pending.future.exception()
            with contextlib.suppress(ValueError):
                self._commands.remove(pending)

    # --- what the pump tells ----------------------------------------------------

    def _job_ended(self, run: JobRun) -> None:
        """The running job's run ended: how it is reported, and what is owed after it."""
        job, self._job = self._job, None
        self._wire.close_log()
        pump = self._wire.pump
        connection_ends = pump is None or pump.dialect.failure is not None
        if run.error is not None:
            # What of the safe stop was not confirmed is owed: it goes first at the next
            # greeting (or, on a link that goes on, as the controller takes it).
            self._owed.commands = run.owed_safe_stop
        if job is not None:
            job.drop_m0()
            owes = bool(self._owed.commands) and connection_ends and not run.emergency
            if owes and self.settings.reconnect and not self._closing:
                self._wait_for_owed_safe_stop(job, run)
            else:
                job.finish(run, *self._owed.run_ended(run, connection_ends, self.heaters_on))
        healthy = pump is not None and pump.dialect.failure is None
        if healthy and (self.state is State.PRINTING or self.state is State.PAUSED):
            self._set_state(State.READY, "the job ended")

    def _link_failed(self, failure: DialectFailed) -> None:
        """The dialect stopped: the greeting fails, or the connection ends (and is greeted
        again, where the session reconnects)."""
        error = failure_error(failure)
        if failure.kind is FailureKind.NO_ANSWER:
            error = LinkError(self._no_answer(failure.reason))
        if self.state is State.CONNECTING:
            # The greeting (or its M115) failed: whoever greets says why.
            self._fail_waiters(error)
            return
        if failure.kind is FailureKind.RESET:
            self._hub.publish(Notice("the controller reset; greeting it again"))
        self._end_connection(error)
        if self.settings.reconnect and not self._closing:
            self._spawn(self._regreet(failure.reason))
        else:
            # Once what the pump has yet to write (an abort) went: it writes after this.
            self._loop.call_soon(self._wire.drop_connection)
            self._set_state(State.DISCONNECTED, failure.reason)

    # --- state and events ----------------------------------------------------

    def _set_state(self, state: State, reason: str = "") -> None:
        if state is self.state:
            return
        previous, self.state = self.state, state
        self.state_reason = reason
        if state in (State.CONNECTING, State.DISCONNECTED) or previous is State.READY:
            self.motion = MotionState()  # the controller may be reset; a job moves it
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
        if job is not None and self._wire.pump is not None:
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
        self._wire.drop_connection()
        await self._loop.run_in_executor(None, self.link.close)
        self._set_state(State.CLOSED, "closed")
        self._hub.close()

    async def __aenter__(self) -> Printer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _SessionSide:
    """What the session's own parts may do to it: the pump's listener
    (:class:`~repetrel_host.session.listener.ListenerSession`) and its jobs
    (:class:`~repetrel_host.session.print_job.JobSession`); kept off the public Printer."""

    def __init__(self, printer: Printer) -> None:
        self._printer = printer

    # --- for the pump's listener

    @property
    def port(self) -> str:
        return self._printer.port

    @property
    def settings(self) -> SessionSettings:
        return self._printer.settings

    @property
    def pump(self) -> Pump | None:
        return self._printer._wire.pump

    @property
    def job(self) -> PrintJob | None:
        return self._printer._job

    @property
    def pending_commands(self) -> deque[PendingCommand]:
        return self._printer._commands

    @property
    def autoreporting(self) -> bool:
        return self._printer._temperature_watch.autoreport

    @property
    def state(self) -> State:
        return self._printer.state

    @property
    def firmware(self) -> Firmware | None:
        return self._printer.firmware

    def send_own_command(self, command: str) -> PendingCommand:
        return self._printer._send_command(command, own=True)

    async def poll_command(self, command: str, timeout: float) -> Reply | None:
        printer = self._printer
        if printer._lock.locked() or printer._commands:
            return None  # a caller's command goes first: no poll this time
        async with printer._lock:
            return await printer._command(command, timeout, own=True)

    @property
    def owed(self) -> OwedSafeStop:
        return self._printer._owed

    def publish(self, event: PrinterEvent) -> None:
        self._printer._hub.publish(event)

    def broadcast(self, event: Notice | Message) -> None:
        self._printer._broadcast(event)

    def greeted(self, probe: ProbeKind, identity: str) -> None:
        printer = self._printer
        printer._identity.greeting = identity
        ready = printer._ready
        if ready is not None and not ready.done():
            ready.set_result(probe)

    def identity_heard(self, text: str) -> None:
        self._printer._take_identity_line(text)

    def temperatures_heard(
        self, readings: dict[str, tuple[float, float | None]], line: str
    ) -> None:
        self._printer.temperatures = readings
        self._printer._hub.publish(Temperatures(readings, line))

    def command_confirmed(self, command: str) -> None:
        printer = self._printer
        hyrel = None
        if printer.settings.protocol == "hyrel":
            machine = printer.profile.machine
            hyrel = machine.firmware if machine is not None else "v5"
        readings = with_target(printer.temperatures, command, printer._heaters.tool, hyrel)
        if readings is not None:
            self.temperatures_heard(readings, command)
        moved = motion_after(printer.motion, command, hyrel is not None)
        if moved is not None and moved != printer.motion:
            printer.motion = moved
            printer._changed()

    def fail_commands(self, commands: Iterable[PendingCommand], error: HostError) -> None:
        self._printer._fail_commands(commands, error)

    def changed(self) -> None:
        self._printer._changed()

    def set_state(self, state: State, reason: str) -> None:
        self._printer._set_state(state, reason)

    def heaters_on(self) -> list[str]:
        return self._printer.heaters_on()

    def spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        return self._printer._spawn(coroutine)

    def spawn_marker(self, coroutine: Coroutine[Any, Any, None]) -> None:
        printer = self._printer
        printer._markers.add(printer._spawn(coroutine))

    def drive_pump(self) -> None:
        self._printer._wire.drive()

    def job_ended(self, run: JobRun) -> None:
        self._printer._job_ended(run)

    def link_failed(self, failure: DialectFailed) -> None:
        self._printer._link_failed(failure)

    # --- for its jobs

    def stop_job(self, job: PrintJob, error: HostError | None) -> bool:
        return self._printer._stop_job(job, error)

    def waits_for_safe_stop(self, job: PrintJob) -> bool:
        return self._printer._owed.waits_for(job)

    @property
    def last_sent(self) -> object | None:
        pump = self._printer._wire.pump
        return pump.dialect.last_sent if pump else None


def _heater_name(kind: str, index: int | None) -> str:
    return kind if index is None else f"{kind} T{index}"


async def open_printer(
    link: Link,
    settings: SessionSettings,
    *,
    line_tap: Callable[[str, bool], None] | None = None,
    on_event: Callable[[PrinterEvent], None] | None = None,
    owe_safe_stop: Iterable[Heater] | None = None,
) -> Printer:
    """A session on ``link`` (not yet opened), opened and greeted: READY, or closed again
    and the HostError raised (``connect``'s work once it chose the link and settings)."""
    printer = Printer(link, settings)
    if line_tap is not None:
        printer.tap_lines(line_tap)
    if on_event is not None:
        printer._hub.callbacks.append(on_event)
    if owe_safe_stop is not None:
        printer._heaters.restore(owe_safe_stop)
        printer._owed.whole = True
    try:
        await printer._open()
    except BaseException:
        await printer.close()
        raise
    return printer
