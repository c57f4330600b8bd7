"""Transmissions in flight and the room the controller's receive buffer has for more."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from repetrel_host.protocol.flow import FlowControl
from repetrel_host.protocol.history import Line


@dataclass(slots=True)
class Transmission:
    """One line (or a checksum probe, ``line`` None) put on the wire at ``sent_at``."""

    line: Line | None
    wire: bytes
    sent_at: float
    number: int
    # Stale: sent before a resend request; the controller refuses it (or has
    # dropped it), so whatever it draws acknowledges nothing.
    stale: bool = False
    retransmitted: bool = False


REFILL_FRACTION = 8


class Window:
    """What the controller has not answered yet, counted in lines and bytes.

    Live transmissions are lines that will draw an ok; stale ones and probes are
    counted in bytes only (they still occupy the receive buffer for a while).
    """

    __slots__ = (
        "batch_bytes",
        "batch_lines",
        "byte_limit",
        "bytes",
        "in_flight",
        "line_limit",
        "live",
        "read_through",
        "stale_bytes",
        "stale_expire_at",
    )

    def __init__(self, flow: FlowControl) -> None:
        self.line_limit = flow.line_limit  # read for every line: kept at hand
        self.byte_limit = flow.byte_limit
        # A refill waits for room for an eighth of the window while lines are in flight:
        # a line written for each ok would cost a write, and a wakeup of the controller's
        # reader, per line (with a window of a few lines it changes nothing).
        self.batch_lines = max(1, self.line_limit // REFILL_FRACTION)
        self.batch_bytes = self.byte_limit // REFILL_FRACTION
        self.in_flight: deque[Transmission] = deque()
        self.bytes = 0
        self.live = 0  # transmissions neither stale nor probes
        self.stale_bytes = 0
        self.stale_expire_at = 0.0
        # ADVANCED_OK's N: the last line the controller took out of its receive buffer.
        # Only for flow control (a garbled N costs a resend, never a line).
        self.read_through = -1

    def limit_bytes(self, byte_limit: int) -> None:
        """Keep at most ``byte_limit`` bytes in flight (if that is fewer), and batch to match."""
        self.byte_limit = min(self.byte_limit, byte_limit)
        self.batch_bytes = self.byte_limit // REFILL_FRACTION

    def push(self, transmission: Transmission) -> None:
        self.in_flight.append(transmission)
        self.bytes += len(transmission.wire)
        if transmission.line is not None:
            self.live += 1

    def drop(self, transmission: Transmission) -> None:
        self.in_flight.remove(transmission)
        self._uncount(transmission)

    def pop_oldest(self) -> Transmission:
        """Drop the oldest transmission (the one a reply answers) and return it."""
        transmission = self.in_flight.popleft()
        self._uncount(transmission)
        return transmission

    def _uncount(self, transmission: Transmission) -> None:
        size = len(transmission.wire)
        self.bytes -= size
        if transmission.stale:
            self.stale_bytes -= size
        elif transmission.line is not None:
            self.live -= 1

    def discard(self, transmission: Transmission) -> None:
        """Drop ``transmission`` if an answer has not dropped it already."""
        if any(t is transmission for t in self.in_flight):
            self.drop(transmission)

    def drop_through(self, last: Transmission) -> None:
        """Drop every transmission up to and including ``last``: all were answered."""
        while self.in_flight:
            if self.pop_oldest() is last:
                return

    def mark_stale(self, expire_at: float) -> None:
        """Nothing in flight will acknowledge anything any more (a resend request came)."""
        for transmission in self.in_flight:
            if not transmission.stale:
                transmission.stale = True
                self.stale_bytes += len(transmission.wire)
                if transmission.line is not None:
                    self.live -= 1
        # Refused lines leave the controller's buffer fast; a reply that never comes
        # (flushed, dropped, an ok some firmwares omit) must not hold the window shut.
        self.stale_expire_at = expire_at

    def forget(self) -> None:
        self.in_flight.clear()
        self.bytes = self.live = self.stale_bytes = 0

    def wants_refill(self, now: float) -> bool:
        """Nothing live in flight (no ok is coming to wake the host), or room for a batch."""
        if not self.live:
            return True
        return self.has_room(self.batch_bytes, now, self.batch_lines)

    def has_room(self, size: int, now: float, lines_wanted: int = 1) -> bool:
        used = self.bytes
        lines = self.live
        if self.read_through >= 0:
            read_out_bytes, read_out_lines = self._read_out()
            used -= read_out_bytes
            lines -= read_out_lines
        if lines + lines_wanted > self.line_limit:
            return False
        if now >= self.stale_expire_at:
            used -= self.stale_bytes
        if used == 0:
            return True  # a line longer than the buffer still has to go, alone
        return used + size <= self.byte_limit

    def oldest_live(self) -> Transmission | None:
        return next((t for t in self.in_flight if not t.stale), None)

    def waiting_on_unbuffered(self) -> bool:
        """The oldest live line (a probe aside) waits for the machine (G28, M109...)."""
        for transmission in self.in_flight:
            line = transmission.line
            if not transmission.stale and line is not None and not line.is_probe:
                return line.unbuffered
        return False

    def _read_out(self) -> tuple[int, int]:
        """Bytes and lines in flight that ADVANCED_OK says left the receive buffer.

        They wait in the command slots for their ok: counted against the buffer and
        the line limit they would leave the buffer part empty and the slots unfilled.
        """
        read_out_bytes = read_out_lines = 0
        for transmission in self.in_flight:
            if transmission.stale:
                continue
            if transmission.line is None or transmission.number > self.read_through:
                break
            read_out_bytes += len(transmission.wire)
            read_out_lines += 1
        return read_out_bytes, read_out_lines
