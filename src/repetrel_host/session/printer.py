"""The printer session: one long-lived connection to one controller.

``connect`` (``repetrel_host.session.connect``) opens the port and hands back a READY
:class:`Printer`, once :func:`open_printer` greeted the controller (M110 and a probe on the
RepRap link, a ping on Hyrel's) and asked M115 who it is. The session then keeps reading:
controller messages and temperatures become events, commands get their replies, jobs stream
one after another on the same numbering, and a vanished port is reopened (with backoff) and
greeted again. It never resumes a job by itself.

This module is the session's table of contents: :class:`Printer`'s public face, and the
parts that do its work, each owning its own state. Bytes go between a link
(``repetrel_host.links``) and the one pump (:mod:`.pump`), which drives the dialect, over
the wire (:mod:`.wire`); what the pump sees comes back through its listener
(:mod:`.listener`). The connection's greeting is :mod:`.greeting`'s, its opening, loss and
reconnecting :mod:`.reconnect`'s, the safe stop still owed :mod:`.owed`'s, the commands
waiting for their replies :mod:`.command_queue`'s, the jobs :mod:`.job_control`'s, the
temperature reports :mod:`.temperature_watch`'s. Models: zigpy-znp's ``api.py`` (connect,
request and wait for the response, reconnect), Klipper's ``serialhdl.py`` (connect with
retry, ``send_with_response``), h11's ``start_next_cycle`` (one connection, many
exchanges).
"""

from __future__ import annotations

import asyncio
import contextlib
import weakref
from collections import deque
from collections.abc import AsyncIterator, Callable, Coroutine, Iterable
from pathlib import Path
from typing import Any

from repetrel_host.errors import ControllerError, HostError, LinkError
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import HEATING, Heater, HeaterLog, complete_safe_stop
from repetrel_host.links import Link
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.events import DialectFailed, ProbeKind
from repetrel_host.protocol.reports import Firmware
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.commands import PendingCommand, Reply, clean_command
from repetrel_host.session.events import (
    Message,
    Notice,
    PrinterEvent,
    State,
    StateChanged,
    Temperatures,
)
from repetrel_host.session.greeting import Greeter
from repetrel_host.session.hub import EventFanout
from repetrel_host.session.identify import hotend_count
from repetrel_host.session.job_control import JobControl
from repetrel_host.session.listener import PumpListener
from repetrel_host.session.machine_state import HomeAxes
from repetrel_host.session.motion_state import MotionState
from repetrel_host.session.motion_state import after as motion_after
from repetrel_host.session.owed import OwedSafeStop, OwedStopSender
from repetrel_host.session.planning import (
    JobPlan,
    JobRequest,
    Profile,
    controller_profile,
    plan_job,
    recovery_plan,
)
from repetrel_host.session.planning import safe_stop as safe_stop_for
from repetrel_host.session.print_job import ActionHandler, PrintJob
from repetrel_host.session.pump import JobRun, Pump
from repetrel_host.session.reconnect import Reconnector
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.targets import heaters_on, with_target
from repetrel_host.session.temperature_watch import TemperatureWatch
from repetrel_host.session.wire import Wire

# Closing waits this long for the snapshots a job's markers asked for (M790, M791).
MARKER_TIMEOUT = 30.0


class Printer:
    """One long-lived connection to one controller (see the module's docstring)."""

    def __init__(self, link: Link, settings: SessionSettings) -> None:
        self._loop = asyncio.get_running_loop()
        self.link = link
        self.settings = settings
        self.state = State.CONNECTING
        self.state_reason = ""  # why it came to its state, where the session said (a lost port)
        self.probe: ProbeKind | None = None
        self.temperatures: dict[str, tuple[float, float | None]] = {}
        # The axes homed and the factors, as the commands the controller ran left them.
        self.motion = MotionState()
        self._hub: EventFanout[PrinterEvent] = EventFanout()
        self._heaters = HeaterLog()  # every heater the session's commands set
        self._state_waiters: list[tuple[Callable[[], bool], asyncio.Future[None]]] = []
        self._watchers: list[Callable[[], None]] = []
        self._tasks: set[asyncio.Task[Any]] = set()
        self._markers: weakref.WeakSet[asyncio.Task[None]] = weakref.WeakSet()  # snapshots
        # Its parts (see the module), each reaching the session through its inner side.
        side = _SessionSide(self)
        self._wire = Wire(self._loop)
        self._commands = CommandQueue(self._wire, link.port)
        self._owing = OwedStopSender(side, self._commands, self._wire)
        self._temperature_watch = TemperatureWatch(side, self._commands)
        self._greeter = Greeter(
            side,
            self._wire,
            self._commands,
            PumpListener(side),
            self._heaters,
            self._temperature_watch,
        )
        self._reconnector = Reconnector(
            side,
            link,
            self._wire,
            self._greeter,
            self._owing,
            self._commands,
            self._temperature_watch,
        )
        self._jobs = JobControl(self, side, self._wire, self._commands, self._owing)

    @property
    def firmware(self) -> Firmware | None:
        """What the controller's M115 said it is (or its greeting), None when unknown."""
        return self._greeter.firmware

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
        return self._jobs.job

    @property
    def last_job(self) -> PrintJob | None:
        """The job started last, streaming or ended (after a failure: its recovery_line)."""
        return self._jobs.last_job

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
        owed = self._owing.owed
        return self.safe_stop if owed.whole else list(owed.commands)

    @property
    def heater_log(self) -> HeaterLog:
        """Every heater (and fan) the session's commands set: what a safe stop turns off."""
        return self._heaters

    def heaters_on(self) -> list[str]:
        """The heaters that may be on: set above zero by a command the session sent (and
        not turned off since, as far as the controller confirmed), or reported with a
        target above zero."""
        return heaters_on(self._heaters, self.temperatures)

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
        return self._wire.tap_lines(callback)

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
            self._jobs.check_can_break_wait()
            self._commands.urgent(command)
            return Reply(command, [], "")
        self._jobs.check_can_command()
        async with self._commands.lock:
            self._jobs.check_can_command()
            self._jobs.before_command(word)
            reply = await self._commands.ask(command, timeout)
            if word in HEATING and reply.ok and not self.temperatures:
                # The target is set: a report that does not come only leaves it unread.
                with contextlib.suppress(HostError, TimeoutError):
                    await self._temperature_watch.first_report(timeout)
            return reply

    @property
    def pending(self) -> list[str]:
        """Commands sent or queued that still wait for their reply (an M109 heating...)."""
        return [pending.command for pending in self._commands.waiting]

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
        self._commands.urgent("M112")
        self._owing.after_emergency()
        self._spawn(self._owing.send())  # a halted one fails it: at the greeting

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
        return await self._jobs.start(
            job,
            header=header,
            force=force,
            history=history,
            on_action=on_action,
            on_warning=on_warning,
            report=report,
            from_line=from_line,
            command_line=command_line,
        )

    async def pause(self, at_layer_end: bool = False) -> None:
        """Stop feeding the job; returns once it is PAUSED: on Hyrel's link once the
        controller was told to hold it at the end of the move (or of the layer:
        ``at_layer_end``), on the RepRap link once every line sent is confirmed."""
        await self._jobs.pause(at_layer_end)

    async def resume(self) -> None:
        """Go on with a paused job (paused by :meth:`pause` or by an M0)."""
        await self._jobs.resume()

    async def cancel(self) -> None:
        """Stop the job with the safe-stop sequence; returns once it went."""
        await self._jobs.cancel()

    # --- state, tasks, events -------------------------------------------------

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

    def _changed(self) -> None:
        for watcher in self._watchers:
            watcher()

    def _spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = self._loop.create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _broadcast(self, event: Notice | Message) -> None:
        """To the session's subscribers and the running job's."""
        self._hub.publish(event)
        job = self._jobs.job
        if job is not None:
            job.publish(event)

    # --- closing ----------------------------------------------------------------

    async def close(self) -> None:
        """Stop a running job with the safe stop first, then close the port."""
        if self.state is State.CLOSED:
            return
        await self._jobs.stop_for_close()
        self._owing.give_up("the session was closed")
        markers = {task for task in self._markers if not task.done()}
        if markers:  # a snapshot the job's last lines asked for is still taken
            await asyncio.wait(markers, timeout=MARKER_TIMEOUT)
        self._reconnector.closing = True
        for task in list(self._tasks):
            task.cancel()
        self._reconnector.end(LinkError("the session is closed"))
        await self._wire.close_connection()
        await self._loop.run_in_executor(None, self.link.close)
        self._set_state(State.CLOSED, "closed")
        self._hub.close()

    async def __aenter__(self) -> Printer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _SessionSide:
    """What the session's own parts may do to it (the pump's listener, the temperature
    watch, the greeting, the reconnecting, the owed safe stop, the jobs: each names what it
    needs in a Protocol of its own); kept off the public Printer."""

    def __init__(self, printer: Printer) -> None:
        self._printer = printer

    @property
    def port(self) -> str:
        return self._printer.port

    @property
    def settings(self) -> SessionSettings:
        return self._printer.settings

    @property
    def state(self) -> State:
        return self._printer.state

    @property
    def firmware(self) -> Firmware | None:
        return self._printer.firmware

    @property
    def temperatures(self) -> dict[str, tuple[float, float | None]]:
        return self._printer.temperatures

    @property
    def probe(self) -> ProbeKind | None:
        return self._printer.probe

    @probe.setter
    def probe(self, probe: ProbeKind | None) -> None:
        self._printer.probe = probe

    @property
    def safe_stop(self) -> list[str]:
        return self._printer.safe_stop

    def heaters_on(self) -> list[str]:
        return self._printer.heaters_on()

    @property
    def pump(self) -> Pump | None:
        return self._printer._wire.pump

    @property
    def job(self) -> PrintJob | None:
        return self._printer._jobs.job

    @property
    def pending_commands(self) -> deque[PendingCommand]:
        return self._printer._commands.waiting

    @property
    def autoreporting(self) -> bool:
        return self._printer._temperature_watch.autoreport

    @property
    def owed(self) -> OwedSafeStop:
        return self._printer._owing.owed

    @property
    def reconnects(self) -> bool:
        return self._printer._reconnector.reconnects

    def set_state(self, state: State, reason: str) -> None:
        self._printer._set_state(state, reason)

    async def until(self, ready: Callable[[], bool]) -> None:
        await self._printer._until(ready)

    def changed(self) -> None:
        self._printer._changed()

    def spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        return self._printer._spawn(coroutine)

    def spawn_marker(self, coroutine: Coroutine[Any, Any, None]) -> None:
        printer = self._printer
        printer._markers.add(printer._spawn(coroutine))

    def publish(self, event: PrinterEvent) -> None:
        self._printer._hub.publish(event)

    def broadcast(self, event: Notice | Message) -> None:
        self._printer._broadcast(event)

    def drive_pump(self) -> None:
        self._printer._wire.drive()

    # --- what the pump's listener hears

    def greeted(self, probe: ProbeKind, identity: str) -> None:
        self._printer._greeter.greeted(probe, identity)

    def identity_heard(self, text: str) -> None:
        self._printer._greeter.heard(text)

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
        self._printer._commands.fail(commands, error)

    def job_ended(self, run: JobRun) -> None:
        self._printer._jobs.ended(run)

    def link_failed(self, failure: DialectFailed) -> None:
        self._printer._reconnector.failed(failure)


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
        printer._owing.owed.whole = True
    try:
        await printer._reconnector.open()
    except BaseException:
        await printer.close()
        raise
    return printer
