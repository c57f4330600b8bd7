"""The RepRap/Marlin line protocol as a dialect (pure: no I/O, no clock).

Why no line is lost or run twice
--------------------------------
The controller executes a numbered line only when its number is the previous
one plus one and its checksum matches, so a line can never run twice, and a
gap is always noticed. The host keeps every line the controller may still ask
for and answers ``Resend: n`` by sending ``n`` and what follows again (go-back-N).

A plain ``ok`` does not say which line it answers, and real links drop,
duplicate and garble replies; counting oks is therefore only used for flow
control and progress. Where it matters (the end of a job, a renumbering, a
host action, a stall) the host *probes*: it sends ``N<next> M105*<cs>``, a real,
harmless line that the controller accepts only once it holds every line before it,
and answers ``ok T:...`` once it ran it. Since nothing is sent after a probe until it
is answered, its answer settles every reply still owed. It draws no error from the
firmware: a healthy link stays healthy, whatever the host asks.

A silence is read before it is suspected (:mod:`~repetrel_host.protocol.silence`): a
controller whose planner is full of long moves, that dwells, homes or heats, answers
nothing for as long as that takes, and says so only in its reports and busy lines. The
host probes only once the silence outlasts what it sent, and one probe at a time.

A controller that answers M105 with a plain ``ok`` (its temperatures on a line of
their own) cannot tell a probe's answer from another's: for it alone the host probes
with ``N<next> M105 S<k>*9999``, whose checksum is wrong on purpose and stays wrong
under any one-byte corruption, so it never runs; Marlin answers it with
``Error:checksum mismatch, Last Line: <next - 1>`` and ``Resend: <next>`` exactly
when it has accepted every line before it (and empties its receive buffer: an error
each time, the only way that controller has).

The state lives in small parts, each with one job: :class:`History` (numbering
and the lines that may be asked for again), :class:`Window` (what is in flight),
:class:`RoundTrip` (timeouts), :class:`ResendGuard` (which requests to obey),
:class:`~repetrel_host.protocol.dialects.reprap_probes.Probing` (the probe in flight),
:class:`~repetrel_host.protocol.dialects.reprap_greeting.Greeting` (the greeting's attempts)
and :class:`~repetrel_host.protocol.silence.Silence` (what explains a silence); the phase is
explicit (:class:`~repetrel_host.protocol.dialects.reprap_greeting.RepRapPhase`). What the
controller says is read in :mod:`~repetrel_host.protocol.dialects.reprap_replies`, what a line
error says of the line in :mod:`~repetrel_host.protocol.dialects.reprap_line_errors`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from repetrel_host.errors import UsageError
from repetrel_host.gcode.commands import UNBUFFERED, command_word
from repetrel_host.gcode.estimate import Limits
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects.reprap_greeting import Greeting, RepRapPhase
from repetrel_host.protocol.dialects.reprap_probes import PROBE_COMMAND, Probing, ping_wire
from repetrel_host.protocol.dialects.reprap_replies import RepRapReplies
from repetrel_host.protocol.events import (
    DialectFailed,
    Event,
    FailureKind,
    ProbeKind,
)
from repetrel_host.protocol.flow import FlowControl
from repetrel_host.protocol.framing import frame
from repetrel_host.protocol.history import History, Line
from repetrel_host.protocol.resend import ResendGuard
from repetrel_host.protocol.rtt import MAX_BACKOFF_EXPONENT, RoundTrip
from repetrel_host.protocol.silence import UNBUFFERED_GRACE, Silence
from repetrel_host.protocol.window import Transmission, Window

# Marlin and RepRap count line numbers in a C long, Repetier modulo 65536: renumber
# before 65536 so every firmware agrees on the numbers.
DEFAULT_LINE_NUMBER_LIMIT = 65535
# Lines kept behind the last acknowledged one, for resend requests after oks that were
# counted wrongly (duplicated). Far more than any window plus the drift between probes.
DEFAULT_HISTORY_MARGIN = 1024
# Silence beyond what explains it that means the controller is gone.
DEFAULT_REPLY_TIMEOUT = 30.0
# A probe behind a command that waits (G28, M109...) is answered after it: another goes
# only this long after it, so that probes do not pile up in a controller busy for long.
SLOW_PING_INTERVAL = 20.0
# Probe answers in a row, nothing of the caller's sent between, that end a sync (the end of
# a job, a host action): an M105's answer cannot be told from another M105's said twice,
# and two cannot both be one. A checksum probe's answer states the last line: one does.
SYNC_ANSWERS = {ProbeKind.COMMAND: 2, ProbeKind.CHECKSUM: 1}


class RepRapDialect(RepRapReplies):
    """Numbering, history, window, go-back-N resend and probes for one RepRap controller.

    ``probe``: how to probe; None: with M105 lines, unless the greeting finds that the
    controller's ok for M105 carries no temperatures (see the module's docstring).
    ``limits``: the machine's planner limits, for the time its moves take (None: Marlin's).
    """

    acks_say_received = False  # an ok comes once the controller took the line to run
    last_ran: object | None = None
    last_sent: object | None = None  # the tag of the last caller's line first transmitted
    on_first_send: Callable[[str, object, bool, int | None], None] | None = None

    def __init__(
        self,
        flow: FlowControl | None = None,
        *,
        line_number_limit: int = DEFAULT_LINE_NUMBER_LIMIT,
        history_margin: int = DEFAULT_HISTORY_MARGIN,
        reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
        probe: ProbeKind | None = None,
        limits: Limits | None = None,
    ) -> None:
        if line_number_limit < 3:
            raise ValueError("line_number_limit must be at least 3")
        self.flow = flow or FlowControl()
        self.line_number_limit = line_number_limit
        self.reply_timeout = reply_timeout
        self.stats = Statistics()
        self._phase = RepRapPhase.IDLE
        self._history = History(max(history_margin, 4 * self.flow.line_limit))
        self._window = Window(self.flow)
        self._line_limit = self._window.line_limit  # read for every line: kept at hand
        self._rtt = RoundTrip()
        self._guard = ResendGuard()
        self._probing = Probing(probe or ProbeKind.COMMAND)
        self._may_fall_back = probe is None  # to checksum probes, if M105's ok says nothing
        self._greeting = Greeting()
        self._silence = Silence(limits)
        # (the silence it is for: the last progress then, until when it is explained)
        self._explained: tuple[float, float] | None = None
        # command, tag, unbuffered, confirm
        self._pending: deque[tuple[str, object, bool, bool]] = deque()
        self._candidate: Line | None = None  # the next new line, framed, not yet numbered
        self._sync_requested = False
        self._acked_through = -1  # by counting oks: progress
        self._confirmed_through = -1  # by the controller's own numbers: exact
        self._last_received_at = 0.0
        self._last_sent_at = 0.0
        self._last_progress_at = 0.0
        self._machine_waited_until = 0.0  # the ok of the last unbuffered command
        self._previous_reply: replies.Reply | None = None
        self._sync_answers = 0  # probes answered since the caller's last line went
        self._trailing_ok_until: float | None = None  # an ok by then ends an error reply
        self._suspect_error: tuple[str, float] | None = None  # (text, when it becomes fatal)
        self._suspect_lines = 0
        self._line_error_at: float | None = None  # a line error no resend request followed
        self._warned_resends = False
        self._receive_buffer = bytearray()
        self._outgoing = bytearray()
        self._events: deque[Event] = deque()
        self._failure: DialectFailed | None = None

    # --- feeding ------------------------------------------------------------

    def start(self, now: float) -> None:
        """Begin: the first line on the wire will be ``N0 M110 N0``."""
        if self._phase is not RepRapPhase.IDLE:
            raise UsageError("the dialect was already started")
        self._last_received_at = self._last_sent_at = self._last_progress_at = now
        self._greeting.started_at = now
        self._begin_greeting()

    pause_command = None  # the host holds a job at M0 (the controller's ok says it stopped)

    def send(
        self, command: str, tag: object = None, *, confirm: bool = False, urgent: bool = False
    ) -> None:
        """Queue one clean command (see :func:`clean_line`); ``tag`` comes back in events.

        An ok already says that the controller ran the line, and nothing goes ahead of
        what it holds (``urgent``): both are how every line goes here. A ``confirm`` line
        is probed for a lost ok only after :data:`UNBUFFERED_GRACE`: a probe's answer comes
        before the oks of lines the controller still holds, and would settle the command
        before its reply's lines came (they would then answer the next command)."""
        word = command_word(command)
        if word == "M110":
            raise UsageError("M110 sets line numbers, which the host owns; it cannot be queued")
        self._pending.append((command, tag, word in UNBUFFERED, confirm))
        self._sync_requested = False

    def send_urgent(self, command: str) -> None:
        """Write ``command`` unnumbered, ahead of everything (Marlin's emergency parser
        reads M112, M108 and M410 as they arrive, whatever the line numbers).

        The line still goes on into the receive buffer and runs in its turn, as any
        unnumbered line: M108 and M410 then draw an ok (OctoPrint counts it too), which is
        counted in flight so that it acknowledges none of the host's lines; M112 halts."""
        data = command.encode("ascii") + b"\n"
        if self.on_first_send is not None:
            self.on_first_send(command, None, False, None)
        if command_word(command) == "M112" or self._phase is not RepRapPhase.RUNNING:
            self.stats.bytes_sent += len(data)
            self._outgoing += data
            return
        line = Line(-1, command, None, data, False, transmitted=True, is_host_line=True)
        self._push(Transmission(line, data, self._last_sent_at, -1))

    def abort(self) -> bool:
        return False  # no way to take back what the controller holds

    def hold(self, at_layer_end: bool = False) -> bool:
        return False

    def end_wait(self) -> None:
        pass

    def request_status(self) -> bool:
        return False  # M105 is a line like any other here

    def request_sync(self) -> None:
        """No more lines for now: confirm that the controller accepted every line sent.

        :attr:`is_done` becomes true once it has.
        """
        self._sync_requested = True

    def cancel_pending(self) -> list[tuple[str, object]]:
        """Drop queued lines not yet on the wire; return them (command, tag)."""
        dropped = [(command, tag) for command, tag, _, _ in self._pending]
        self._pending.clear()
        self._candidate = None
        return dropped

    @property
    def awaiting(self) -> tuple[str, object] | None:
        for transmission in self._window.in_flight:
            line = transmission.line
            if not transmission.stale and line is not None and not line.is_host_line:
                return line.command, line.tag
        return None

    @property
    def wants_lines(self) -> bool:
        """True when the queue is short enough that a new line could go out soon."""
        return self._phase is not RepRapPhase.FAILED and len(self._pending) < self._line_limit

    @property
    def is_done(self) -> bool:
        """Every line queued so far is confirmed accepted by the controller itself."""
        history = self._history
        return (
            self._phase is RepRapPhase.RUNNING
            and not self._pending
            and history.cursor == history.next_number
            and self._settled()
            and self._window.live == 0
        )

    def _settled(self) -> bool:
        """The controller's own answers say it took every line sent (see SYNC_ANSWERS)."""
        return (
            self._confirmed_through == self._history.next_number - 1
            and self._sync_answers >= SYNC_ANSWERS[self._probing.kind]
        )

    @property
    def is_ready(self) -> bool:
        return self._phase is RepRapPhase.RUNNING

    @property
    def probe(self) -> ProbeKind:
        return self._probing.kind

    @property
    def phase(self) -> RepRapPhase:
        return self._phase

    @property
    def failure(self) -> DialectFailed | None:
        return self._failure

    @property
    def retransmission_timeout(self) -> float:
        return self._rtt.rto

    # --- output -------------------------------------------------------------

    def data_to_send(self, now: float) -> bytes:
        """Bytes to write now: every line the window has room for, or a probe."""
        # While live lines are in flight and the window has room for less than a batch,
        # wait: their oks (or the timeout's probe) call again. Bytes already queued (a
        # probe, an urgent line) still go; after a resend request nothing live is in
        # flight, so the lines asked for go at once.
        refill = self._phase is not RepRapPhase.RUNNING or self._window.wants_refill(now)
        while (
            refill
            and (self._phase is RepRapPhase.RUNNING or self._phase is RepRapPhase.GREETING)
            and self._probing.current is None
        ):
            line = self._next_line_to_transmit()
            if line is None:
                if self._wants_probe():
                    self._send_probe(now)
                break
            if self._phase is RepRapPhase.RUNNING and not self._window.has_room(
                len(line.wire), now
            ):
                break
            self._transmit(line, now)
        if not self._outgoing:
            return b""
        self._last_sent_at = now
        data = bytes(self._outgoing)
        self._outgoing.clear()
        return data

    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timeout` wants to be called, or None."""
        phase = self._phase
        if phase is RepRapPhase.FAILED or phase is RepRapPhase.IDLE:
            return None
        if self._suspect_error is not None:
            return self._suspect_error[1]
        window = self._window
        if phase is not RepRapPhase.RUNNING:
            return self._greeting.deadline(self._last_received_at, self._last_sent_at)
        probing = self._probing
        wait = self._rtt.backed_off(probing.unanswered)
        # A silence found explained (by handle_timeout) is waited out; a new answer starts
        # a new silence, read again once its round trip passed.
        explained = self._explained
        until = 0.0
        if explained is not None and explained[0] == self._last_progress_at:
            until = explained[1]
        probe = probing.current
        if probe is not None:
            if window.waiting_on_unbuffered():
                # A long command holds the probe back (a command probe waits behind it, a
                # checksum probe in the receive buffer of a controller that reads none
                # meanwhile): ask again, but seldom.
                return max(probe.sent_at + SLOW_PING_INTERVAL, until)
            # From the last progress too: the oks of the lines ahead of the probe just
            # came, so its answer is one round trip behind them. Each one unanswered
            # doubles the wait, up to the slow interval: a controller that answers
            # nothing is asked seldom, not flooded with lines that run.
            wait = min(self._rtt.rto * 2.0 ** min(probing.unanswered, 16), SLOW_PING_INTERVAL)
            return max(probe.sent_at + wait, self._last_progress_at + wait, until)
        # A line error that no resend request followed: the controller dropped the
        # line without asking for it again. Probe within a round trip, not later.
        refused = None if self._line_error_at is None else self._line_error_at + self._rtt.rto
        oldest = window.oldest_live()
        if oldest is None:
            if not window.in_flight:
                return refused
            # Only stale transmissions left, whose replies may never come (flushed).
            deadline = max(window.in_flight[-1].sent_at, self._last_progress_at) + wait
        else:
            line = oldest.line
            if probing.kind is ProbeKind.CHECKSUM and line is not None and line.patient:
                # A checksum probe is answered as it arrives, before the oks (and a
                # command's reply) of what the controller holds: not while it works.
                wait = max(wait, UNBUFFERED_GRACE)
            deadline = max(oldest.sent_at, self._last_progress_at) + wait
        deadline = max(deadline, until)
        return deadline if refused is None else min(deadline, refused)

    def handle_timeout(self, now: float) -> None:
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return
        if self._suspect_error is not None:
            self._fail_suspect()
            return
        window = self._window
        if self._phase is not RepRapPhase.RUNNING:
            greeting = self._greeting
            if greeting.timed_out():
                if greeting.greeted:  # renumbering mid-stream: it stopped answering
                    self._fail(
                        FailureKind.TIMEOUT,
                        "the controller did not answer M110 (line numbering reset)",
                    )
                else:
                    self._fail(
                        FailureKind.NO_ANSWER,
                        f"no answer to M110 (line numbering reset), sent {greeting.unanswered} "
                        f"times in {now - greeting.started_at:.0f} s",
                    )
                return
            # No answer (the board still booting, a line lost): greet again, with new
            # numbers.
            self._regreet()
            if not greeting.greeted:
                self._events.append(greeting.retry(now))
            return
        since = self._last_progress_at
        probing = self._probing
        if self._line_error_at is not None:
            # The error answered the oldest line, refused without a resend request: its
            # ok will never come. The probe below finds out which line to send again.
            self._line_error_at = None
            if window.in_flight:
                window.pop_oldest()
            explained = since
        else:
            explained = self._silence.explained_until(since, now)
            # Each probe unanswered doubles the silence waited for the next: a controller
            # slower than its plan answers the first before another goes.
            stretch = 2.0 ** min(probing.unanswered, MAX_BACKOFF_EXPONENT)
            deadline = since + (explained - since) * stretch + self._rtt.rto
            if deadline > now:
                self._explained = (since, deadline)
                return
        silent = now - self._last_received_at
        if silent >= self.reply_timeout and not window.waiting_on_unbuffered():
            self._fail(
                FailureKind.TIMEOUT,
                f"no answer from the controller for {silent:.1f} s; it stopped answering",
            )
            return
        self.stats.stalls_recovered += 1
        history = self._history
        if history.cursor < history.next_number and probing.kind is ProbeKind.COMMAND:
            # Lines asked for again wait their turn behind an answer lost: a probe, the
            # next number, would leave a gap. The oldest transmission is taken as
            # answered (not its line): the next line goes, and tells.
            if window.in_flight:
                window.pop_oldest()
            return
        # A lost ok (or a lost resend request): ask where the controller stands.
        probing.unanswered += 1
        self._silence.suspected(since, explained)
        probe = probing.current
        if probe is not None:
            # Its answer, or its line, was lost, or it still waits behind what the
            # controller holds. The next goes, numbered next (Marlin 2.1 drops a copy of
            # the line it took last without a word). Should this one's answer come after
            # all, it is taken for the next one's: which says no more than the truth, as
            # nothing of the caller's went between them.
            window.discard(probe)
            probing.current = None
        self._send_probe(now)

    # --- transmission -------------------------------------------------------

    def _begin_greeting(self) -> None:
        self._greeting.begin()
        self._restart_greeting()

    def _restart_greeting(self) -> None:
        self._phase = RepRapPhase.GREETING
        self._candidate = None
        self._acked_through = self._confirmed_through = self._window.read_through = -1
        self._queue_greeting()

    def _queue_greeting(self) -> None:
        """(Re)send M110 and the probe behind it; the probe's answer confirms the reset.

        Attempt ``k`` (from 0) sends ``Nk M110 Nk`` and probes line k + 1, so that a
        late answer to an earlier attempt's probe is never taken for this one's: lines
        must not start while an earlier M110 could still reset the numbering.
        """
        self._history.restart(self._greeting.reset_line())
        self._probing.superseded()

    def _next_line_to_transmit(self) -> Line | None:
        history = self._history
        if history.cursor < history.next_number:
            return history.lines[history.cursor]
        if self._phase is RepRapPhase.GREETING or not self._pending:
            return None
        if history.next_number > self.line_number_limit:
            # Renumber only once the controller confirmed every line: no resend
            # request may ever name a number from before the reset.
            if self._settled() and not self._window.live:
                self._begin_greeting()
                return history.lines[history.cursor]
            self._sync_requested = True
            return None
        # Numbered only once it goes out (see _transmit), so that every number
        # below next_number has been on the wire and a probe can follow them.
        if self._candidate is None:
            command, tag, unbuffered, confirm = self._pending[0]
            number = history.next_number
            wire = frame(number, command)
            patient = unbuffered or confirm
            self._candidate = Line(number, command, tag, wire, unbuffered, patient=patient)
        return self._candidate

    def _wants_probe(self) -> bool:
        history = self._history
        if self._phase is RepRapPhase.GREETING:
            return history.cursor == history.next_number  # the reset line went out
        if self._settled():
            return False
        # After the oks of what was sent, so that an M400 before a pause has finished.
        return self._sync_requested and not self._window.live

    def _transmit(self, line: Line, now: float) -> None:
        history = self._history
        if line is self._candidate:
            self._pending.popleft()
            history.append(line)
            self._candidate = None
        history.cursor = line.number + 1
        retransmitted = line.transmitted
        if retransmitted:
            self.stats.retransmissions += 1
            self._guard.sent_again(line.number, now)
        else:
            line.transmitted = True
            if self.on_first_send is not None:
                self.on_first_send(line.command, line.tag, line.is_host_line, line.number)
            if not line.is_host_line:
                self.stats.lines_sent += 1
                self.last_sent = line.tag
                self._silence.sent(line.command)
                self._sync_answers = 0
        self._push(Transmission(line, line.wire, now, line.number, retransmitted=retransmitted))

    def _send_probe(self, now: float) -> None:
        """A probe behind what went: a numbered M105, or (for a controller whose M105
        answer says nothing) a line whose checksum never fits."""
        probing = self._probing
        history = self._history
        if probing.kind is ProbeKind.COMMAND:
            self._candidate = None  # framed with the number the probe now takes
            number = history.next_number
            wire = frame(number, PROBE_COMMAND)
            line = Line(
                number,
                PROBE_COMMAND,
                None,
                wire,
                False,
                is_probe=True,
                transmitted=True,  # it goes out now, below
                is_host_line=True,
            )
            history.append(line)
            history.cursor = number + 1
            if self.on_first_send is not None:
                self.on_first_send(PROBE_COMMAND, None, True, number)
        else:
            # The number the controller expects next when it has everything: its answer
            # says so ("Last Line: <number - 1>"), or names the line it misses. (Never
            # one it took: Marlin 2.1 drops that without a word.)
            number = history.next_number
            line, wire = None, ping_wire(number)
        probe = Transmission(line, wire, now, number)
        probing.current = probe
        self.stats.pings += 1
        self._push(probe)

    def _push(self, transmission: Transmission) -> None:
        self._window.push(transmission)
        self.stats.bytes_sent += len(transmission.wire)
        self._outgoing += transmission.wire
