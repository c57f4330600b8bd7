"""The safe stop still owed: what a stopped or failed job (its link lost, its controller
gone quiet) could not get confirmed, or a whole safe stop owed from before the session (a
server's restart); and the job that waits for it to go after a reconnect before it ends.

:class:`OwedStopSender` sends it first once the controller answers again (at each greeting,
after what the controller still holds is released), and ends the job that waits for it.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from typing import Protocol

from repetrel_host.errors import HostError, SafeStopError
from repetrel_host.gcode.heaters import off_lines
from repetrel_host.protocol.dialects import release_bytes
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.events import Notice, PrinterEvent
from repetrel_host.session.print_job import PrintJob
from repetrel_host.session.pump import JobRun, Outcome, Summary
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.wire import Wire

# How long each line of an owed safe stop may take to be answered after a reconnect.
SAFE_STOP_TIMEOUT = 30.0


class OwedSafeStop:
    """Safe-stop commands still to go, and the job (with its run) that waits for them."""

    def __init__(self) -> None:
        # The safe stop a job that failed (the link, the controller) could not send.
        self.commands: list[str] = []
        # A safe stop owed from before this session (a server's restart): the whole of it,
        # made once the controller said who it is, for the heaters kept from before.
        self.whole = False
        # The job that waits for it to go (after a reconnect) before it ends, and the timer
        # that ends it without.
        self.waiting: tuple[PrintJob, JobRun] | None = None
        self._timer: asyncio.TimerHandle | None = None

    @property
    def any(self) -> bool:
        """Something is owed (before the greeting: what the controller holds goes first)."""
        return bool(self.commands) or self.whole

    def make_whole(self, safe_stop: list[str]) -> None:
        """The profile is known: a whole safe stop owed becomes its commands, once."""
        if self.whole:
            self.commands = safe_stop
            self.whole = False

    def after_emergency(self, safe_stop: list[str]) -> None:
        """An emergency stop went: what a controller does then is its own (Marlin halts
        with its heaters off until a reset; Hyrel's documents say nothing), so the safe
        stop's heater-off lines are owed, and nothing else (no move)."""
        self.commands = off_lines(safe_stop)
        self.whole = False

    def confirmed(self, command: str) -> None:
        """The controller confirmed one of the commands: no longer owed."""
        with contextlib.suppress(ValueError):
            self.commands.remove(command)

    def waits_for(self, job: PrintJob) -> bool:
        """``job`` is the one waiting for the safe stop to go."""
        return self.waiting is not None and self.waiting[0] is job

    def wait(self, job: PrintJob, run: JobRun, timer: asyncio.TimerHandle) -> None:
        """``job`` ends once the safe stop went, or when ``timer`` fires."""
        self.waiting = (job, run)
        self._timer = timer

    def stop_waiting(self) -> None:
        """No job waits any more (it ends now, one way or the other)."""
        self.waiting = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def run_ended(
        self, run: JobRun, connection_ends: bool, heaters_on: Callable[[], list[str]]
    ) -> tuple[HostError | None, Summary | None]:
        """How a run that just ended is reported (a reconnect aside); ``heaters_on``: the
        heaters that may be on, for a stop not confirmed."""
        error = run.error
        if error is None or run.emergency:
            return error, run.summary
        if isinstance(error, SafeStopError):  # abandoned by the caller
            going = "; they still go as the controller takes them, while the session is open"
            going = "" if connection_ends else going
            return unsafe_stop_error(f"{error}{going}", heaters_on()), None
        if self.commands and connection_ends:
            return unsafe_stop_error(f"{error}; the safe stop was not sent", heaters_on()), None
        return error, None


def unsafe_stop_error(cause: str, heaters_on: list[str]) -> SafeStopError:
    """The sentence for a stop not confirmed: what may be on, and what to do."""
    on = f"; heaters that may be on: {', '.join(heaters_on)}" if heaters_on else ""
    return SafeStopError(f"{cause}{on}; check the machine (its power switch stops it)")


def delivered(run: JobRun, now: float) -> tuple[HostError | None, Summary | None]:
    """How a job whose safe stop went after a reconnect ended: cancelled, if that is how it
    was stopping; else its failure, saying the safe stop went."""
    if run.cancelled_stop:
        stats = run.resends_before, run.retransmissions_before
        seconds = now - run.started_at
        return None, Summary(Outcome.CANCELLED, run.lines, seconds, *stats)
    assert run.error is not None
    went = "the safe stop went once the controller answered again"
    return type(run.error)(f"{run.error}; {went}"), None


class OwingSession(Protocol):
    """What sending the owed safe stop needs of the session."""

    @property
    def settings(self) -> SessionSettings: ...

    @property
    def safe_stop(self) -> list[str]:
        """The profile's safe stop, for every heater the session set."""
        ...

    def heaters_on(self) -> list[str]:
        """The heaters that may be on."""
        ...

    def publish(self, event: PrinterEvent) -> None:
        """To the session's subscribers."""


class OwedStopSender:
    """Sends the safe stop still owed (:attr:`owed`) once the controller answers, and ends
    the job that waits for it, or gives up on it."""

    def __init__(self, session: OwingSession, commands: CommandQueue, wire: Wire) -> None:
        self._session = session
        self._commands = commands
        self._wire = wire
        self.owed = OwedSafeStop()

    def release(self) -> bool:
        """With a safe stop owed, before the greeting: what the controller still holds or
        waits for must not hold the safe stop (nor the greeting) up (:func:`release_bytes`).
        True when it wrote."""
        if not self.owed.any:
            return False
        self.tell(Notice("a safe stop is owed: ending what the controller holds first"))
        self._wire.write(release_bytes(self._session.settings.protocol))
        return True

    async def send(self) -> None:
        """What a failed job could not send: heaters off before anything else. Each line
        is owed until the controller confirms it; the job that waits for them ends then."""
        owed = self.owed
        if owed.whole:  # the profile is known now: made whole once
            owed.make_whole(self._session.safe_stop)
        commands = list(owed.commands)
        if not commands:
            return
        self.tell(Notice(f"sending the safe stop the interrupted job missed: {commands}"))
        for command in commands:
            try:
                await self._commands.ask(command, SAFE_STOP_TIMEOUT)
            except (HostError, TimeoutError):
                return  # the rest goes at the next greeting
            owed.confirmed(command)
        if owed.waiting is not None:
            job, run = owed.waiting
            ended = self._delivered(run)
            owed.stop_waiting()
            job.finish(run, *ended)

    def after_emergency(self) -> None:
        """An emergency stop went: where a heater may be on, the safe stop's heater-off
        lines are owed (:meth:`OwedSafeStop.after_emergency`)."""
        session = self._session
        self.owed.after_emergency(session.safe_stop if session.heaters_on() else [])

    def tell(self, event: Notice) -> None:
        """To the session's subscribers and the job that waits for the safe stop."""
        self._session.publish(event)
        if self.owed.waiting is not None:
            self.owed.waiting[0].publish(event)

    def wait_for(self, job: PrintJob, run: JobRun) -> None:
        """The job's link failed before its safe stop was confirmed: it ends once the safe
        stop went after a reconnect, or after ``reconnect_wait`` seconds without one."""
        wait = self._session.settings.reconnect_wait
        timer = self._wire.loop.call_later(
            wait, self.give_up, f"the controller did not answer again within {wait:g} s"
        )
        self.owed.wait(job, run, timer)
        self.tell(
            Notice(
                f"{run.error}. The safe stop did not go: trying to reach the controller again "
                f"to send it (for up to {wait:g} s)"
            )
        )

    def give_up(self, why: str) -> None:
        """The job waiting for its safe stop ends without it (it stays owed: it goes at
        the session's next greeting, should there be one)."""
        if self.owed.waiting is None:
            return
        job, run = self.owed.waiting
        self.owed.stop_waiting()
        error = unsafe_stop_error(
            f"{run.error}; the safe stop could not be sent ({why})", self._session.heaters_on()
        )
        job.finish(run, error, None)

    def _delivered(self, run: JobRun) -> tuple[HostError | None, Summary | None]:
        """How a job whose safe stop went after a reconnect ended (:func:`delivered`), told."""
        if run.cancelled_stop:
            self.tell(Notice("the safe stop completed once the controller answered again"))
        return delivered(run, self._wire.loop.time())
