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
        self._transmitted = 0  # lines put on the wire, the host's own too
        self._unconfirmed = 0  # lines sent since the last sync that confirmed them
        self._sync_at = 0  # _transmitted once the sync's M115 went
        self._sync_requested = False
        self._sync: _Sent | None = None  # the M115 whose answer is awaited
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
        self._push(_Sent(None, command, None, len(wire), host_line=True), wire)

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
        return not self._pending and not self._in_flight and self._unconfirmed == 0

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
                self._transmit(command, tag)
            if (
                self._sync_requested
                and not self._pending
                and self._unconfirmed
                and self._sync is None
                and self._has_room()
            ):
                self._sync = self._transmit(SYNC_COMMAND, None, host_line=True)
                self._sync_at = self._transmitted
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

    def _transmit(self, command: str, tag: object, host_line: bool = False) -> _Sent:
        number = self._next_number if self.numbered else None
        self._next_number += 1
        wire = frame(command, number, self.checksum)
        sent = _Sent(number, command, tag, len(wire), host_line)
        self._push(sent, wire)
        self._transmitted += 1
        self._unconfirmed += 1
        if not host_line:
            self.stats.lines_sent += 1
        return sent

    def _push(self, sent: _Sent, wire: bytes) -> None:
        if not self._in_flight:
            self._last_progress_at = max(self._last_progress_at, self._last_sent_at)
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
        sent = self._in_flight.popleft()
        self._in_flight_bytes -= sent.size
        self._last_progress_at = now
        self._status_asked = 0
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
        if "FIRMWARE_NAME:" in text and self._sync is not None:
            # The sync's M115 ran: so did every line sent before it.
            self._sync = None
            self._sync_requested = False
            self._unconfirmed = self._transmitted - self._sync_at  # those sent after it
        if isinstance(reply, replies.HyrelReport) and reply.tag == "ER" and _FATAL.search(text):
            # A line refused cannot be sent again in its place; the watchdog stopped the
            # extruders: the job cannot go on as written.
            self._fail(FailureKind.CONTROLLER, f"the controller says: {text}")
            return
        self._events.append(ControllerMessage(reply, text))

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
        elif now >= self._last_sent_at + KEEPALIVE:
            self._outgoing.append(Control.WATCHDOG)

    def _fail(self, kind: FailureKind, reason: str) -> None:
        oldest = next((s for s in self._in_flight if not s.host_line), None)
        self._failure = Failed(kind, reason, oldest.tag if oldest is not None else None)
        self._phase = Phase.FAILED
        self._events.append(self._failure)
