"""The safe stop still owed: what a stopped or failed job (its link lost, its controller
gone quiet) could not get confirmed, or a whole safe stop owed from before the session (a
server's restart); and the job that waits for it to go after a reconnect before it ends.

The session (``repetrel_host.session.printer``) sends it first once the controller answers
again.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from repetrel_host.errors import HostError, SafeStopError
from repetrel_host.gcode.heaters import off_lines
from repetrel_host.session.print_job import PrintJob
from repetrel_host.session.pump import JobRun, Outcome, Summary


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
