"""What the pump tells the session, turned into the session's doing: commands get their
lines and replies, controller lines become messages and temperatures, a job's resends,
pauses, host actions and markers become its events, and its end or a link's failure goes
to the session.

The listener reaches the session only through :class:`ListenerSession`, the short list of
what it may do there (the session, ``repetrel_host.session.printer``, hands it one).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Coroutine, Iterable
from typing import Any, Protocol

from repetrel_host.errors import ControllerError, HostError, JobError, UsageError
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import HEATING
from repetrel_host.protocol import replies
from repetrel_host.protocol.events import DialectFailed, GreetingRetry, ProbeKind
from repetrel_host.protocol.reports import parse_temperatures
from repetrel_host.session.commands import PendingCommand, Reply
from repetrel_host.session.events import (
    Action,
    Message,
    NoAnswerYet,
    Notice,
    Paused,
    PauseReason,
    PrinterEvent,
    Resend,
    State,
    StopDelayed,
)
from repetrel_host.session.job import ActionKind, HostAction, JobLine
from repetrel_host.session.motion_state import MOTION_WORDS
from repetrel_host.session.owed import OwedSafeStop
from repetrel_host.session.print_job import ActionHandler, PrintJob
from repetrel_host.session.pump import JobRun, Listener, Pump
from repetrel_host.session.settings import SessionSettings

# The session's log, as before its parts had modules of their own.
log = logging.getLogger("repetrel_host.session.printer")
# The commands whose acknowledgement changes what the session keeps of the controller:
# heater targets (M104, M140...: targets.py), homing, motors off and the speed and flow
# factors (motion_state.py); and their first letters and digits, a cheap first look at
# each of a job's lines.
CONFIRMED_WORDS = frozenset({*HEATING, *MOTION_WORDS})
_MAY_BE_CONFIRMED = tuple(
    {word[:2] for word in CONFIRMED_WORDS} | {w[:2].lower() for w in CONFIRMED_WORDS}
)


def confirms(command: str) -> bool:
    """``command``'s acknowledgement may change what the session keeps (CONFIRMED_WORDS)."""
    return command.startswith(_MAY_BE_CONFIRMED) and command_word(command) in CONFIRMED_WORDS


class ListenerSession(Protocol):
    """What the pump's listener may do to the session it serves."""

    @property
    def port(self) -> str: ...

    @property
    def settings(self) -> SessionSettings: ...

    @property
    def pump(self) -> Pump | None:
        """The pump of the connection, None between a failure and the next greeting."""
        ...

    @property
    def job(self) -> PrintJob | None:
        """The job streaming now, if any."""
        ...

    @property
    def pending_commands(self) -> deque[PendingCommand]:
        """Commands sent that wait for their reply, oldest first."""
        ...

    @property
    def autoreporting(self) -> bool:
        """The controller reports temperatures itself (M155 took)."""
        ...

    @property
    def owed(self) -> OwedSafeStop:
        """The safe stop still owed."""
        ...

    def publish(self, event: PrinterEvent) -> None:
        """To the session's subscribers."""

    def broadcast(self, event: Notice | Message) -> None:
        """To the session's subscribers and the running job's."""

    def greeted(self, probe: ProbeKind, identity: str) -> None:
        """The greeting is over (``identity``: what the controller said of itself)."""

    def identity_heard(self, text: str) -> None:
        """A line that says which firmware this is."""

    def temperatures_heard(
        self, readings: dict[str, tuple[float, float | None]], line: str
    ) -> None:
        """The controller reported its temperatures (in ``line``)."""

    def command_confirmed(self, command: str) -> None:
        """The controller acknowledged having run ``command``, which may set a heater's
        target or the motion state (:data:`CONFIRMED_WORDS` names the commands that may)."""

    def fail_commands(self, commands: Iterable[PendingCommand], error: HostError) -> None:
        """Those commands fail with ``error``."""

    def changed(self) -> None:
        """The job's phase changed: the session's watchers are told."""

    def set_state(self, state: State, reason: str) -> None:
        """The session's state is now ``state``."""

    def heaters_on(self) -> list[str]:
        """The heaters that may be on."""
        ...

    def spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        """JobRun ``coroutine`` as one of the session's tasks."""
        ...

    def spawn_marker(self, coroutine: Coroutine[Any, Any, None]) -> None:
        """JobRun ``coroutine`` (a marker's snapshot), which closing waits for."""

    def drive_pump(self) -> None:
        """Let the pump write what it can now."""

    def job_ended(self, run: JobRun) -> None:
        """The running job's run ended (see :meth:`Listener.finished`)."""

    def link_failed(self, failure: DialectFailed) -> None:
        """The dialect stopped (see :meth:`Listener.failed`)."""


class PumpListener(Listener):
    """What the pump tells the session, kept off the public Printer."""

    def __init__(self, session: ListenerSession) -> None:
        self.session = session

    def greeting_retry(self, retry: GreetingRetry) -> None:
        session = self.session
        baud = session.settings.baud
        event = NoAnswerYet(session.port, baud, retry.attempt, retry.attempts, retry.waited)
        log.debug("%s at %d baud: %s", session.port, baud, event.text)
        session.publish(event)

    def ready(self, probe: ProbeKind, identity: str) -> None:
        self.session.greeted(probe, identity)

    def command_done(self, tag: object, data: str) -> None:
        if not isinstance(tag, PendingCommand):
            return
        session = self.session
        with contextlib.suppress(ValueError):
            session.pending_commands.remove(tag)
        if data:
            self._temperatures(data, f"ok {data}")
        if confirms(tag.command):  # read back before its caller has the reply
            session.command_confirmed(tag.command)
        if not tag.future.done():
            tag.future.set_result(Reply(tag.command, tag.lines, f"ok {data}" if data else "ok"))

    def acknowledged(self, line: JobLine) -> None:
        # A job's M104 or G28 too, where the ok says the line ran (RepRap's); Hyrel's ack
        # says it arrived, and the line may wait there behind the moves before it.
        if confirms(line.command):
            pump = self.session.pump
            if pump is not None and not pump.dialect.acks_say_received:
                self.session.command_confirmed(line.command)

    def commands_dropped(self, tags: list[object]) -> None:
        error = UsageError("the command was not sent: the job it waited behind was stopped")
        self.session.fail_commands((t for t in tags if isinstance(t, PendingCommand)), error)

    def command_refused(self, tag: object, reason: str) -> None:
        if isinstance(tag, PendingCommand):
            self.session.fail_commands([tag], ControllerError(reason))

    def read_to_end(self) -> None:
        self.session.changed()  # what is left is the controller's to run: finishing

    def resend(self, line: JobLine) -> None:
        job = self.session.job
        if job is not None:
            job.publish(Resend(line.position))

    def message(self, text: str, reply: replies.Reply) -> None:
        if isinstance(reply, replies.Busy | replies.Wait):
            return  # keepalives
        job = self.session.job
        if job is not None and isinstance(reply, replies.HyrelReport):
            for line in job.reports.feed(text):  # the M773 report is the job's
                self._message(line, replies.classify(line))
            return
        self._message(text, reply)

    def _message(self, text: str, reply: replies.Reply) -> None:
        session = self.session
        if text.startswith("Cap:") or "FIRMWARE_NAME:" in text:
            session.identity_heard(text)
        reported = self._temperatures(text, text)
        commands = session.pending_commands
        if commands and not (reported and self._unasked(reply, commands[0])):
            commands[0].lines.append(text)
            return
        # A Hyrel notice (an M-code ran) tells what ran; it is no message for the user.
        notice = isinstance(reply, replies.HyrelReport) and reply.tag == "MC"
        if not reported and not notice:
            session.broadcast(Message(text))

    def _unasked(self, reply: replies.Reply, command: PendingCommand) -> bool:
        """Whether a temperature report is no part of ``command``'s reply: the firmware's
        own reports, or Hyrel's status report (0x05, which the host asks for between its
        syncs' answers and for the temperatures) while a command other than M105 runs."""
        if self.session.autoreporting:
            return True
        status = isinstance(reply, replies.HyrelReport) and reply.tag == "ST"
        return status and command_word(command.command) != "M105"

    def _temperatures(self, text: str, line: str) -> bool:
        readings = parse_temperatures(text)
        if not readings:
            return False
        self.session.temperatures_heard(readings, line)
        return True

    def notice(self, text: str) -> None:
        self.session.broadcast(Notice(text))

    def action_due(self, action: HostAction) -> None:
        session = self.session
        job = session.job
        if job is not None:
            session.spawn(_perform(session, job, action))

    def marker_reached(self, action: HostAction) -> None:
        session = self.session
        job = session.job
        if job is not None:
            # Told at once: a marker reached in the job's last exchange comes before Done.
            job.publish(Action(action.kind, action.message, action.actions, action.position))
            if job.on_action is not None:
                session.spawn_marker(_mark(job, job.on_action, action))

    def paused(self) -> None:
        session = self.session
        job = session.job
        if job is not None:
            last = job.last
            job.publish(Paused(PauseReason.REQUEST, "", last.position if last else ""))
            session.set_state(State.PAUSED, "paused")

    def stop_delayed(self, run: JobRun, reason: str) -> None:
        session = self.session
        job = session.job
        if job is not None:
            pump = session.pump
            urgent = pump is not None and (pump.breaks_waits or pump.dialect.acks_say_received)
            job.publish(StopDelayed(reason, tuple(session.heaters_on()), urgent))

    def safe_stop_confirmed(self, command: str) -> None:
        self.session.owed.confirmed(command)

    def finished(self, run: JobRun) -> None:
        self.session.job_ended(run)

    def failed(self, failure: DialectFailed) -> None:
        self.session.link_failed(failure)


async def _perform(session: ListenerSession, job: PrintJob, action: HostAction) -> None:
    """Carry out a host action once everything before it is confirmed."""
    job.publish(Action(action.kind, action.message, action.actions, action.position))
    result: bool | HostError
    try:
        proceed = await job.on_action(action) if job.on_action is not None else True
        if proceed and action.kind is ActionKind.PAUSE:
            job.m0 = asyncio.get_running_loop().create_future()
            job.publish(Paused(PauseReason.M0, action.message, action.position))
            session.set_state(State.PAUSED, f"M0 at {action.position}")
            await job.m0
        result = proceed
    except HostError as exc:
        result = exc
    except asyncio.CancelledError:
        return  # the job was stopped meanwhile
    except Exception as exc:  # a handler's own failure stops the job, safely
        result = JobError(f"{action.position}: the host action failed ({exc!r})")
    pump = session.pump
    if pump is not None and session.job is job:
        pump.action_done(result)
        session.drive_pump()


async def _mark(job: PrintJob, on_action: ActionHandler, action: HostAction) -> None:
    """Carry out a marker (a snapshot) beside the stream: its failure stops nothing."""
    try:
        await on_action(action)
    except asyncio.CancelledError:
        return
    except Exception as exc:
        job.publish(Notice(f"{action.position}: the host action failed ({exc!r})"))
