"""The one pump between a dialect and what feeds it: a job's lines, single commands, the
safe stop. Sans-IO like the dialect: no asyncio, no port, no clock.

Whoever drives it (the session on a real link, the loopback on simulated time, the
framed preview) does three things: hands it received bytes (:meth:`Pump.receive`),
calls :meth:`Pump.poke` after anything happened and writes the bytes it returns,
and calls :meth:`Pump.timeout` once :attr:`Pump.deadline` has passed. What happens
is told to a :class:`Listener`.

A job is a :class:`JobRun`: its lines are read while the controller works, a host
action (M0, M792...) waits until every line before it is confirmed, and a stop
drops what is queued (what the controller holds too, where the link can) and sends
the safe-stop sequence ahead of anything else. A pause holds the controller where the
link can (Hyrel's), else stops feeding and lets the controller run what it has.

A stop is over only once the controller confirmed its safe stop: lines of the job it
still runs meanwhile are counted as they are acknowledged (so that the record and the
recovery point stay true), a heat wait among them is broken where the firmware can
(Marlin's emergency parser: ``M108``, again for each wait), and a stop held up (by a wait
nothing can break, or for long) is told at once, never ended as if it had gone.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from enum import Enum
from itertools import chain

from repetrel_host.errors import (
    ControllerError,
    HostError,
    JobError,
    LinkError,
    ProtocolError,
    SafeStopError,
    UsageError,
)
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import WAITS, HeaterLog, complete_safe_stop, turns_off
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Dialect
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    DialectFailed,
    FailureKind,
    GreetingRetry,
    LineAcknowledged,
    LineRefused,
    Notice,
    ProbeKind,
    ResendRequested,
)
from repetrel_host.session.job import ActionKind, HostAction, JobItem, JobLine

# A stop whose safe stop is not confirmed this long after it began is told as held up
# (it goes on: the safe stop goes whenever the controller takes it). Closing a session
# waits this long for a stop under way.
CANCEL_DRAIN_TIMEOUT = 30.0
STOP_PATIENCE = 10.0
# M108 goes again this often while a heat wait holds a stop (it may come before the wait
# began, and Marlin forgets it then).
BREAK_REPEAT = 1.0
SAFE_STOP_SOURCE = "safe stop"
_MOVES = frozenset({"G0", "G1", "G2", "G3"})
_HEATER_OR_TOOL = ("M1", "T")  # M104, M109, M140, M190, M141, M191; T1 (a tool change)


class Outcome(Enum):
    COMPLETED = "completed"
    CANCELLED = "cancelled"


@dataclass(frozen=True, slots=True)
class Summary:
    """How a job ended."""

    outcome: Outcome
    lines: int  # job lines acknowledged
    seconds: float
    resends: int
    retransmissions: int


class Listener:
    """Told what the pump sees; override what you need."""

    def ready(self, probe: ProbeKind, identity: str) -> None:
        """The greeting is over: lines flow (``identity``: what the controller said of
        itself in the greeting, or "")."""

    def greeting_retry(self, retry: GreetingRetry) -> None:
        """No answer to the greeting yet: it goes again now (before :meth:`ready`)."""

    def acknowledged(self, line: JobLine) -> None:
        """A line of the running job (or its header or safe stop) was acknowledged."""

    def command_done(self, tag: object, data: str) -> None:
        """A command sent with :meth:`Pump.command` was acknowledged; ``data`` follows its ok."""

    def commands_dropped(self, tags: list[object]) -> None:
        """Commands that will never go: the stream failed or stopped before they went out."""

    def command_refused(self, tag: object, reason: str) -> None:
        """The controller will not run a command it received (``reason``: why)."""

    def read_to_end(self) -> None:
        """The running job was read to its end: what is left is on its way (once a job,
        and again after a pause held lines back)."""

    def resend(self, line: JobLine) -> None:
        """The controller asked for a job line again."""

    def message(self, text: str, reply: replies.Reply) -> None:
        """A controller line that is not flow control (echo:, busy, temperatures...)."""

    def notice(self, text: str) -> None:
        """Something worth knowing that does not stop anything."""

    def action_due(self, action: HostAction) -> None:
        """Every line before ``action`` is confirmed: do it, then call :meth:`Pump.action_done`."""

    def marker_reached(self, action: HostAction) -> None:
        """The line before a marker (:attr:`HostAction.is_marker`) was acknowledged; the
        stream goes on meanwhile."""

    def paused(self) -> None:
        """A pause asked for is reached: every line sent so far is confirmed."""

    def stop_delayed(self, run: JobRun, reason: str) -> None:
        """The safe stop of a stopping run is held up (``reason``: by what); it still goes
        as soon as the controller takes it."""

    def safe_stop_confirmed(self, command: str) -> None:
        """A safe-stop line of a run that already ended was confirmed (an abandoned stop's
        lines still go when the controller takes them)."""

    def finished(self, run: JobRun) -> None:
        """The run ended: :attr:`JobRun.outcome` or :attr:`JobRun.error` says how."""

    def failed(self, failure: DialectFailed) -> None:
        """The dialect stopped: the connection needs a new greeting (or a new link)."""


class JobRun:
    """One job streaming through the pump: its lines, its progress, how it ends."""

    def __init__(
        self, items: Iterable[JobItem], safe_stop: Sequence[str] = (), started_at: float = 0.0
    ) -> None:
        self.items: Iterator[JobItem] = iter(items)
        self.resends_before = self.retransmissions_before = 0  # the connection's, at the start
        self.safe_stop = list(safe_stop)
        self.started_at = started_at
        self.exhausted = False
        self.error: HostError | None = None  # reported once the safe stop is acknowledged
        self.stopping = False  # no more job lines: cancelled, refused or failed
        self.barrier: HostAction | None = None  # waiting for every earlier line's ok
        # Markers, each due once the lines read before it are acknowledged: ``fed`` is
        # the index of the last job line read, ``header_fed`` the header lines read.
        self.markers: deque[tuple[int, int, HostAction]] = deque()
        self.fed = 0
        self.header_fed = 0
        self.action_running = False
        self.pause_requested = False
        self.paused = False
        self.held = False  # the controller holds the job (a pause on Hyrel's link)
        self.stop_deadline: float | None = None  # when a stop not confirmed is told as late
        self.stop_requests = 0
        self.safe_stop_queued = False  # the stop began: its safe stop went to the dialect
        self.safe_stop_completed = False  # made whole for the heaters on (complete_safe_stop)
        self.safe_stop_lines: list[JobLine] = []  # queued at the stop, not yet confirmed
        self.safe_stop_unsent: list[JobLine] = []  # of those, never on the wire (a failure)
        self.breaking: JobLine | None = None  # the heat wait M108 went for, and when
        self.broke_at = 0.0
        self.held_by: JobLine | None = None  # the wait told as holding the stop up
        self.cancelled_stop = False  # stopped without an error, then the stream failed
        self.emergency = False  # ended by M112: only its heater-off lines are owed
        # Progress: the job line with the highest index acknowledged so far.
        self.lines = 0
        self.offset = 0
        self.last: JobLine | None = None
        # The last job line known to have run, where an acknowledgement says only that it
        # was received (Hyrel's link); elsewhere an acknowledged line is taken to run.
        self.ran: JobLine | None = None
        self.acks_say_received = False
        # The last job line on the wire when the run ended (None: none, or a stop's line
        # went after it): lines after the last acknowledged, up to it, may have run.
        self.last_sent: JobLine | None = None
        self.sent_before: object | None = None  # the dialect's last_sent as the job began
        self.ran_before: object | None = None  # what had run when the job began: not its
        self.header_acknowledged = 0
        self.outcome: Outcome | None = None
        self.summary: Summary | None = None
        self.finished = False

    @property
    def safe_stop_missing(self) -> list[str]:
        """Safe-stop commands not acknowledged (all of them before a stop began)."""
        if not self.safe_stop_queued:
            return list(self.safe_stop)
        return [line.command for line in self.safe_stop_lines]

    @property
    def owed_safe_stop(self) -> list[str]:
        """What of the safe stop the controller must still be sent, should this stream end
        now: the lines it did not confirm, but for a move already on the wire (it may
        have run: a second lift would lift twice). None after an emergency stop (the
        session owes what it leaves: ``OwedSafeStop.after_emergency``)."""
        if self.emergency:
            return []
        if not self.safe_stop_queued:
            return list(self.safe_stop)
        unsent = [id(line) for line in self.safe_stop_unsent]
        return [
            line.command
            for line in self.safe_stop_lines
            if command_word(line.command) not in _MOVES or id(line) in unsent
        ]

    @property
    def recovery_line(self) -> int | None:
        """The source line to recover from: the one after the last job line known to have run
        (:attr:`ran` on Hyrel's link, else :attr:`last`); None when none did, or all did."""
        line = self.ran if self.acks_say_received else self.last
        if line is None or (self.exhausted and line.index == self.fed):
            return None
        return line.source_line + 1

    def where(self) -> str:
        """The last line the controller acknowledged, for failure messages."""
        line = self.last
        if line is None:
            return "no line of the job was acknowledged"
        return (
            f"the last line the controller acknowledged is {line.position} "
            f"(command {line.index} of the job, {line.command})"
        )

    def naming_where(self, error: HostError) -> HostError:
        """``error`` with where the job stood (:meth:`where`) after it."""
        return type(error)(f"{error}; {self.where()}")


class Pump:
    """Feeds ``dialect`` from the current run and commands; reports to ``listener``.

    ``heaters`` is told every command sent (the safe stop turns off every heater in it);
    ``hotends``: how many the controller has; ``breaks_waits``: ``M108`` ends a heat wait
    (Marlin's emergency parser), so that a stop need not wait for it."""

    def __init__(
        self,
        dialect: Dialect,
        listener: Listener | None = None,
        heaters: HeaterLog | None = None,
    ) -> None:
        self.dialect = dialect
        self.listener = listener or Listener()
        self.run: JobRun | None = None
        self.heaters = heaters if heaters is not None else HeaterLog()
        self.hotends = 1
        self.breaks_waits = False

    # --- driving ------------------------------------------------------------

    def start(self, now: float) -> bytes:
        """Greet the controller; returns the first bytes to write."""
        self.dialect.start(now)
        return self.poke(now)

    def receive(self, data: bytes, now: float) -> None:
        self.dialect.receive_data(data, now)

    def timeout(self, now: float) -> None:
        run = self.run
        if run is not None and run.stop_deadline is not None and now >= run.stop_deadline:
            run.stop_deadline = None  # told once; the stop goes on
            self._tell_late(run)
        self.dialect.handle_timeout(now)

    @property
    def deadline(self) -> float | None:
        deadline = self.dialect.next_deadline()
        run = self.run
        if run is not None:
            for due in (run.stop_deadline, run.broke_at + BREAK_REPEAT if run.breaking else None):
                if due is not None:
                    deadline = due if deadline is None else min(deadline, due)
        return deadline

    def poke(self, now: float) -> bytes:
        """Feed, take the bytes to write, read ahead, and act on what happened."""
        out = b""
        while True:
            self._feed()
            out += self.dialect.data_to_send(now)
            # Read the next lines now, while the controller works, not once its ok is here.
            self._feed()
            if not self._dispatch(now) or not self._settle(now):
                return out

    # --- jobs and commands ---------------------------------------------------

    def begin(self, run: JobRun) -> None:
        if self.run is not None:
            raise UsageError("a job is already running on this connection")
        self.run = run
        run.ran_before = self.dialect.last_ran
        run.sent_before = self.dialect.last_sent
        stats = self.dialect.stats
        run.resends_before = stats.resend_requests
        run.retransmissions_before = stats.retransmissions

    def command(self, command: str, tag: object) -> None:
        """Send one command outside any job; :meth:`Listener.command_done` gets ``tag``
        once the controller ran it (its reply is complete then)."""
        self.heaters.note(command)
        self.dialect.send(command, tag, confirm=True)

    def pause(self, at_layer_end: bool = False) -> None:
        """Stop feeding job lines; :meth:`Listener.paused` once the controller holds the
        job (Hyrel's link: at the end of the move, or layer) or ran every line sent.

        Lines read ahead but not yet on the wire wait for :meth:`resume`."""
        run = self.run
        if run is None or run.stopping or run.pause_requested:
            return
        run.pause_requested = True
        held: list[JobItem] = []
        for command, tag in self.dialect.cancel_pending():
            if isinstance(tag, JobLine):
                held.append(tag)
                if tag.index == 0:
                    run.header_fed -= 1  # read again on resume
            else:
                self.dialect.send(command, tag, confirm=True)  # not the job's: it goes
        if run.barrier is not None and not run.action_running:
            held.append(run.barrier)  # after the lines before it, as in the file
            run.barrier = None
        run.items = chain(held, run.items)
        if held:
            run.exhausted = False  # the lines held back are still to be read
        if self.dialect.hold(at_layer_end):
            run.held = run.paused = True
            self.listener.paused()

    def resume(self) -> None:
        run = self.run
        if run is not None:
            if run.held:
                self.dialect.end_wait()
            run.pause_requested = run.paused = run.held = False

    @property
    def controller_holds(self) -> bool:
        """The controller holds the job's lines (a pause, or its own M0, on Hyrel's link):
        a command would wait behind them."""
        run = self.run
        return run is not None and (
            run.held
            or (
                run.action_running
                and run.barrier is not None
                and run.barrier.kind is ActionKind.PAUSE
                and self.dialect.pause_command is not None
            )
        )

    def action_done(self, proceed: bool | HostError) -> None:
        """The host action is over: go on, stop the job (False), or stop it with an error."""
        run = self.run
        if run is None or run.barrier is None:
            return
        if isinstance(proceed, HostError) or not proceed:
            if isinstance(proceed, HostError):
                run.error = proceed
            self._stop_feeding(run)
            return
        waiting = self.controller_holds  # at its own M0
        run.barrier = None
        run.action_running = False
        if waiting:
            self.dialect.end_wait()

    def stop(self, now: float, error: HostError | None = None) -> bool:
        """Stop the job: the safe-stop sequence goes ahead of anything not yet sent.

        A second call abandons the safe stop and ends the job at once; returns True then.
        """
        run = self.run
        if run is None:
            return False
        run.stop_requests += 1
        if run.stop_requests > 1:
            # Nothing missing: every line went (on Hyrel's link: received), not known to run.
            missing = ", ".join(run.safe_stop_missing) or "that it ran"
            cause = f" (the job had stopped: {run.error})" if run.error is not None else ""
            awaited = self.dialect.awaiting
            held = awaited[1] if awaited is not None else None
            if isinstance(held, JobLine) and held.source != SAFE_STOP_SOURCE:
                cause += (
                    f"; the controller still holds the job's lines from {held.position} on, "
                    "which run unless it is reset"
                )
            self._finish(
                run,
                SafeStopError(
                    f"the safe stop was abandoned before the controller confirmed {missing}{cause}"
                ),
                now,
            )
            return True
        if error is not None and run.error is None:
            run.error = error
        self._stop_feeding(run)
        run.stop_deadline = now + STOP_PATIENCE
        self._break_waits(run, now)
        return False

    def abort(self, now: float, error: HostError) -> None:
        """End the job at once with ``error``: nothing more goes, not even the safe stop
        (the link is gone, or an emergency stop was sent)."""
        run = self.run
        if run is not None:
            run.cancelled_stop = run.stopping and run.error is None
            run.stopping = True
            self._drop_pending()
            self._finish(run, error, now)

    def emergency_stop(self, now: float, error: HostError) -> None:
        """M112 went: the job ends with ``error``; only the safe stop's heater-off lines
        are owed (the controller's own stop is its own)."""
        run = self.run
        if run is not None:
            run.emergency = True
        self.abort(now, error)

    # --- inside ---------------------------------------------------------------

    def _feed(self) -> None:
        """Queue job lines while the dialect wants them, up to a host action."""
        run = self.run
        if run is None:
            return
        dialect = self.dialect
        while (
            dialect.wants_lines
            and not run.stopping
            and run.barrier is None
            and not run.pause_requested
            and not run.exhausted
        ):
            try:
                item = next(run.items)
            except StopIteration:
                run.exhausted = True
                self.listener.read_to_end()
                break
            except HostError as exc:
                # A line that cannot go: the lines before it still do, then the safe stop.
                run.error = exc
                run.exhausted = True
                break
            except Exception as exc:  # the file could not be read on: stop, safely
                run.error = JobError(f"the job could not be read on ({exc!r})")
                run.exhausted = True
                break
            if isinstance(item, JobLine):
                if item.index:
                    run.fed = item.index
                else:
                    run.header_fed += 1
                if item.command.startswith(_HEATER_OR_TOOL):  # a test, not a parse, a line
                    self.heaters.note(item.command)
                dialect.send(item.command, item)
            elif not item.is_marker:
                run.barrier = item
            else:
                run.markers.append((run.fed, run.header_fed, item))
                self._markers_due(run)
        if run.barrier is not None or run.exhausted or run.stopping or run.pause_requested:
            dialect.request_sync()  # nothing more for now: have the controller confirm it all

    def _dispatch(self, now: float) -> bool:
        """Hand the dialect's events on; False once it failed."""
        listener = self.listener
        dialect = self.dialect
        if self.run is not None:
            self._note_ran(self.run)
        while (event := dialect.next_event()) is not None:
            if isinstance(event, LineAcknowledged):
                tag = event.tag
                if isinstance(tag, JobLine):
                    self._acknowledged(tag)
                else:
                    self.heaters.note(event.command, confirmed=True)
                    listener.command_done(tag, event.data)
            elif isinstance(event, ControllerMessage):
                named = event.tag
                if isinstance(named, JobLine):  # the line it names, by its number
                    listener.message(f"{event.text} ({named.position})", event.reply)
                else:
                    listener.message(event.text, event.reply)
            elif isinstance(event, ResendRequested):
                if isinstance(event.tag, JobLine):
                    listener.resend(event.tag)
            elif isinstance(event, ControllerReady):
                listener.ready(event.probe, event.identity)
            elif isinstance(event, GreetingRetry):
                listener.greeting_retry(event)
            elif isinstance(event, Notice):
                listener.notice(event.text)
            elif isinstance(event, LineRefused):
                self._refused(event, now)
            elif isinstance(event, DialectFailed):
                run = self.run
                self._drop_pending()  # first: what never went is known before the run ends
                if run is not None:
                    run.cancelled_stop = run.stopping and run.error is None
                    self._finish(run, failure_error(event, run), now)
                listener.failed(event)
                return False
        if self.run is not None and self.run.stopping:
            self._break_waits(self.run, now)
        return True

    def _refused(self, event: LineRefused, now: float) -> None:
        """A line that will not run: the job stops there, its safe stop first."""
        tag, run = event.tag, self.run
        where = f" (at {tag.position})" if isinstance(tag, JobLine) else ""
        if run is not None:
            error = ControllerError(f"{event.reason}{where}")
            if run.stopping:  # a safe-stop line: the rest of it still goes
                run.error = run.error or error
            else:
                self.stop(now, error)
        elif tag is not None:
            self.listener.command_refused(tag, event.reason)

    def _acknowledged(self, line: JobLine) -> None:
        if line.command.startswith("M1"):  # M104, M140...: confirmed, a heater may be off
            self.heaters.note(line.command, confirmed=True)
        run = self.run
        if run is None:
            if line.source == SAFE_STOP_SOURCE:  # an abandoned stop's, going on
                self.listener.safe_stop_confirmed(line.command)
            return
        if line.index > run.lines:
            run.lines = line.index
            run.offset = line.end_offset
            run.last = line
        elif line.source == SAFE_STOP_SOURCE:
            if line in run.safe_stop_lines:
                run.safe_stop_lines.remove(line)
        elif line.index == 0:
            run.header_acknowledged += 1
        self.listener.acknowledged(line)
        if run.markers:
            self._markers_due(run)

    def _note_ran(self, run: JobRun) -> None:
        """Where acknowledgements say only *received*: the last job line known to have run."""
        dialect = self.dialect
        if dialect.acks_say_received:
            run.acks_say_received = True
            line = dialect.last_ran
            if (
                isinstance(line, JobLine)
                and line is not run.ran_before
                and line.index > (run.ran.index if run.ran else 0)
            ):
                run.ran = line

    def _markers_due(self, run: JobRun) -> None:
        """Tell the markers whose lines before them are all acknowledged."""
        markers = run.markers
        while markers and markers[0][0] <= run.lines and markers[0][1] <= run.header_acknowledged:
            self.listener.marker_reached(markers.popleft()[2])

    def _settle(self, now: float) -> bool:
        """Act once the controller confirmed everything; True when more was queued."""
        run = self.run
        if run is None or not self.dialect.is_done:
            return False
        if run.barrier is not None:
            if not run.action_running:
                run.action_running = True
                self.listener.action_due(run.barrier)
        elif run.stopping:
            self._finish_stopped(run, now)
        elif run.exhausted and run.error is not None:
            self._stop_feeding(run)
            return True
        elif run.exhausted:
            self._finish(run, Outcome.COMPLETED, now)
        elif run.pause_requested and not run.paused:
            run.paused = True
            self.listener.paused()
        return False

    def _stop_feeding(self, run: JobRun) -> None:
        """No more job lines: drop what is queued and queue the safe stop."""
        if run.stopping:
            return
        waiting = self.controller_holds  # held, or at its own M0
        run.stopping = True
        run.barrier = None
        run.action_running = False
        run.pause_requested = run.paused = run.held = False
        self._drop_pending()
        urgent = self.dialect.abort()  # where the link can: what the controller holds too
        if waiting:
            self.dialect.end_wait()  # should the abort not have ended the hold as well
        self._complete_safe_stop(run)
        run.safe_stop_queued = True
        for command in run.safe_stop:
            line = JobLine(0, 0, command, 0, SAFE_STOP_SOURCE)
            run.safe_stop_lines.append(line)
            # Urgent lines run in no promised order: only those that turn something off go
            # so (a lift's G91, G0 Z10, G90 out of order is an absolute move); the rest go
            # in order behind them, the controller's queue dropped by the abort.
            self.dialect.send(command, line, urgent=urgent and turns_off(command))

    def _complete_safe_stop(self, run: JobRun) -> None:
        """The run's safe stop, whole for every heater and fan the session turned on (by
        its index: Marlin's M104 S0 is the active hotend's), as it stands now: computed
        once, as the stop begins or as the run ends without one (then owed)."""
        if not run.safe_stop_queued and not run.safe_stop_completed:
            run.safe_stop = complete_safe_stop(run.safe_stop, self.heaters, self.hotends)
            run.safe_stop_completed = True

    def _break_waits(self, run: JobRun, now: float) -> None:
        """While a stop waits behind a heat wait of the job: M108 where the firmware takes
        it (again every :data:`BREAK_REPEAT` s, and for each wait in turn), else say at
        once that the safe stop waits for it."""
        awaited = self.dialect.awaiting
        line = awaited[1] if awaited is not None else None
        if (
            not isinstance(line, JobLine)
            or line.source == SAFE_STOP_SOURCE
            or command_word(line.command) not in WAITS
        ):
            run.breaking = None
            return
        if self.breaks_waits:
            if line is not run.breaking or now >= run.broke_at + BREAK_REPEAT:
                run.breaking, run.broke_at = line, now
                self.dialect.send_urgent("M108")
        elif line is not run.held_by:
            run.held_by = line
            self.listener.stop_delayed(
                run,
                f"the controller is waiting for a heater ({line.command}, {line.position}) "
                "and its firmware cannot be interrupted (it has no emergency parser to take "
                "M108): the safe stop goes once that wait ends",
            )

    def _tell_late(self, run: JobRun) -> None:
        awaited = self.dialect.awaiting
        line = awaited[1] if awaited is not None else None
        where = (
            f": the controller has yet to confirm {line.command} ({line.position})"
            if isinstance(line, JobLine)
            else ""
        )
        self.listener.stop_delayed(
            run, f"the safe stop is not confirmed {STOP_PATIENCE:g} s after the stop{where}"
        )

    def _drop_pending(self) -> None:
        """Drop what is queued and not on the wire; commands among it are told."""
        dropped = self.dialect.cancel_pending()
        run = self.run
        if run is not None:
            run.safe_stop_unsent += [t for _, t in dropped if t in run.safe_stop_lines]
        commands = [t for _, t in dropped if not isinstance(t, JobLine)]
        if commands:
            self.listener.commands_dropped(commands)

    def _finish_stopped(self, run: JobRun, now: float) -> None:
        """A stopped job ends cancelled, or with its error (a bad line, a failed action)."""
        self._finish(
            run, Outcome.CANCELLED if run.error is None else run.naming_where(run.error), now
        )

    def _finish(self, run: JobRun, result: Outcome | HostError, now: float) -> None:
        if run.finished:
            return
        run.finished = True
        self._complete_safe_stop(run)  # what is owed, should this end be a failure
        sent = self.dialect.last_sent
        if isinstance(sent, JobLine) and sent.index and sent is not run.sent_before:
            run.last_sent = sent
        self._note_ran(run)
        self.run = None
        if run.held:  # a pause that came as the job ended holds nothing after it
            self.dialect.end_wait()
        if isinstance(result, HostError):
            run.error = result
        else:
            run.outcome = result
            stats = self.dialect.stats
            run.summary = Summary(
                outcome=result,
                lines=run.lines,
                seconds=now - run.started_at,
                resends=stats.resend_requests - run.resends_before,
                retransmissions=stats.retransmissions - run.retransmissions_before,
            )
        self.listener.finished(run)


def failure_error(event: DialectFailed, run: JobRun | None = None) -> HostError:
    """The error a dialect's failure is reported as, naming where the job stood."""
    where = f" (at {event.tag.position})" if isinstance(event.tag, JobLine) else ""
    reason = f"{event.reason}{where}"
    error: HostError
    if event.kind is FailureKind.CONTROLLER or event.kind is FailureKind.RESET:
        error = ControllerError(reason)
    elif event.kind is FailureKind.TIMEOUT or event.kind is FailureKind.NO_ANSWER:
        error = LinkError(reason)
    else:
        error = ProtocolError(reason)
    return error if run is None else run.naming_where(error)
