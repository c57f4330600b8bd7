"""The host side of the line protocol as a pure state machine (no I/O, no clock).

Feed it commands with :meth:`HostProtocol.send`, bytes from the controller with
:meth:`HostProtocol.receive_data`, and the current time where it matters; take
bytes to write from :meth:`HostProtocol.data_to_send` and happenings from
:meth:`HostProtocol.next_event`.

Why no line is lost or run twice
--------------------------------
The controller executes a numbered line only when its number is the previous
one plus one and its checksum matches, so a line can never run twice, and a
gap is always noticed. The host keeps every line the controller may still ask
for and answers ``Resend: n`` by sending ``n`` and what follows again (go-back-N).

A plain ``ok`` does not say which line it answers, and real links drop,
duplicate and garble replies; counting oks is therefore only used for flow
control and progress. Where it matters (the end of a job, a renumbering, a
host action, a stall) the host *pings*: it sends ``N<next> M105 S<k>*9999``, a
line whose checksum is wrong on purpose and stays wrong under any one-byte
corruption, so it never runs. The controller answers it with ``Error:checksum
mismatch, Last Line: <next - 1>`` and ``Resend: <next>`` exactly when it has
accepted every line before it; any other state draws a resend request for the
first missing line. Since nothing is sent after a ping until it is answered,
its answer also settles every reply still owed.
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass
from enum import Enum

from repetrel_host.errors import ProtocolError
from repetrel_host.gcode.commands import UNBUFFERED, command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.framing import checksum, frame, reset_command

# Marlin and RepRap count line numbers in a C long, Repetier modulo 65536: renumber
# before 65536 so every firmware agrees on the numbers.
DEFAULT_LINE_NUMBER_LIMIT = 65535
# Lines kept behind the last acknowledged one, for resend requests after oks that were
# counted wrongly (duplicated). Far more than any window plus the drift between pings.
DEFAULT_HISTORY_MARGIN = 1024
# Silence that means the controller is gone, while a buffered command waits for its ok.
DEFAULT_REPLY_TIMEOUT = 30.0
# Retransmission timeout from the measured round trip (RFC 6298), clamped as
# Klipper's serial queue does: short enough that a lost ok costs a fraction of a
# second on a fast link, long enough not to ping during a slow USB frame.
MIN_RTO = 0.025
MAX_RTO = 5.0
INITIAL_RTO = 1.0
# A command that waits for the machine (G28, M109...) may stay silent this long
# before the host pings to find out whether its ok was lost.
UNBUFFERED_GRACE = 5.0
# Pings sent in a row without an answer while a long command (G28, M109...) runs,
# before the host stops adding to that controller's buffer and just waits.
MAX_UNANSWERED_PINGS = 4
# An error that is not about a line becomes fatal after this long, or this many other
# replies, without a resend request (Marlin halts and says little more).
SUSPECT_ERROR_GRACE = 0.2
SUSPECT_ERROR_LINES = 2
SLOW_PING_INTERVAL = 20.0  # then one ping this often: a lost answer must not stall for good
# Marlin ends a line error with an ok, written right behind the resend request;
# some 2.0.x builds leave it out. An ok arriving within half the smoothed round
# trip is that trailing ok, not the answer to a line sent since.
TRAILING_OK_SHARE = 0.5
TRAILING_OK_WINDOW = 0.002  # before any round trip was measured
# A round trip under a quarter of the smoothed one is taken for an outlier.
RTT_OUTLIER = 0.25
RTT_NUDGE = 0.98
# Boards that reset when the port opens need about two seconds to boot.
HELLO_TIMEOUT = 2.0
HELLO_ATTEMPTS = 10  # a corrupted M110 or a garbled answer costs one timeout
# The same line requested this many times in a row, without progress, is a loop.
RESEND_LOOP_LIMIT = 10
# Warn once when more than this share of lines needed resending (after enough lines).
RESEND_WARNING_RATIO = 0.10
RESEND_WARNING_AFTER = 100

# A ping's checksum field. Valid checksums are 0..255; one changed character turns
# "9999" into 0, 9, 99 or a number above 255, so the ping's body is chosen with a
# checksum outside {0, 9, 99} and can never become valid.
_PING_CHECKSUM = b"9999"
_PING_UNSAFE = frozenset({0, 9, 99})
_LAST_LINE = re.compile(r"last\s*line:?\s*(-?\d+)", re.IGNORECASE)


class FlowMode(Enum):
    """How many lines may be unacknowledged at once."""

    UNBUFFERED = "unbuffered"  # one line in flight: wait for each ok
    BUFFERED = "buffered"  # as many as the controller's receive buffer holds


@dataclass(frozen=True, slots=True)
class FlowControl:
    """Flow-control limits.

    In buffered mode the host counts the bytes of unacknowledged lines against
    the controller's receive buffer (character counting, as grbl and
    Repetier-Host do): a line leaves that buffer before it is acknowledged, so
    the buffer never overflows. One byte stays free because a ring buffer of
    N bytes holds N - 1. When the controller reports ADVANCED_OK
    (``ok N<last line> P.. B..``), lines up to that N have left the buffer for the
    command slots and stop counting, so the buffer is kept full.
    """

    mode: FlowMode = FlowMode.BUFFERED
    rx_buffer: int = 128  # the controller's receive buffer in bytes (AVR Marlin: 128)
    max_lines: int = 8  # lines in flight at most, whatever their length

    def __post_init__(self) -> None:
        if self.rx_buffer < 2:
            raise ValueError("rx_buffer must be at least 2 bytes")
        if self.max_lines < 1:
            raise ValueError("max_lines must be at least 1")

    @property
    def byte_limit(self) -> int:
        return self.rx_buffer - 1

    @property
    def line_limit(self) -> int:
        return 1 if self.mode is FlowMode.UNBUFFERED else self.max_lines


# --- events ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ControllerReady:
    """The controller confirmed the opening M110: it is there and numbering agrees."""


@dataclass(frozen=True, slots=True)
class LineAcknowledged:
    """The controller acknowledged a line sent with :meth:`HostProtocol.send` (once per line)."""

    number: int
    command: str
    tag: object
    data: str  # what followed "ok", e.g. temperatures


@dataclass(frozen=True, slots=True)
class ResendRequested:
    """The controller asked for ``number`` and what follows again; the host will send them."""

    number: int
    command: str
    tag: object


@dataclass(frozen=True, slots=True)
class ControllerMessage:
    """A line that is not flow control: echo, comments, Hyrel reports, busy, line errors."""

    reply: replies.Reply
    text: str


@dataclass(frozen=True, slots=True)
class Notice:
    """Something the user should know that does not stop the job (a high resend rate)."""

    text: str


@dataclass(frozen=True, slots=True)
class Failed:
    """The stream cannot go on. Nothing more is sent; ``reason`` is one sentence.

    ``kind`` is ``"controller"`` (an error or a reset reported by the controller),
    ``"protocol"`` (a request the host cannot honour) or ``"timeout"``.
    """

    kind: str
    reason: str
    tag: object = None  # the oldest unacknowledged line's tag, where the trouble most likely is


Event = ControllerReady | LineAcknowledged | ResendRequested | ControllerMessage | Notice | Failed


# --- state ----------------------------------------------------------------------


class _Phase(Enum):
    IDLE = "idle"  # start() not called yet
    GREETING = "greeting"  # M110 and a ping in flight: numbering being (re)set
    RUNNING = "running"
    FAILED = "failed"


@dataclass(slots=True)
class _Line:
    number: int
    command: str
    tag: object
    wire: bytes
    unbuffered: bool
    is_reset: bool = False
    transmitted: bool = False
    acknowledged: bool = False


@dataclass(slots=True)
class _Transmission:
    line: _Line | None  # None for a ping
    wire: bytes
    sent_at: float
    number: int
    # Stale: sent before a resend request; the controller refuses it (or has
    # dropped it), so whatever it draws acknowledges nothing.
    stale: bool = False
    retransmitted: bool = False


@dataclass(slots=True)
class Statistics:
    lines_sent: int = 0  # first transmissions
    retransmissions: int = 0
    resend_requests: int = 0  # honoured requests
    ignored_resend_requests: int = 0  # echoes of one request, garbled numbers
    unexpected_oks: int = 0
    pings: int = 0  # sync pings sent
    stalls_recovered: int = 0  # timeouts answered by a ping
    bytes_sent: int = 0


class HostProtocol:
    """Numbering, history, window, go-back-N resend and sync pings for one controller."""

    def __init__(
        self,
        flow: FlowControl | None = None,
        *,
        line_number_limit: int = DEFAULT_LINE_NUMBER_LIMIT,
        history_margin: int = DEFAULT_HISTORY_MARGIN,
        reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    ) -> None:
        if line_number_limit < 3:
            raise ValueError("line_number_limit must be at least 3")
        self.flow = flow or FlowControl()
        self.line_number_limit = line_number_limit
        self._line_limit = self.flow.line_limit  # read for every line: kept at hand
        self._byte_limit = self.flow.byte_limit
        self.history_margin = max(history_margin, 4 * self._line_limit)
        self.reply_timeout = reply_timeout
        self.stats = Statistics()
        self._phase = _Phase.IDLE
        self._pending: deque[tuple[str, object, bool]] = deque()  # command, tag, unbuffered
        self._candidate: _Line | None = None  # the next new line, framed, not yet numbered
        self._history: dict[int, _Line] = {}
        self._history_floor = 0  # lowest number still held
        self._next_number = 0  # number the next new line gets
        self._cursor = 0  # next number to transmit (< _next_number while resending)
        self._in_flight: deque[_Transmission] = deque()
        self._bytes_in_flight = 0
        self._live_in_flight = 0  # transmissions neither stale nor pings
        self._resend_target: int | None = None
        self._echoes_expected = 0
        self._stale_bytes = 0
        self._stale_expire_at = 0.0
        self._acked_through = -1  # by counting oks: progress
        self._confirmed_through = -1  # by the controller's own numbers: exact
        # ADVANCED_OK's N: the last line the controller took out of its receive buffer.
        # Only for flow control (a garbled N costs a resend, never a line).
        self._read_through = -1
        self._ping: _Transmission | None = None
        self._ping_attempt = 0  # pings sent since one was last answered
        self._trailing_ok_until: float | None = None  # an ok by then ends an error reply
        self._unanswered_pings = 0
        self._sync_requested = False
        self._greeting_attempts = 0
        self._greeted = False
        self._srtt: float | None = None
        self._rttvar = 0.0
        self._rto = INITIAL_RTO
        self._last_received_at = 0.0
        self._last_progress_at = 0.0
        self._previous_reply: replies.Reply | None = None
        self._loop_number = -1
        self._loop_count = 0
        self._loop_retransmitted = False
        self._warned_resends = False
        self._suspect_error: tuple[str, float] | None = None  # (text, when it becomes fatal)
        self._suspect_lines = 0
        self._unheld_requests: dict[int, int] = {}
        self._receive_buffer = bytearray()
        self._outgoing = bytearray()
        self._events: deque[Event] = deque()
        self._failure: Failed | None = None

    # --- feeding ------------------------------------------------------------

    def start(self, now: float) -> None:
        """Begin: the first line on the wire will be ``N0 M110 N0``."""
        if self._phase is not _Phase.IDLE:
            raise ProtocolError("the protocol was already started")
        self._last_received_at = self._last_progress_at = now
        self._begin_greeting()

    def send(self, command: str, tag: object = None) -> None:
        """Queue one clean command (see :func:`clean_line`); ``tag`` comes back in events."""
        word = command_word(command)
        if word == "M110":
            raise ProtocolError("M110 sets line numbers, which the host owns; it cannot be queued")
        self._pending.append((command, tag, word in UNBUFFERED))
        self._sync_requested = False

    def request_sync(self) -> None:
        """No more lines for now: confirm that the controller accepted every line sent.

        :attr:`is_done` becomes true once it has.
        """
        self._sync_requested = True

    def cancel_pending(self) -> int:
        """Drop queued lines not yet on the wire; return how many were dropped."""
        dropped = len(self._pending)
        self._pending.clear()
        self._candidate = None
        return dropped

    @property
    def wants_lines(self) -> bool:
        """True when the queue is short enough that a new line could go out soon."""
        return self._phase is not _Phase.FAILED and len(self._pending) < self._line_limit

    @property
    def is_done(self) -> bool:
        """Every line queued so far is confirmed accepted by the controller itself."""
        return (
            self._phase is _Phase.RUNNING
            and not self._pending
            and self._cursor == self._next_number
            and self._confirmed_through == self._next_number - 1
            and self._live_in_flight == 0
        )

    @property
    def failure(self) -> Failed | None:
        return self._failure

    @property
    def retransmission_timeout(self) -> float:
        return self._rto

    # --- output -------------------------------------------------------------

    def data_to_send(self, now: float) -> bytes:
        """Bytes to write now: every line the window has room for, or a ping."""
        while self._phase in (_Phase.GREETING, _Phase.RUNNING) and self._ping is None:
            line = self._next_line_to_transmit()
            if line is None:
                if self._wants_sync_ping():
                    self._send_ping(now)
                break
            if not self._window_has_room(len(line.wire), now):
                break
            self._transmit(line, now)
        data = bytes(self._outgoing)
        self._outgoing.clear()
        return data

    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timeout` wants to be called, or None."""
        if self._phase in (_Phase.FAILED, _Phase.IDLE):
            return None
        if self._suspect_error is not None:
            return self._suspect_error[1]
        backoff = 2.0 ** min(self._unanswered_pings, 4)
        if self._phase is _Phase.GREETING:
            if not self._in_flight:
                return None
            return max(self._last_received_at, self._in_flight[-1].sent_at) + HELLO_TIMEOUT
        if self._ping is not None:
            if self._unanswered_pings >= MAX_UNANSWERED_PINGS and self._waiting_on_unbuffered():
                # A long command holds the pings back: ask again, but seldom.
                return self._ping.sent_at + SLOW_PING_INTERVAL
            return self._ping.sent_at + min(self._rto * backoff, MAX_RTO)
        oldest = next((t for t in self._in_flight if not t.stale), None)
        if oldest is None:
            if not self._in_flight:
                return None
            # Only stale transmissions left, whose replies may never come (flushed).
            base = max(self._in_flight[-1].sent_at, self._last_progress_at)
            return base + min(self._rto * backoff, MAX_RTO)
        base = max(oldest.sent_at, self._last_progress_at)
        wait = min(self._rto * backoff, MAX_RTO)
        if oldest.line is not None and oldest.line.unbuffered:
            wait = max(wait, UNBUFFERED_GRACE)
        return base + wait

    def handle_timeout(self, now: float) -> None:
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return
        if self._suspect_error is not None and now >= self._suspect_error[1]:
            self._fail_suspect()
            return
        if self._phase is _Phase.GREETING:
            if self._greeting_attempts >= HELLO_ATTEMPTS:
                self._fail("timeout", "the controller did not answer M110 (line numbering reset)")
                return
            self._forget_in_flight()
            self._queue_greeting()
            return
        silent = now - self._last_received_at
        if silent >= self.reply_timeout and not self._waiting_on_unbuffered():
            self._fail(
                "timeout",
                f"no answer from the controller for {silent:.1f} s; it stopped answering",
            )
            return
        # A lost ok (or a lost resend request): ask where the controller stands.
        self.stats.stalls_recovered += 1
        self._unanswered_pings += 1
        if self._ping is not None:
            self._drop_transmission(self._ping)
            self._ping = None
        self._send_ping(now)

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
                and self._phase is _Phase.RUNNING
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
        if self._phase is _Phase.FAILED:
            return
        if self._suspect_error is not None:
            if isinstance(reply, replies.Resend):
                self._suspect_error = None
            else:
                self._suspect_lines += 1
                if self._suspect_lines > SUSPECT_ERROR_LINES:
                    self._fail_suspect()
                    return
        if isinstance(reply, replies.Ok):
            self._handle_ok(reply, now)
        elif isinstance(reply, replies.Resend):
            self._handle_resend(reply.line_number, now)
        elif isinstance(reply, replies.Start):
            self._handle_start(text)
        elif isinstance(reply, replies.Error):
            if not reply.line_error:
                # Fatal, unless a resend request follows: then it was a line error whose
                # words a garbled newline cut off ("Error:chec" / "ksum mismatch...").
                self._suspect_error = (reply.text, now + max(SUSPECT_ERROR_GRACE, self._rto))
                self._suspect_lines = 0
            # A line error is told by the resend request that follows it.
        else:
            if isinstance(reply, replies.Busy):
                self._last_progress_at = now  # a long command is running: not a lost ok
            self._events.append(ControllerMessage(reply, text))

    def _handle_ok(self, reply: replies.Ok, now: float) -> None:
        self._last_progress_at = now
        if not self._in_flight:
            self.stats.unexpected_oks += 1
            return
        if (
            reply.line_number is not None
            and reply.line_number < self._next_number
            and self.flow.mode is FlowMode.BUFFERED  # unbuffered means one line in flight
        ):
            self._read_through = reply.line_number
        transmission = self._in_flight[0]
        if transmission is self._ping:
            # Nothing is sent after a ping and a ping draws no plain ok: this ok is
            # one too many (duplicated, or owed to a line already settled).
            self.stats.unexpected_oks += 1
            return
        self._drop_transmission(transmission)
        line = transmission.line
        if transmission.stale or line is None:
            return
        if not transmission.retransmitted:  # Karn: no samples from retransmissions
            self._sample_rtt(now - transmission.sent_at)
        if line.is_reset:
            return  # the ping behind it confirms the reset
        self._acknowledge(line, reply.data)

    def _handle_resend(self, number: int, now: float) -> None:
        self._last_progress_at = now
        previous = self._previous_reply
        stated_last = _stated_last_line(previous)
        if stated_last is not None and stated_last + 1 != number:
            self.stats.ignored_resend_requests += 1  # garbled: the two lines disagree
            return
        ping = self._ping
        window = TRAILING_OK_WINDOW if self._srtt is None else self._srtt * TRAILING_OK_SHARE
        self._trailing_ok_until = now + window
        if ping is not None and number == ping.number and _is_checksum_error(previous):
            self._ping_answered(ping)
            return
        # An error, its resend request and (on most firmwares) an ok answer one
        # transmission, the oldest: the ok is part of that answer, not another one.
        if self._in_flight and self._in_flight[0] is not ping:
            self._drop_transmission(self._in_flight[0])
        if stated_last is not None and self._phase is _Phase.RUNNING:
            self._confirm_through(stated_last)  # true whatever line drew it
        if self._echoes_expected and number == self._resend_target:
            # An echo of the request being served, from a line that was in transit
            # when the first came (the resend storm).
            self._echoes_expected -= 1
            self.stats.ignored_resend_requests += 1
            return
        if self._phase is _Phase.GREETING:
            # An earlier greeting's answer, or this M110 did not take (corrupted, or
            # the board still booting): the hello timeout greets again, with new numbers.
            self.stats.ignored_resend_requests += 1
            return
        corroborated = stated_last is not None
        if number == self._next_number:
            # "Send me the next line": everything sent was accepted.
            self._mark_in_flight_stale(number, now, expect_echoes=False)
            self._cursor = number
            self._end_ping()
            return
        line = self._history.get(number)
        if line is None or line.is_reset:
            self._unheld_request(number, corroborated)
            return
        if self._resend_loop(number):
            return
        self.stats.resend_requests += 1
        self._mark_in_flight_stale(number, now)
        self._cursor = number
        self._acked_through = min(self._acked_through, number - 1)
        self._end_ping()
        self._events.append(ResendRequested(number, line.command, line.tag))
        self._maybe_warn()

    def _ping_answered(self, ping: _Transmission) -> None:
        """The controller accepted every line before the ping and nothing after it."""
        self._unanswered_pings = self._ping_attempt = 0
        # Every transmission before the ping was answered (replies come in order),
        # whether or not its ok reached us; none was sent after it.
        while self._in_flight:
            if self._in_flight[0] is ping:
                self._drop_transmission(ping)
                break
            self._drop_transmission(self._in_flight[0])
        self._ping = None
        self._echoes_expected = 0
        self._confirm_through(ping.number - 1)
        self._cursor = ping.number
        if self._phase is _Phase.GREETING:
            self._phase = _Phase.RUNNING
            self._acked_through = ping.number - 1
            if not self._greeted:
                self._greeted = True
                self._events.append(ControllerReady())

    def _handle_start(self, text: str) -> None:
        if self._greeted:
            # Never resend across a reset: the controller lost its queue and state.
            self._fail("controller", "the controller reset (it sent 'start') during the job")
        else:
            # The boot banner while greeting: the ping (or its timeout) tells the rest.
            self._events.append(ControllerMessage(replies.Start(), text))

    def _unheld_request(self, number: int, corroborated: bool) -> None:
        # A garbled number must not stop a job; a real request for a line we no
        # longer hold must. The controller repeats real requests.
        seen = self._unheld_requests.get(number, 0) + 1
        self._unheld_requests[number] = seen
        if seen < 2 and not (corroborated and number < self._history_floor):
            self.stats.ignored_resend_requests += 1
            return
        held = f"{self._history_floor}..{self._next_number - 1}"
        self._fail(
            "protocol",
            f"the controller asked for line {number} again, but the host holds only "
            f"lines {held}; stopping rather than guessing",
        )

    def _resend_loop(self, number: int) -> bool:
        # Count rounds: a request counts again only once the line went out again
        # (more requests before that are echoes the storm rules did not catch).
        if number == self._loop_number:
            if not self._loop_retransmitted:
                return False
            self._loop_count += 1
        else:
            self._loop_number, self._loop_count = number, 1
        self._loop_retransmitted = False
        if self._loop_count < RESEND_LOOP_LIMIT:
            return False
        line = self._history[number]
        self._fail(
            "controller",
            f"the controller asked for line {number} ({line.command}) {self._loop_count} times "
            "in a row; the link is too noisy to go on",
        )
        return True

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

    # --- acknowledgement and confirmation -----------------------------------

    def _acknowledge(self, line: _Line, data: str = "") -> None:
        if line.number > self._acked_through:
            self._acked_through = line.number
        if line.number > self._loop_number:
            self._loop_count = 0
        self._unheld_requests.clear()  # progress: only requests repeated in a row count
        if not line.acknowledged:  # after a resend the controller may acknowledge it again
            line.acknowledged = True
            self._events.append(LineAcknowledged(line.number, line.command, line.tag, data))
        self._prune_history()

    def _confirm_through(self, number: int) -> None:
        """The controller said its last accepted line is ``number``: acknowledge up to it."""
        if number <= self._confirmed_through:
            return
        start = max(self._confirmed_through + 1, self._history_floor)
        self._confirmed_through = number
        for n in range(start, number + 1):
            line = self._history.get(n)
            if line is not None and not line.is_reset:
                self._acknowledge(line)

    def _sample_rtt(self, rtt: float) -> None:
        if self._srtt is not None and rtt < self._srtt * RTT_OUTLIER:
            # Most likely a duplicated ok taken for a line just sent: let it only
            # nudge the estimate, or the trailing-ok window would shrink to nothing.
            self._srtt *= RTT_NUDGE
            return
        if self._srtt is None:
            self._srtt, self._rttvar = rtt, rtt / 2
        else:
            self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - rtt)
            self._srtt = 0.875 * self._srtt + 0.125 * rtt
        self._rto = min(max(self._srtt + 4 * self._rttvar, MIN_RTO), MAX_RTO)
        self._unanswered_pings = 0

    # --- transmission -------------------------------------------------------

    def _begin_greeting(self) -> None:
        self._phase = _Phase.GREETING
        self._candidate = None
        self._acked_through = self._confirmed_through = self._read_through = -1
        self._greeting_attempts = 0
        self._queue_greeting()

    def _queue_greeting(self) -> None:
        """(Re)send M110 and the ping behind it; the ping's answer confirms the reset.

        Attempt ``k`` (from 0) sends ``Nk M110 Nk`` and pings for line k + 1, so that a
        late answer to an earlier attempt's ping is never taken for this one's: lines
        must not start while an earlier M110 could still reset the numbering.
        """
        base = self._greeting_attempts
        self._greeting_attempts += 1
        command = reset_command(base)
        self._history = {base: _Line(base, command, None, frame(base, command), True, True)}
        self._history_floor = base
        self._next_number = base + 1
        self._cursor = base  # the reset line first, then the ping
        self._end_ping()

    def _next_line_to_transmit(self) -> _Line | None:
        if self._phase is _Phase.GREETING:
            return self._history[self._cursor] if self._cursor < self._next_number else None
        if self._cursor < self._next_number:
            return self._history[self._cursor]
        if not self._pending:
            return None
        if self._next_number > self.line_number_limit:
            # Renumber only once the controller confirmed every line: no resend
            # request may ever name a number from before the reset.
            if self._confirmed_through == self._next_number - 1 and not self._live_in_flight:
                self._begin_greeting()
                return self._history[self._cursor]
            self._sync_requested = True
            return None
        # Numbered only once it goes out (see _transmit), so that every number
        # below _next_number has been on the wire and a ping can follow them.
        if self._candidate is None:
            command, tag, unbuffered = self._pending[0]
            number = self._next_number
            self._candidate = _Line(number, command, tag, frame(number, command), unbuffered)
        return self._candidate

    def _wants_sync_ping(self) -> bool:
        if self._phase is _Phase.GREETING:
            return self._cursor == self._next_number  # the reset line went out: confirm it
        if self._confirmed_through == self._next_number - 1:
            return False
        # After the oks of what was sent, so that an M400 before a pause has finished.
        return self._sync_requested and not self._live_in_flight

    def _window_has_room(self, size: int, now: float) -> bool:
        if self._phase is _Phase.GREETING:
            return True
        used = self._bytes_in_flight
        lines = self._live_in_flight
        if self._read_through >= 0:
            read_out_bytes, read_out_lines = self._read_out()
            used -= read_out_bytes
            lines -= read_out_lines
        if lines >= self._line_limit:
            return False
        if now >= self._stale_expire_at:
            used -= self._stale_bytes
        if used == 0:
            return True  # a line longer than the buffer still has to go, alone
        return used + size <= self._byte_limit

    def _transmit(self, line: _Line, now: float) -> None:
        if line is self._candidate:
            self._pending.popleft()
            self._history[line.number] = line
            self._next_number += 1
            self._candidate = None
        self._cursor = line.number + 1
        retransmitted = line.transmitted
        if retransmitted:
            self.stats.retransmissions += 1
            self._loop_retransmitted |= line.number == self._loop_number
        else:
            line.transmitted = True
            self.stats.lines_sent += not line.is_reset
        self._push(_Transmission(line, line.wire, now, line.number, retransmitted=retransmitted))

    def _send_ping(self, now: float) -> None:
        # The number the controller should expect next. Pings alternate between the
        # next new number (right when it has everything) and the first line not yet
        # confirmed (right when lines are missing, and it settles every reply owed
        # even then). Neither can be a duplicate that newer Marlin ignores in silence.
        if self._phase is _Phase.GREETING or self._ping_attempt % 2 == 0:
            number = self._next_number
        else:
            number = self._confirmed_through + 1
        self._ping_attempt += 1
        ping = _Transmission(None, _ping_wire(number), now, number)
        self._ping = ping
        self.stats.pings += 1
        self._push(ping)

    def _push(self, transmission: _Transmission) -> None:
        self._in_flight.append(transmission)
        self._bytes_in_flight += len(transmission.wire)
        if transmission.line is not None:
            self._live_in_flight += 1
        self.stats.bytes_sent += len(transmission.wire)
        self._outgoing += transmission.wire

    def _drop_transmission(self, transmission: _Transmission) -> None:
        self._in_flight.remove(transmission)
        self._bytes_in_flight -= len(transmission.wire)
        if transmission.stale:
            self._stale_bytes -= len(transmission.wire)
        elif transmission.line is not None:
            self._live_in_flight -= 1

    def _mark_in_flight_stale(self, number: int, now: float, expect_echoes: bool = True) -> None:
        # The transmission of line ``number`` drew this request (unless its reply was
        # counted off already); every other one in flight may draw an echo (or
        # nothing, if the controller flushed it or dropped it as a duplicate).
        cause = any(t.number == number and t.line is not None for t in self._in_flight)
        self._echoes_expected = len(self._in_flight) - cause if expect_echoes else 0
        for transmission in self._in_flight:
            if not transmission.stale:
                transmission.stale = True
                self._stale_bytes += len(transmission.wire)
                if transmission.line is not None:
                    self._live_in_flight -= 1
        self._resend_target = number
        # Refused lines leave the controller's buffer fast; a reply that never comes
        # (flushed, dropped, an ok some firmwares omit) must not hold the window shut.
        self._stale_expire_at = now + self._rto

    def _end_ping(self) -> None:
        """A resend request answers a ping too: its line is now just a stale transmission."""
        if self._ping is not None:
            self._ping = None
            self._unanswered_pings = self._ping_attempt = 0

    def _forget_in_flight(self) -> None:
        self._in_flight.clear()
        self._bytes_in_flight = self._live_in_flight = 0
        self._stale_bytes = 0
        self._ping = None

    def _read_out(self) -> tuple[int, int]:
        """Bytes and lines in flight that ADVANCED_OK says left the receive buffer.

        They wait in the command slots for their ok: counted against the buffer and
        the line limit they would leave the buffer part empty and the slots unfilled.
        """
        read_out_bytes = read_out_lines = 0
        for transmission in self._in_flight:
            if transmission.stale:
                continue
            if transmission.line is None or transmission.number > self._read_through:
                break
            read_out_bytes += len(transmission.wire)
            read_out_lines += 1
        return read_out_bytes, read_out_lines

    def _waiting_on_unbuffered(self) -> bool:
        oldest = next((t for t in self._in_flight if not t.stale and t.line is not None), None)
        return oldest is not None and oldest.line is not None and oldest.line.unbuffered

    def _prune_history(self) -> None:
        floor = self._acked_through - self.history_margin
        while self._history_floor < floor:
            self._history.pop(self._history_floor, None)
            self._history_floor += 1

    def _fail_suspect(self) -> None:
        assert self._suspect_error is not None
        self._fail("controller", f"the controller reported an error: {self._suspect_error[0]}")

    def _fail(self, kind: str, reason: str) -> None:
        self._phase = _Phase.FAILED
        oldest = self._history.get(self._acked_through + 1)
        self._failure = Failed(kind, reason, oldest.tag if oldest is not None else None)
        self.cancel_pending()
        self._events.append(self._failure)


def _ping_wire(number: int) -> bytes:
    """``N<number> M105 S<k>*9999``: refused by any controller that checks checksums."""
    for k in range(10):
        body = f"N{number} M105 S{k}".encode("ascii")
        if checksum(body) not in _PING_UNSAFE:
            return body + b"*" + _PING_CHECKSUM + b"\n"
    raise AssertionError("unreachable: ten bodies cannot all have unsafe checksums")


def _stated_last_line(reply: replies.Reply | None) -> int | None:
    """The "Last Line: L" of a Marlin line error just before a resend request."""
    if isinstance(reply, replies.Error) and reply.line_error:
        match = _LAST_LINE.search(reply.text)
        if match is not None:
            return int(match.group(1))
    return None


def _is_checksum_error(reply: replies.Reply | None) -> bool:
    return (
        isinstance(reply, replies.Error) and reply.line_error and "checksum" in reply.text.lower()
    )
