"""The host side of the line protocol as a pure state machine (no I/O, no clock).

Feed it commands with :meth:`HostProtocol.send`, bytes from the controller with
:meth:`HostProtocol.receive_data`, and the current time where it matters; take
bytes to write from :meth:`HostProtocol.data_to_send` and happenings from
:meth:`HostProtocol.next_event`.

How delivery stays exact: every line carries a number and a checksum, and the
controller executes a line only when its number is the previous one plus one.
The host keeps each sent line until it is acknowledged and, when the controller
asks for line ``n`` again, sends ``n`` and everything after it once more
(go-back-N). Replies come in order, one ``ok`` per received line, so each
``ok`` answers the oldest transmission still in flight.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

from repetrel_host.errors import ProtocolError
from repetrel_host.gcode.commands import is_unbuffered
from repetrel_host.protocol import replies
from repetrel_host.protocol.framing import frame, is_reset_command, reset_command

# Marlin and RepRap count line numbers in a C long, Repetier modulo 65536: renumber
# before 65536 so every firmware agrees on the numbers.
DEFAULT_LINE_NUMBER_LIMIT = 65535
# Acknowledged lines kept for resend requests that come late. A controller only
# asks for a line it has not accepted, which is always unacknowledged; the margin
# covers firmwares that acknowledge on receipt (Repetier) and ask later.
DEFAULT_HISTORY_MARGIN = 256
# The longest an acknowledgement of a buffered command may take: the controller
# holds it back while its planner is full, and one slow move can last seconds.
DEFAULT_REPLY_TIMEOUT = 30.0
# Waiting for the answer to the opening M110: boards that reset when the port
# opens need about two seconds to boot; M110 is idempotent, so we repeat it.
HELLO_TIMEOUT = 2.0
HELLO_ATTEMPTS = 5


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
    N bytes holds N - 1.
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
    """The controller acknowledged the opening M110: it is there and numbering agrees."""


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
class Failed:
    """The stream cannot go on. Nothing more is sent; ``reason`` is one sentence.

    ``kind`` is ``"controller"`` (an error or a reset reported by the controller),
    ``"protocol"`` (a request the host cannot honour) or ``"timeout"``.
    """

    kind: str
    reason: str
    tag: object = None  # the oldest unacknowledged line's tag, where the trouble most likely is


Event = ControllerReady | LineAcknowledged | ResendRequested | ControllerMessage | Failed


# --- state ----------------------------------------------------------------------


class _Phase(Enum):
    IDLE = "idle"  # start() not called yet
    RESETTING = "resetting"  # the M110 that sets numbering is in flight
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
    line: _Line
    sent_at: float
    # Stale: sent before a resend request, so the controller refuses it; its
    # reply (an error, a resend request and an ok) acknowledges nothing.
    stale: bool = False


@dataclass(slots=True)
class Statistics:
    lines_sent: int = 0  # first transmissions
    retransmissions: int = 0
    resend_requests: int = 0  # honoured requests
    ignored_resend_requests: int = 0  # echoes of one request from lines in transit
    unexpected_oks: int = 0
    bytes_sent: int = 0


class HostProtocol:
    """Numbering, history, window and go-back-N resend for one controller."""

    def __init__(
        self,
        flow: FlowControl | None = None,
        *,
        line_number_limit: int = DEFAULT_LINE_NUMBER_LIMIT,
        history_margin: int = DEFAULT_HISTORY_MARGIN,
        reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    ) -> None:
        if line_number_limit < 2:
            raise ValueError("line_number_limit must be at least 2")
        self.flow = flow or FlowControl()
        self.line_number_limit = line_number_limit
        self.history_margin = history_margin
        self.reply_timeout = reply_timeout
        self.stats = Statistics()
        self._phase = _Phase.IDLE
        self._pending: deque[tuple[str, object]] = deque()
        self._history: dict[int, _Line] = {}
        self._history_floor = 0  # lowest number still held
        self._next_number = 0  # number the next new line gets
        self._cursor = 0  # next number to transmit (< _next_number while resending)
        self._reset_due = False  # the reset line must be (re)transmitted
        self._in_flight: deque[_Transmission] = deque()
        self._bytes_in_flight = 0
        self._stale_in_flight = 0
        self._resend_target: int | None = None
        self._acked_through = -1
        self._hello_attempts = 0
        self._greeted = False  # the opening M110 was acknowledged
        self._last_received_at = 0.0
        self._receive_buffer = bytearray()
        self._outgoing = bytearray()
        self._events: deque[Event] = deque()
        self._failure: Failed | None = None

    # --- feeding ------------------------------------------------------------

    def start(self, now: float) -> None:
        """Begin: the first line on the wire will be ``N0 M110 N0``."""
        if self._phase is not _Phase.IDLE:
            raise ProtocolError("the protocol was already started")
        self._last_received_at = now
        self._begin_reset()

    def send(self, command: str, tag: object = None) -> None:
        """Queue one clean command (see :func:`clean_line`); ``tag`` comes back in events."""
        if is_reset_command(command):
            raise ProtocolError("M110 sets line numbers, which the host owns; it cannot be queued")
        self._pending.append((command, tag))

    def cancel_pending(self) -> int:
        """Drop queued lines not yet on the wire; return how many were dropped."""
        dropped = len(self._pending)
        self._pending.clear()
        return dropped

    @property
    def wants_lines(self) -> bool:
        """True when the queue is short enough that a new line could go out soon."""
        return self._phase is not _Phase.FAILED and len(self._pending) < self.flow.line_limit

    @property
    def is_done(self) -> bool:
        """Every line queued so far was transmitted and acknowledged."""
        return (
            self._phase is _Phase.RUNNING
            and not self._pending
            and self._cursor == self._next_number
            and self._acked_through == self._next_number - 1
        )

    @property
    def failure(self) -> Failed | None:
        return self._failure

    # --- output -------------------------------------------------------------

    def data_to_send(self, now: float) -> bytes:
        """Bytes to write now: every line the window has room for."""
        while self._phase in (_Phase.RESETTING, _Phase.RUNNING):
            line = self._next_line_to_transmit()
            if line is None or not self._window_has_room(len(line.wire)):
                break
            self._transmit(line, now)
        data = bytes(self._outgoing)
        self._outgoing.clear()
        return data

    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timeout` wants to be called, or None."""
        if self._phase is _Phase.FAILED or not self._in_flight:
            return None
        oldest = self._in_flight[0]
        if self._phase is _Phase.RESETTING:
            return max(self._last_received_at, oldest.sent_at) + HELLO_TIMEOUT
        if oldest.line.unbuffered and not oldest.stale:
            return None  # a long wait here is the command working, not a failure
        return max(self._last_received_at, oldest.sent_at) + self.reply_timeout

    def handle_timeout(self, now: float) -> None:
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return
        if self._phase is _Phase.RESETTING and self._hello_attempts < HELLO_ATTEMPTS:
            # Assume the M110 was lost (a board still booting); repeating it is harmless.
            # Were its ok only late, one ok would be left over: issue 4's fault model.
            self._forget_in_flight()
            self._reset_due = True
            return
        if self._phase is _Phase.RESETTING:
            self._fail("timeout", "the controller did not answer M110 (line numbering reset)")
        else:
            line = self._in_flight[0].line
            self._fail(
                "timeout",
                f"no answer from the controller for {now - self._last_received_at:.1f} s "
                f"while line {line.number} ({line.command}) waited for its acknowledgement",
            )

    # --- input --------------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes read from the controller."""
        if not data:
            return
        self._last_received_at = now
        self._receive_buffer += data
        while True:
            end = self._receive_buffer.find(b"\n")
            if end < 0:
                break
            raw = bytes(self._receive_buffer[:end])
            del self._receive_buffer[: end + 1]
            text = raw.decode("ascii", errors="replace").strip()
            if text:
                self._handle_reply(replies.classify(text), text)

    # --- internals ----------------------------------------------------------

    def _handle_reply(self, reply: replies.Reply, text: str) -> None:
        if self._phase is _Phase.FAILED:
            return
        if isinstance(reply, replies.Ok):
            self._handle_ok(reply)
        elif isinstance(reply, replies.Resend):
            self._handle_resend(reply.line_number)
        elif isinstance(reply, replies.Start):
            self._handle_start(text)
        elif isinstance(reply, replies.Error) and not reply.line_error:
            self._fail("controller", f"the controller reported an error: {reply.text}")
        else:
            self._events.append(ControllerMessage(reply, text))

    def _handle_ok(self, reply: replies.Ok) -> None:
        if not self._in_flight:
            self.stats.unexpected_oks += 1
            return
        transmission = self._in_flight.popleft()
        line = transmission.line
        self._bytes_in_flight -= len(line.wire)
        if transmission.stale:
            self._stale_in_flight -= 1
            return
        if line.is_reset:
            self._phase = _Phase.RUNNING
            self._acked_through = line.number
            if not self._greeted:
                self._greeted = True
                self._events.append(ControllerReady())
            return
        if line.number > self._acked_through:
            self._acked_through = line.number
        if not line.acknowledged:  # after a resend the controller may acknowledge it again
            line.acknowledged = True
            self._events.append(LineAcknowledged(line.number, line.command, line.tag, reply.data))
        self._prune_history()

    def _handle_resend(self, number: int) -> None:
        if self._stale_in_flight and number == self._resend_target:
            # An echo of the request we are already serving, from a line that
            # was in transit when the first came (the resend storm).
            self.stats.ignored_resend_requests += 1
            return
        if self._phase is _Phase.RESETTING:
            self._mark_in_flight_stale(number)
            self._reset_due = True
            return
        line = self._history.get(number)
        if line is None or line.is_reset:
            held = f"{self._history_floor}..{self._next_number - 1}"
            self._fail(
                "protocol",
                f"the controller asked for line {number} again, but the host holds only "
                f"lines {held}; stopping rather than guessing",
            )
            return
        self.stats.resend_requests += 1
        self._mark_in_flight_stale(number)
        self._cursor = number
        self._acked_through = min(self._acked_through, number - 1)
        self._events.append(ResendRequested(number, line.command, line.tag))

    def _handle_start(self, text: str) -> None:
        # While greeting, 'start' is the boot banner: it came either before our
        # M110 (whose ok follows) or after it (the M110 was lost, and the hello
        # timeout repeats it). Guessing which would risk an extra ok.
        if self._greeted:
            # Never resend across a reset: the controller lost its queue and state.
            self._fail("controller", "the controller reset (it sent 'start') during the job")
        else:
            self._events.append(ControllerMessage(replies.Start(), text))

    def _mark_in_flight_stale(self, number: int) -> None:
        for transmission in self._in_flight:
            if not transmission.stale:
                transmission.stale = True
                self._stale_in_flight += 1
        self._resend_target = number

    def _forget_in_flight(self) -> None:
        self._in_flight.clear()
        self._bytes_in_flight = 0
        self._stale_in_flight = 0

    def _begin_reset(self) -> None:
        self._phase = _Phase.RESETTING
        self._history.clear()
        self._history_floor = 0
        command = reset_command(0)
        self._history[0] = _Line(0, command, None, frame(0, command), True, is_reset=True)
        self._next_number = 1
        self._cursor = 1
        self._acked_through = -1
        self._hello_attempts = 0
        self._reset_due = True

    def _next_line_to_transmit(self) -> _Line | None:
        if self._reset_due:
            return self._history[0]
        if self._phase is not _Phase.RUNNING:
            return None
        if self._cursor < self._next_number:
            return self._history[self._cursor]
        if not self._pending:
            return None
        if self._next_number > self.line_number_limit:
            # Renumber once everything in flight is answered, so that no resend
            # request can ever name a number from before the reset.
            if not self._in_flight:
                self._begin_reset()
                return self._history[0]
            return None
        command, tag = self._pending.popleft()
        number = self._next_number
        line = _Line(number, command, tag, frame(number, command), is_unbuffered(command))
        self._history[number] = line
        self._next_number += 1
        return line

    def _window_has_room(self, size: int) -> bool:
        if not self._in_flight:
            return True  # a line longer than the buffer still has to go, alone
        if len(self._in_flight) >= self.flow.line_limit:
            return False
        return self._bytes_in_flight + size <= self.flow.byte_limit

    def _transmit(self, line: _Line, now: float) -> None:
        if line.is_reset:
            self._reset_due = False
            self._hello_attempts += 1
        else:
            self._cursor = line.number + 1
            if line.transmitted:
                self.stats.retransmissions += 1
            else:
                line.transmitted = True
                self.stats.lines_sent += 1
        self._in_flight.append(_Transmission(line, now))
        self._bytes_in_flight += len(line.wire)
        self.stats.bytes_sent += len(line.wire)
        self._outgoing += line.wire

    def _prune_history(self) -> None:
        floor = self._acked_through - self.history_margin
        while self._history_floor < floor:
            self._history.pop(self._history_floor, None)
            self._history_floor += 1

    def _fail(self, kind: str, reason: str) -> None:
        self._phase = _Phase.FAILED
        oldest = self._history.get(self._acked_through + 1)
        self._failure = Failed(kind, reason, oldest.tag if oldest is not None else None)
        self._pending.clear()
        self._events.append(self._failure)
