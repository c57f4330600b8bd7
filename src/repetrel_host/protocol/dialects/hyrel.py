"""Hyrel's own link, the host's side: ACK credit, control bytes, tagged messages (sans-IO).

PROTOCOL-NOTES.md §4. The controller answers every line it receives with one ACK byte
while its receive buffer has headroom: the window is credit, counted in lines and bytes
as the RepRap dialect counts them, and each ACK releases the oldest line on the wire.
There is no resend: a line the controller refuses (its checksum) cannot be sent again in
its place, so the stream fails, naming it.

An ACK says "received", not "run". What has run is learned from the controller's own
answers: when every line sent must be confirmed (the end of a job, before a host action)
the host sends ``M115``, whose identity line (``FIRMWARE_NAME:>Hy: ...``) the controller
writes when it processes it, after every line before it was processed (moves planned,
waits such as a heat-up or a dwell over). Up to 8 KB of job may wait in the controller
when the last ACK comes: the job ends with that answer, the link kept alive until then.

The controller stops its extruders after 30 s without a byte from the host: the dialect
sends the watchdog byte whenever it has been quiet for :data:`KEEPALIVE` seconds, through
heat-ups, dwells and pauses. While lines wait for their ACKs it asks for a status report
(0x05) now and then: an answer means the controller is there, its buffer full behind a
long command; none, several times, means it is gone.
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass
from enum import Enum

from repetrel_host.errors import UsageError
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    Event,
    Failed,
    FailureKind,
    LineAcknowledged,
    ProbeKind,
)
from repetrel_host.protocol.flow import FlowControl
from repetrel_host.protocol.hyrel import Control, HostReceiver, frame, urgent

HELLO_TIMEOUT = 2.0  # for the ping's answer
HELLO_ATTEMPTS = 5
KEEPALIVE = 10.0  # the longest quiet from the host: well inside the 30 s watchdog
STATUS_AFTER = 5.0  # lines waiting this long for an ACK: ask whether the controller is there
STATUS_ATTEMPTS = 4  # unanswered status requests in a row: it is gone
SYNC_COMMAND = "M115"  # answered when processed: every line before it ran
SYNC_RETRY = 30.0  # a sync unanswered this long, nothing in flight: its answer was lost
RECENT = 1024  # lines remembered by number, to name the one an error report names
_LINE_NUMBER = re.compile(r"\bline\s+(\d+)|\bN(\d+)\b", re.IGNORECASE)
_FATAL = re.compile(r"checksum|watchdog", re.IGNORECASE)


class Phase(Enum):
    IDLE = "idle"
    GREETING = "greeting"
    RUNNING = "running"
    FAILED = "failed"


@dataclass(slots=True)
class _Sent:
    """A line on the wire, waiting for its ACK."""

    number: int | None
    command: str
    tag: object
    size: int
    host_line: bool = False  # the sync's M115, an urgent line: not the caller's
    lines_before: int = 0  # the caller's lines sent before this one
    seq: int = 0  # its place on the wire, the host's lines counted


class HyrelDialect:
    """The session's dialect for a Hyrel controller on its own link.

    ``numbered``: lines carry ``N<n>``, so that the controller's reports name them;
    ``checksum``: they carry the additive checksum too (a mismatch fails the stream).
    """

    def __init__(
        self, flow: FlowControl | None = None, numbered: bool = True, checksum: bool = False
    ) -> None:
        self.flow = flow or FlowControl()
        self.numbered = numbered
        self.checksum = checksum
        self.stats = Statistics()
        self._phase = Phase.IDLE
        self._pending: deque[tuple[str, object]] = deque()
        self._in_flight: deque[_Sent] = deque()
        self._in_flight_bytes = 0
        self._next_number = 1
        self._lines_sent = 0  # the caller's lines put on the wire
        self._seq = 0  # every line put on the wire
        self._confirmed = 0  # of those, how many are known to have run
        self._sync_requested = False
        # Every M115 on the wire, the caller's and the host's syncs, in order: each
        # "FIRMWARE_NAME:" answer is the oldest one's.
        self._m115s: deque[_Sent] = deque()
        self._sync_sent_at: float | None = None  # the last sync, while one is unanswered
        self._recent: dict[int, object] = {}  # line number -> tag, of the last RECENT lines
        self._receiver = HostReceiver()
        self._outgoing = bytearray()
        self._events: deque[Event] = deque()
        self._failure: Failed | None = None
        self._hello_attempts = 0
        self._hello_deadline = 0.0
        self._last_sent_at = 0.0
        self._last_progress_at = 0.0  # an ACK, an answer: the controller is there
        self._status_asked = 0

    # --- feeding ----------------------------------------------------------------

    def start(self, now: float) -> None:
        """Ping the controller; its ``>Hy:`` answer opens the stream."""
        if self._phase is not Phase.IDLE:
            raise UsageError("the dialect was already started")
        self._last_sent_at = self._last_progress_at = now
        self._ping(now)

    def send(self, command: str, tag: object = None) -> None:
        if command_word(command) == "M110":
            raise UsageError("M110 sets line numbers, which the host owns; it cannot be queued")
        self._pending.append((command, tag))

    def send_urgent(self, command: str) -> None:
        """Ahead of everything the controller holds (0x09 first)."""
        wire = urgent(frame(command))
        sent = _Sent(None, command, None, len(wire), True, self._lines_sent)
        self._push(sent, wire, self._last_sent_at)

    def request_sync(self) -> None:
        self._sync_requested = True

    def cancel_pending(self) -> list[tuple[str, object]]:
        dropped = list(self._pending)
        self._pending.clear()
        return dropped

    @property
    def wants_lines(self) -> bool:
        return self._phase is not Phase.FAILED and len(self._pending) < self.flow.line_limit

    @property
    def is_done(self) -> bool:
        """Every line queued so far was received and ran (the sync's answer says so)."""
        return not self._pending and not self._in_flight and self._confirmed == self._lines_sent

    @property
    def is_ready(self) -> bool:
        return self._phase is Phase.RUNNING

    @property
    def probe(self) -> ProbeKind:
        return ProbeKind.COMMAND  # a real command whose answer confirms

    @property
    def failure(self) -> Failed | None:
        return self._failure

    # --- output -----------------------------------------------------------------

    def data_to_send(self, now: float) -> bytes:
        if self._phase is Phase.RUNNING:
            while self._pending and self._has_room():
                command, tag = self._pending.popleft()
                self._transmit(command, tag, now)
            if (
                self._sync_requested
                and not self._pending
                and self._confirmed < self._lines_sent
                and self._sync_sent_at is None
                and self._has_room()
            ):
                self._transmit(SYNC_COMMAND, None, now, host_line=True)
                self._sync_sent_at = now
        if not self._outgoing:
            return b""
        self._last_sent_at = now
        data = bytes(self._outgoing)
        self._outgoing.clear()
        return data

    def _has_room(self) -> bool:
        flow = self.flow
        if not self._in_flight:
            return True  # a line longer than the window still goes, alone
        command = self._pending[0][0] if self._pending else SYNC_COMMAND
        size = len(command) + 1  # and its newline
        if self.numbered:
            size += len(str(self._next_number)) + 2  # "N<n> "
        if self.checksum:
            size += 7  # "*<sum>": a line of 96 ASCII bytes sums to at most 5 digits
        return (
            len(self._in_flight) < flow.line_limit
            and self._in_flight_bytes + size <= flow.byte_limit
        )

    def _transmit(self, command: str, tag: object, now: float, host_line: bool = False) -> None:
        number = self._next_number if self.numbered else None
        self._next_number += 1
        wire = frame(command, number, self.checksum)
        sent = _Sent(number, command, tag, len(wire), host_line, self._lines_sent)
        self._push(sent, wire, now)
        if command_word(command) == "M115":
            self._m115s.append(sent)
        if number is not None:
            self._recent[number] = tag
            self._recent.pop(number - RECENT, None)
        if not host_line:
            self._lines_sent += 1
            self.stats.lines_sent += 1

    def _push(self, sent: _Sent, wire: bytes, now: float) -> None:
        self._seq += 1
        sent.seq = self._seq
        if not self._in_flight:
            self._last_progress_at = now  # the first line waiting: its ACK is due from now
        self._in_flight.append(sent)
        self._in_flight_bytes += sent.size
        self._outgoing += wire
        self.stats.bytes_sent += len(wire)

    def _ping(self, now: float) -> None:
        self._phase = Phase.GREETING
        self._hello_attempts += 1
        self._hello_deadline = now + HELLO_TIMEOUT
        self._outgoing.append(Control.PING)
        self.stats.pings += 1

    # --- input ------------------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        if not data or self._phase is Phase.FAILED:
            return
        lines = self._receiver.feed(data)
        for _ in range(self._receiver.take_acks()):
            self._acknowledged(now)
        for text in lines:
            self._handle_line(text, now)
            if self._failure is not None:
                return

    def _acknowledged(self, now: float) -> None:
        if not self._in_flight:
            self.stats.unexpected_oks += 1  # an ACK nothing was owed
            return
        self._last_progress_at = now
        self._status_asked = 0
        self._acknowledged_line(self._in_flight[0])

    def _acknowledged_line(self, sent: _Sent) -> None:
        self._in_flight.popleft()
        self._in_flight_bytes -= sent.size
        if not sent.host_line:
            number = sent.number if sent.number is not None else -1
            self._events.append(LineAcknowledged(number, sent.command, sent.tag, ""))

    def _handle_line(self, text: str, now: float) -> None:
        reply = replies.classify(text)
        self._last_progress_at = now
        self._status_asked = 0
        if isinstance(reply, replies.HyrelReport) and reply.tag == "HY":
            if self._phase is Phase.GREETING:
                self._phase = Phase.RUNNING
                self._events.append(ControllerReady(ProbeKind.COMMAND))
            return
        if "FIRMWARE_NAME:" in text and self._m115s and self._answered(self._m115s.popleft()):
            return  # the host's own sync: not the caller's business
        if isinstance(reply, replies.HyrelReport) and reply.tag == "ER" and _FATAL.search(text):
            # A line refused cannot be sent again in its place; the watchdog stopped the
            # extruders: the job cannot go on as written.
            self._fail(FailureKind.CONTROLLER, f"the controller says: {text}", _named(text))
            return
        self._events.append(ControllerMessage(reply, text))

    def _answered(self, m115: _Sent) -> bool:
        """An M115 ran, so did every line before it: it and they were received, whatever
        ACKs were lost on the way (their lines leave the window). True for a host's sync."""
        ran = m115.lines_before + (0 if m115.host_line else 1)  # a caller's M115 ran too
        self._confirmed = max(self._confirmed, ran)
        while self._in_flight and self._in_flight[0].seq <= m115.seq:
            self.stats.unexpected_oks += 1  # counted the other way round: an ACK lost
            self._acknowledged_line(self._in_flight[0])
        if m115.host_line:
            self._sync_sent_at = None
            if self._confirmed == self._lines_sent:
                self._sync_requested = False
        return m115.host_line

    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    # --- time -------------------------------------------------------------------

    def next_deadline(self) -> float | None:
        phase = self._phase
        if phase is Phase.GREETING:
            return self._hello_deadline
        if phase is not Phase.RUNNING:
            return None
        deadline = self._last_sent_at + KEEPALIVE
        if self._in_flight:
            deadline = min(deadline, self._last_progress_at + STATUS_AFTER)
        elif self._sync_sent_at is not None:
            deadline = min(deadline, self._sync_sent_at + SYNC_RETRY)
        return deadline

    def handle_timeout(self, now: float) -> None:
        phase = self._phase
        if phase is Phase.GREETING:
            if now < self._hello_deadline:
                return
            if self._hello_attempts >= HELLO_ATTEMPTS:
                self._fail(
                    FailureKind.TIMEOUT,
                    f"no answer to {HELLO_ATTEMPTS} pings (0x07): is a Hyrel controller "
                    "there, on its own link?",
                )
                return
            self._ping(now)
            return
        if phase is not Phase.RUNNING:
            return
        if self._in_flight and now >= self._last_progress_at + STATUS_AFTER:
            if self._status_asked >= STATUS_ATTEMPTS:
                self._fail(
                    FailureKind.TIMEOUT,
                    f"the controller fell silent: no ACK and no answer to "
                    f"{STATUS_ATTEMPTS} status requests",
                )
                return
            self._status_asked += 1
            self._last_progress_at = now  # the next request after as long again
            self._outgoing.append(Control.STATUS)
        elif (
            not self._in_flight
            and self._sync_sent_at is not None
            and now >= self._sync_sent_at + SYNC_RETRY
        ):
            self._sync_sent_at = None  # its answer was lost (or it waits long): ask again
        elif now >= self._last_sent_at + KEEPALIVE:
            self._outgoing.append(Control.WATCHDOG)

    def _fail(self, kind: FailureKind, reason: str, number: int | None = None) -> None:
        if number is not None and number in self._recent:
            tag = self._recent[number]  # the line the report names
        else:
            oldest = next((s for s in self._in_flight if not s.host_line), None)
            tag = oldest.tag if oldest is not None else None
        self._failure = Failed(kind, reason, tag)
        self._phase = Phase.FAILED
        self._events.append(self._failure)


def _named(text: str) -> int | None:
    """The line number an error report names ("line 12", "N12"), if any."""
    match = _LINE_NUMBER.search(text)
    if match is None:
        return None
    return int(match.group(1) or match.group(2))
