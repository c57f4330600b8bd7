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
host action, a stall) the host *probes*: it sends ``N<next> M105 S<k>*9999``, a
line whose checksum is wrong on purpose and stays wrong under any one-byte
corruption, so it never runs. Marlin answers it with ``Error:checksum mismatch,
Last Line: <next - 1>`` and ``Resend: <next>`` exactly when it has accepted
every line before it; any other state draws a resend request for the first
missing line. Since nothing is sent after a probe until it is answered, its
answer also settles every reply still owed.

Not every controller answers a bad checksum that way: OctoPrint's virtual
printer, for one, names a line counted from every valid line it received,
resent ones included, and moves its own idea of the last line to match. The
greeting finds out, before any job line: after M110 and a first probe, it sends
a line with a deliberate gap in the numbering (refused: every controller asks
for the missing line) and probes again. A consistent controller asks for the
same line both times. One that does not is renumbered and probed from then on
with ``N<next> M105*<cs>``, a real line that every firmware accepts only once it
holds every line before it, and answers with ``ok T:...``.

The state lives in small parts, each with one job: :class:`History` (numbering
and the lines that may be asked for again), :class:`Window` (what is in flight),
:class:`RoundTrip` (timeouts), :class:`ResendGuard` (which requests to obey),
:class:`~repetrel_host.protocol.dialects.reprap_probes.Probing` (the probe in flight) and
:class:`~repetrel_host.protocol.dialects.reprap_greeting.Greeting` (the greeting's attempts
and what it learnt); the phase is explicit (:class:`RepRapPhase`). What a line error says is
read in :mod:`~repetrel_host.protocol.dialects.reprap_line_errors`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from enum import Enum

from repetrel_host.errors import UsageError
from repetrel_host.gcode.commands import UNBUFFERED, command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects.reprap_greeting import (
    VIRTUAL_PRINTER_RX_BUFFER,
    CheckVerdict,
    Greeting,
    check_verdict,
)
from repetrel_host.protocol.dialects.reprap_line_errors import (
    is_checksum_error,
    is_number_error,
    stated_last_line,
)
from repetrel_host.protocol.dialects.reprap_probes import PROBE_COMMAND, Probing, ping_wire
from repetrel_host.protocol.events import (
    ControllerMessage,
    DialectFailed,
    Event,
    FailureKind,
    LineAcknowledged,
    Notice,
    ProbeKind,
    ResendRequested,
)
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import frame
from repetrel_host.protocol.history import History, Line
from repetrel_host.protocol.resend import RESEND_LOOP_LIMIT, ResendGuard
from repetrel_host.protocol.rtt import RoundTrip
from repetrel_host.protocol.window import Transmission, Window

# Marlin and RepRap count line numbers in a C long, Repetier modulo 65536: renumber
# before 65536 so every firmware agrees on the numbers.
DEFAULT_LINE_NUMBER_LIMIT = 65535
# Lines kept behind the last acknowledged one, for resend requests after oks that were
# counted wrongly (duplicated). Far more than any window plus the drift between probes.
DEFAULT_HISTORY_MARGIN = 1024
PRUNE_STEP = 64  # lines forgotten at a time, past the margin
# Silence that means the controller is gone, while a buffered command waits for its ok.
DEFAULT_REPLY_TIMEOUT = 30.0
# A command that waits for the machine (G28, M109...) may stay silent this long
# before the host probes to find out whether its ok was lost.
UNBUFFERED_GRACE = 5.0
# Probes sent in a row without an answer while a long command (G28, M109...) runs,
# before the host stops adding to that controller's buffer and just waits.
MAX_UNANSWERED_PINGS = 4
SLOW_PING_INTERVAL = 20.0  # then one probe this often: a lost answer must not stall for good
# An error that is not about a line becomes fatal after this long, or this many other
# replies, without a resend request (Marlin halts and says little more).
SUSPECT_ERROR_GRACE = 0.2
SUSPECT_ERROR_LINES = 2
# Warn once when more than this share of lines needed resending (after enough lines).
RESEND_WARNING_RATIO = 0.10
RESEND_WARNING_AFTER = 100


class RepRapPhase(Enum):
    IDLE = "idle"  # start() not called yet
    GREETING = "greeting"  # M110 and a probe in flight: numbering being (re)set
    GAP_CHECK = "gap check"  # a line with a gap in the numbering, to be refused
    PROBE_CHECK = "probe check"  # a checksum probe: does it name the same line?
    RUNNING = "running"
    FAILED = "failed"


_CHECK_PHASES = frozenset({RepRapPhase.GAP_CHECK, RepRapPhase.PROBE_CHECK})


class RepRapDialect:
    """Numbering, history, window, go-back-N resend and probes for one RepRap controller.

    ``probe``: how to probe; None finds out at the greeting (see the module's docstring).
    """

    acks_say_received = False  # an ok comes once the controller took the line to run
    last_ran: object | None = None
    last_sent: object | None = None  # the tag of the last caller's line first transmitted
    on_first_send: Callable[[str, object, bool], None] | None = None

    def __init__(
        self,
        flow: FlowControl | None = None,
        *,
        line_number_limit: int = DEFAULT_LINE_NUMBER_LIMIT,
        history_margin: int = DEFAULT_HISTORY_MARGIN,
        reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
        probe: ProbeKind | None = None,
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
        self._probing = Probing(probe or ProbeKind.CHECKSUM)
        self._greeting = Greeting(check_due=probe is None)
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
        self._owed_refusals = (-1, 0)  # (line asked for, count): see _probe_answered
        self._previous_reply: replies.Reply | None = None
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
            self.on_first_send(command, None, False)
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
            and self._confirmed_through == history.next_number - 1
            and self._window.live == 0
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
        probe = probing.current
        if probe is not None:
            if (
                probe.line is not None or probing.unanswered >= MAX_UNANSWERED_PINGS
            ) and window.waiting_on_unbuffered():
                # A long command holds the probes back: ask again, but seldom. A command
                # probe at once: it waits in the controller behind the command and is
                # answered after it, and each copy sent meanwhile fills its buffer too.
                return probe.sent_at + SLOW_PING_INTERVAL
            # From the last progress too: the oks of the lines ahead of the probe just
            # came, so its answer is one round trip behind them.
            return max(probe.sent_at, self._last_progress_at) + wait
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
            if oldest.line is not None and oldest.line.patient:
                wait = max(wait, UNBUFFERED_GRACE)
            deadline = max(oldest.sent_at, self._last_progress_at) + wait
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
            # numbers; a check that got no answer is given up.
            self._regreet()
            if not greeting.greeted:
                self._events.append(greeting.retry(now))
            return
        if self._line_error_at is not None:
            # The error answered the oldest line, refused without a resend request: its
            # ok will never come. The probe below finds out which line to send again.
            self._line_error_at = None
            if window.in_flight:
                window.pop_oldest()
        silent = now - self._last_received_at
        if silent >= self.reply_timeout and not window.waiting_on_unbuffered():
            self._fail(
                FailureKind.TIMEOUT,
                f"no answer from the controller for {silent:.1f} s; it stopped answering",
            )
            return
        # A lost ok (or a lost resend request): ask where the controller stands.
        self.stats.stalls_recovered += 1
        probing = self._probing
        probing.unanswered += 1
        probe = probing.current
        if probe is not None and probe.line is not None:
            # A command probe runs: the same line goes again (refused if it arrived), so
            # that probes never pile up in a controller busy heating. Each copy that finds
            # it ran draws a refusal (see _probe_answered).
            window.discard(probe)
            self._transmit(probe.line, now)
            probing.current = window.in_flight[-1]
            probing.attempt += 1
            probing.copies += 1
            self.stats.pings += 1
            return
        if probe is not None:
            window.discard(probe)
            probing.current = None
        self._send_probe(now)

    # --- input --------------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes read from the controller."""
        if not data:
            return
        self._last_received_at = now
        buffer = self._receive_buffer
        buffer += data
        start = 0
        while (end := buffer.find(b"\n", start)) >= 0:
            line_start, start = start, end + 1
            if (
                end - line_start == 2
                and buffer.startswith(b"ok", line_start)
                and self._trailing_ok_until is None
                and self._suspect_error is None
                and self._phase is RepRapPhase.RUNNING
            ):
                # A plain ok in a plain state, the bulk of all replies: the same as
                # the general path below, without decoding and classifying it.
                self._handle_ok(replies.PLAIN_OK, now)
                self._previous_reply = replies.PLAIN_OK
                continue
            text = buffer[line_start:end].decode("ascii", errors="replace").strip()
            if text:
                reply = replies.classify(text)
                trailing = self._trailing_ok_until
                self._trailing_ok_until = None  # it must be the very next line
                if not (trailing is not None and now <= trailing and isinstance(reply, replies.Ok)):
                    self._handle_reply(reply, text, now)
                self._previous_reply = reply
        del buffer[:start]

    # --- replies ------------------------------------------------------------

    def _handle_reply(self, reply: replies.Reply, text: str, now: float) -> None:
        if self._phase is RepRapPhase.FAILED:
            return
        if self._suspect_error is not None:
            if isinstance(reply, replies.ResendRequest):
                self._suspect_error = None
            else:
                self._suspect_lines += 1
                if self._suspect_lines > SUSPECT_ERROR_LINES:
                    self._fail_suspect()
                    return
        if not isinstance(reply, replies.OtherReply):
            self._greeting.heard = True
        if isinstance(reply, replies.Ok):
            self._handle_ok(reply, now)
        elif isinstance(reply, replies.ResendRequest):
            self._handle_resend(reply.line_number, now)
        elif isinstance(reply, replies.Start):
            self._handle_start(text)
        elif isinstance(reply, replies.Error):
            if reply.line_error:
                # Told by the resend request that follows it; if none does, the
                # controller dropped the line without asking for it again.
                self._line_error_at = now
            else:
                # Fatal, unless a resend request follows: then it was a line error whose
                # words a garbled newline cut off ("Error:chec" / "ksum mismatch...").
                self._suspect_error = (reply.text, now + max(SUSPECT_ERROR_GRACE, self._rtt.rto))
                self._suspect_lines = 0
        else:
            if isinstance(reply, replies.Busy):
                self._last_progress_at = now  # a long command is running: not a lost ok
            self._events.append(ControllerMessage(reply, text))

    def _handle_ok(self, reply: replies.Ok, now: float) -> None:
        self._last_progress_at = now
        # A line error with an ok after it was answered (its resend request garbled, say);
        # only one the controller fell silent after dropped its line.
        self._line_error_at = None
        window = self._window
        in_flight = window.in_flight
        if not in_flight:
            self.stats.unexpected_oks += 1  # nothing owed one
            return
        if self._phase is not RepRapPhase.RUNNING and self._phase in _CHECK_PHASES:
            # Only resend requests answer the check's lines; an ok is the M110's (a first
            # round trip to measure), or one too many.
            first = in_flight[0]
            if first.line is not None and first.line.is_reset:
                window.drop(first)
                self._rtt.sample(now - first.sent_at)
            else:
                self.stats.unexpected_oks += 1
            return
        if (
            reply.line_number is not None
            and reply.line_number < self._history.next_number
            and self.flow.mode is FlowMode.BUFFERED  # unbuffered means one line in flight
        ):
            window.read_through = reply.line_number
        transmission = in_flight[0]
        probe = self._probing.current
        if probe is not None:
            if probe.line is not None and self._answers_probe(reply, probe):
                # A command probe's "ok T:...": it ran, so every line before it had.
                self._probe_answered(probe, probe.number, now)
                return
            if transmission is probe:
                # Nothing is sent after a probe and a checksum probe draws no plain ok:
                # this ok is one too many (duplicated, or owed to a line already settled).
                self.stats.unexpected_oks += 1
                return
        window.pop_oldest()
        line = transmission.line
        if transmission.stale or line is None:
            return
        # Karn: no samples from retransmissions. Nor from the time a command took to run: an
        # unbuffered command's ok comes once the machine finished it (a heat-up: minutes),
        # and so do the oks of lines sent behind it. One such sample held the timeout at its
        # ceiling for hundreds of lines: every lost ok then cost 5 s. (M110 is answered at
        # once: its round trip is the first measured.)
        if line.unbuffered and not line.is_reset:
            self._machine_waited_until = now
            if not transmission.retransmitted:
                self._probing.unanswered = 0
        elif (
            not transmission.retransmitted
            and transmission.sent_at >= self._machine_waited_until
            and self._rtt.sample(now - transmission.sent_at)
        ):
            self._probing.unanswered = 0
        if line.is_host_line:
            return  # the probe behind an M110 confirms the reset
        self._acknowledge(line, reply.data)

    def _answers_probe(self, reply: replies.Ok, probe: Transmission) -> bool:
        """An "ok T:..." answers a command probe unless an M105 ahead of it may draw one:
        nothing is sent after a probe, and lost oks must not hide its answer."""
        if "T:" not in reply.data:
            return False
        for transmission in self._window.in_flight:
            if transmission is probe:
                return True
            line = transmission.line
            if line is not None and command_word(line.command) == PROBE_COMMAND:
                return False
        return False

    def _handle_resend(self, number: int, now: float) -> None:
        self._last_progress_at = now
        self._line_error_at = None
        previous = self._previous_reply
        stated_last = stated_last_line(previous)
        if stated_last is not None and stated_last + 1 != number:
            self.stats.ignored_resend_requests += 1  # garbled: the two lines disagree
            return
        self._trailing_ok_until = now + self._rtt.trailing_ok_window
        owed_for, owed = self._owed_refusals
        if owed and number == owed_for:
            self._owed_refusals = (owed_for, owed - 1)  # a copy of a command probe refused
            self.stats.ignored_resend_requests += 1
            return
        phase = self._phase
        if phase is RepRapPhase.GAP_CHECK:
            self._gap_refused(number, previous, now)
            return
        if phase is RepRapPhase.PROBE_CHECK:
            self._check_answered(number, previous)
            return
        window = self._window
        probe = self._probing.current
        if (
            probe is not None
            and probe.line is None
            and number == probe.number
            and is_checksum_error(previous)
        ):
            self._probe_answered(probe, number - 1, now)
            return
        if self._guard.just_sent_again(number, now, self._rtt.rto):
            # An answer to an older transmission (a stale one, if one is still held): the
            # line's new transmission stays in flight, its own answer still to come.
            if window.in_flight and window.in_flight[0].stale:
                window.pop_oldest()
            self.stats.ignored_resend_requests += 1
            return
        # An error, its resend request and (on most firmwares) an ok answer one
        # transmission, the oldest: the ok is part of that answer, not another one. A
        # checksum probe is answered so only when refused for its number (the controller
        # misses lines before it); after a checksum error this is another line's answer
        # (its ok was miscounted), and the probe's own is still to come.
        if window.in_flight and (
            window.in_flight[0] is not probe or probe.line is not None or is_number_error(previous)
        ):
            window.pop_oldest()
        if stated_last is not None and phase is RepRapPhase.RUNNING:
            self._confirm_through(stated_last)  # true whatever line drew it
        if self._guard.is_echo(number):
            # An echo of the request being served, from a line that was in transit
            # when the first came (the resend storm).
            self.stats.ignored_resend_requests += 1
            return
        if phase is RepRapPhase.GREETING:
            # An earlier greeting's answer, or this M110 did not take (corrupted, or
            # the board still booting): the hello timeout greets again, with new numbers.
            self.stats.ignored_resend_requests += 1
            return
        history = self._history
        if number == history.next_number:
            # "Send me the next line": everything sent was accepted.
            self._mark_in_flight_stale(number, now, expect_echoes=False)
            history.cursor = number
            self._probing.superseded()
            return
        line = history.get(number)
        if line is None or line.is_reset:
            self._unheld_request(number, corroborated=stated_last is not None)
            return
        rounds = self._guard.rounds(number)
        if rounds >= RESEND_LOOP_LIMIT:
            self._fail(
                FailureKind.CONTROLLER,
                f"the controller asked for line {number} ({line.command}) {rounds} times "
                "in a row; the link is too noisy to go on",
            )
            return
        self.stats.resend_requests += 1
        self._mark_in_flight_stale(number, now)
        history.cursor = number
        self._acked_through = min(self._acked_through, number - 1)
        self._probing.superseded()
        self._events.append(ResendRequested(number, line.command, line.tag))
        self._maybe_warn()

    def _probe_answered(self, probe: Transmission, accepted_through: int, now: float) -> None:
        """The controller accepted every line through ``accepted_through`` and nothing after."""
        copies = self._probing.copies if probe.line is not None else 0
        self._probing.answered()
        # Every transmission before the probe was answered (replies come in order),
        # whether or not its ok reached us; none was sent after it.
        self._window.drop_through(probe)
        self._guard.echoes = 0
        self._confirm_through(accepted_through)
        self._history.cursor = accepted_through + 1
        if self._phase is RepRapPhase.GREETING:
            self._finish_greeting(accepted_through)
        if copies:
            # A command probe sent more than once ran once (its first copy, taken as the
            # one that answered); each later copy is refused with a request for the line
            # after it, which answers no transmission of ours. Obeyed, it would send again
            # lines the controller holds, each refusal a round trip more (and OctoPrint's
            # virtual printer, its buffer full, a 10 s stall). Those answers come before
            # any ok for a line sent from now on: the first such ok ends the count.
            self._owed_refusals = (probe.number + 1, copies)

    def _finish_greeting(self, accepted_through: int) -> None:
        self._phase = RepRapPhase.RUNNING
        self._acked_through = accepted_through
        ready = self._greeting.finished(self._probing.kind)
        if ready is not None:
            self._events.append(ready)

    def _handle_start(self, text: str) -> None:
        if self._greeting.greeted:
            # Never resend across a reset: the controller lost its queue and state.
            self._fail(FailureKind.RESET, "the controller reset (it sent 'start')")
        else:
            # The boot banner while greeting: the probe (or its timeout) tells the rest.
            self._events.append(ControllerMessage(replies.Start(), text))

    def _unheld_request(self, number: int, corroborated: bool) -> None:
        # A garbled number must not stop a job; a real request for a line we no
        # longer hold must. The controller repeats real requests.
        history = self._history
        seen = self._guard.unheld(number)
        if seen < 2 and not (corroborated and number < history.floor):
            self.stats.ignored_resend_requests += 1
            return
        if number >= history.next_number:
            reason = (
                f"the controller asked for line {number}, which the host never sent "
                f"(it holds lines {history.held()}): the controller counts lines its own "
                "way; stopping rather than guessing"
            )
        else:
            reason = (
                f"the controller asked for line {number} again, but the host holds only "
                f"lines {history.held()}; stopping rather than guessing"
            )
        self._fail(FailureKind.PROTOCOL, reason)

    def _maybe_warn(self) -> None:
        sent = self.stats.lines_sent
        if (
            not self._warned_resends
            and sent >= RESEND_WARNING_AFTER
            and self.stats.resend_requests > RESEND_WARNING_RATIO * sent
        ):
            self._warned_resends = True
            self._events.append(
                Notice(
                    f"{self.stats.resend_requests} resend requests for {sent} lines: "
                    "the serial link is noisy (check the cable, or lower the baud rate)"
                )
            )

    # --- the greeting's check -------------------------------------------------

    def _send_gap_line(self, now: float) -> None:
        """``N<k+2> M105``, valid but for the number: a consistent controller asks for k+1."""
        self._phase = RepRapPhase.GAP_CHECK
        number = self._history.next_number + 1
        self._push(Transmission(None, frame(number, PROBE_COMMAND), now, number))

    def _gap_refused(self, number: int, previous: replies.Reply | None, now: float) -> None:
        expected = self._history.next_number
        if number != expected:
            # An earlier greeting's answer, or this M110 did not take (corrupted, or the
            # board still booting): the hello timeout greets again, with new numbers.
            self.stats.ignored_resend_requests += 1
            return
        self._window.forget()
        self._confirm_through(expected - 1)  # the M110's number: the reset took
        if is_checksum_error(previous):
            # The gap line arrived corrupted: once more, then no verdict.
            if self._greeting.gap_line_garbled():
                self._send_gap_line(now)
            else:
                self._finish_greeting(expected - 1)
            return
        self._greeting.check_due = False  # once per connection
        self._phase = RepRapPhase.PROBE_CHECK
        self._push(Transmission(None, ping_wire(number), now, number))
        self.stats.pings += 1

    def _check_answered(self, number: int, previous: replies.Reply | None) -> None:
        self._window.forget()
        expected = self._history.next_number
        verdict = check_verdict(number, expected, is_checksum_error(previous))
        if verdict is CheckVerdict.OWN_COUNT:
            # It named a line it never got, and now takes it for received: renumber,
            # and from now on probe with lines that run. It answers as OctoPrint's
            # virtual printer does: keep within that one's receive buffer too.
            self._probing.kind = ProbeKind.COMMAND
            self._window.limit_bytes(VIRTUAL_PRINTER_RX_BUFFER)
            self._events.append(
                Notice(
                    "the controller's answer to a bad checksum names a line it never got; "
                    "probing with numbered M105 lines instead, at most "
                    f"{self._window.byte_limit} bytes in flight"
                )
            )
            self._regreet()
            return
        if verdict is CheckVerdict.GARBLED:
            self._regreet()  # a garbled answer: no verdict, keep the usual probe
            return
        self._finish_greeting(expected - 1)

    def _regreet(self) -> None:
        """Greet again with the next attempt's numbers (the check too, if it is still due)."""
        self._window.forget()
        self._probing.current = None
        self._restart_greeting()

    # --- acknowledgement and confirmation -----------------------------------

    def _acknowledge(self, line: Line, data: str = "") -> None:
        number = line.number
        if number > self._acked_through:
            self._acked_through = number
        if self._owed_refusals[1]:
            self._owed_refusals = (-1, 0)  # they came before this ok, or never will
        self._guard.progress(number)
        if not line.acknowledged:  # after a resend the controller may acknowledge it again
            line.acknowledged = True
            self._events.append(LineAcknowledged(number, line.command, line.tag, data))
        history = self._history
        if self._acked_through - history.margin > history.floor + PRUNE_STEP:
            history.prune(self._acked_through)  # in steps: not a call for every line

    def _confirm_through(self, number: int) -> None:
        """The controller said its last accepted line is ``number``: acknowledge up to it."""
        if number <= self._confirmed_through:
            return
        history = self._history
        start = max(self._confirmed_through + 1, history.floor)
        self._confirmed_through = number
        for n in range(start, number + 1):
            line = history.get(n)
            if line is not None and not line.is_host_line:
                self._acknowledge(line)

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
            if self._confirmed_through == history.next_number - 1 and not self._window.live:
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
        if self._confirmed_through == history.next_number - 1:
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
                self.on_first_send(line.command, line.tag, line.is_host_line)
            if not line.is_host_line:
                self.stats.lines_sent += 1
                self.last_sent = line.tag
        self._push(Transmission(line, line.wire, now, line.number, retransmitted=retransmitted))

    def _send_probe(self, now: float) -> None:
        if self._phase is RepRapPhase.GREETING and self._greeting.check_due:
            self._send_gap_line(now)  # its refusal confirms the M110, and starts the check
            return
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
        else:
            # The number the controller should expect next. Probes alternate between
            # the next new number (right when it has everything) and the first line
            # whose ok was not counted (right when that ok was lost). Never the first
            # line not confirmed: the last confirmation may be as old as the greeting,
            # whose own probe must not go out again mid-job.
            if self._phase is RepRapPhase.GREETING or probing.attempt % 2 == 0:
                number = history.next_number
            else:
                number = self._acked_through + 1
            line, wire = None, ping_wire(number)
        probing.attempt += 1
        probe = Transmission(line, wire, now, number)
        probing.current = probe
        self.stats.pings += 1
        self._push(probe)

    def _push(self, transmission: Transmission) -> None:
        self._window.push(transmission)
        self.stats.bytes_sent += len(transmission.wire)
        self._outgoing += transmission.wire

    def _mark_in_flight_stale(self, number: int, now: float, expect_echoes: bool = True) -> None:
        # The transmission of line ``number`` drew this request (unless its reply was
        # counted off already); every other one in flight may draw an echo (or
        # nothing, if the controller flushed it or dropped it as a duplicate).
        window = self._window
        cause = any(t.number == number and t.line is not None for t in window.in_flight)
        self._guard.expect_echoes(number, len(window.in_flight) - cause if expect_echoes else 0)
        window.mark_stale(now + self._rtt.rto)

    def _fail_suspect(self) -> None:
        assert self._suspect_error is not None
        self._fail(
            FailureKind.CONTROLLER,
            f"the controller reported an error: {self._suspect_error[0]}",
        )

    def _fail(self, kind: FailureKind, reason: str) -> None:
        self._phase = RepRapPhase.FAILED
        oldest = self._history.get(self._acked_through + 1)
        self._failure = DialectFailed(kind, reason, oldest.tag if oldest is not None else None)
        self._events.append(self._failure)
