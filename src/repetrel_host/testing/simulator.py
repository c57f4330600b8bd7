"""A Marlin-style controller as a pure simulation with explicit time.

The same engine runs behind the pty fake controller (real time) and in
in-memory tests (simulated time). It models the link (bandwidth and latency
each way), the receive buffer in bytes (dropping bytes on overflow like a UART,
or pushing back like USB), the command slots, the planner, and how long each
command takes. It acknowledges a buffered command once it is planned, an
unbuffered one once the planner drained and the command finished.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from repetrel_host.gcode.commands import command_word, is_unbuffered
from repetrel_host.protocol.controller import Accepted, ControllerProtocol, Rejected

_MOVES = frozenset({"G0", "G1", "G2", "G3", "G5"})
_DWELL = re.compile(r"\b([PS])\s*(\d+(?:\.\d*)?)", re.IGNORECASE)


class Overflow(Enum):
    """What the receive buffer does with bytes that do not fit."""

    DROP = "drop"  # a UART: the bytes are lost
    BLOCK = "block"  # USB: the sender is held back


@dataclass(frozen=True, slots=True)
class ControllerSettings:
    """The simulated controller and link. Times in seconds, sizes in bytes."""

    bandwidth: float | None = None  # bytes per second each way; None: unlimited
    latency: float = 0.0  # one-way delay of the link
    rx_buffer: int = 128  # receive buffer; a ring buffer of N bytes holds N - 1
    overflow: Overflow = Overflow.DROP
    slots: int = 4  # command slots (Marlin's BUFSIZE)
    planner: int = 16  # planner blocks
    move_time: float = 0.0  # how long one move takes to execute
    command_time: float = 0.0  # how long any other command takes
    banner: bool = True  # say "start" at boot


@dataclass(slots=True)
class _Command:
    text: str
    word: str
    started: bool = False


class ControllerSimulator:
    """Feed bytes with :meth:`receive`, run with :meth:`advance`, read :meth:`take_output`."""

    def __init__(
        self,
        settings: ControllerSettings | None = None,
        *,
        now: float = 0.0,
        on_execute: Callable[[str], None] | None = None,
    ) -> None:
        self.settings = settings or ControllerSettings()
        self.protocol = ControllerProtocol()
        self.executed: list[str] = []
        self._on_execute = on_execute or self.executed.append
        self._inbound: deque[tuple[float, bytes]] = deque()
        self._inbound_bytes = 0
        self._in_wire_free = now
        self._rx = bytearray()
        self._queue: deque[_Command] = deque()
        self._planner: deque[float] = deque()  # finish time of each planned move
        self._planner_end = now
        self._busy_until = now
        self._last_step = now
        self._outbound: deque[tuple[float, bytes]] = deque()
        self._out_wire_free = now
        self.bytes_dropped = 0
        self.lines_rejected = 0
        if self.settings.banner:
            self._reply(b"start\n", now)

    # --- link ---------------------------------------------------------------

    def room(self) -> int:
        """Bytes the controller can take now without dropping any (on the wire or buffered)."""
        capacity = self.settings.rx_buffer - 1
        return max(0, capacity - len(self._rx) - self._inbound_bytes)

    def receive(self, data: bytes, now: float) -> None:
        """Bytes the host wrote at ``now``; they reach the receive buffer after the wire's delay.

        Each line arrives on its own, so the firmware can take a line out of the
        buffer before the next one lands, as it does on a real wire.
        """
        start = max(now, self._in_wire_free)
        begin = 0
        while begin < len(data):
            end = data.find(b"\n", begin) + 1 or len(data)
            piece = data[begin:end]
            start += self._wire_time(len(piece))
            self._inbound.append((start + self.settings.latency, piece))
            self._inbound_bytes += len(piece)
            begin = end
        self._in_wire_free = start

    def take_output(self, now: float) -> bytes:
        """Replies that have reached the host by ``now``."""
        out = bytearray()
        while self._outbound and self._outbound[0][0] <= now:
            out += self._outbound.popleft()[1]
        return bytes(out)

    def next_wakeup(self) -> float | None:
        """The next time something happens without new input, or None."""
        times = [self._next_internal_time()]
        if self._outbound:
            times.append(self._outbound[0][0])
        pending = [t for t in times if t is not None]
        return min(pending) if pending else None

    # --- firmware -----------------------------------------------------------

    def advance(self, now: float) -> None:
        """Run the firmware up to ``now``."""
        while True:
            next_time = self._next_internal_time()
            if next_time is None or next_time > now:
                break
            self._step(max(next_time, self._last_step))
        self._step(max(now, self._last_step))

    def _next_internal_time(self) -> float | None:
        times: list[float] = []
        if self._inbound:
            times.append(self._inbound[0][0])
        if self._queue:
            head = self._queue[0]
            if self._busy_until > self._last_step:
                times.append(self._busy_until)
            elif head.word in _MOVES and len(self._planner) >= self.settings.planner:
                times.append(self._planner[0])
            elif is_unbuffered(head.text) and not head.started and self._planner:
                times.append(self._planner_end)
        return min(times) if times else None

    def _step(self, now: float) -> None:
        self._last_step = now
        while True:
            self._fill_slots(now)
            if self._process_head(now):
                continue
            if self._inbound and self._inbound[0][0] <= now:
                self._deliver(self._inbound.popleft()[1])
                continue
            break

    def _deliver(self, data: bytes) -> None:
        self._inbound_bytes -= len(data)
        free = self.settings.rx_buffer - 1 - len(self._rx)
        if len(data) > free and self.settings.overflow is Overflow.DROP:
            self.bytes_dropped += len(data) - free
            data = data[:free]
        # With back-pressure the host was only let to send what fits (room()).
        self._rx += data

    def _fill_slots(self, now: float) -> None:
        while len(self._queue) < self.settings.slots:
            end = self._rx.find(b"\n")
            if end < 0:
                return
            raw = bytes(self._rx[:end]).rstrip(b"\r")
            del self._rx[: end + 1]
            outcome = self.protocol.handle_line(raw)
            if isinstance(outcome, Accepted):
                self._queue.append(_Command(outcome.command, command_word(outcome.command)))
            elif isinstance(outcome, Rejected):
                self.lines_rejected += 1
                self._reply(outcome.reply, now)

    def _process_head(self, now: float) -> bool:
        """Work on the oldest command; True when it finished and the next may start."""
        if not self._queue or self._busy_until > now:
            return False
        while self._planner and self._planner[0] <= now:
            self._planner.popleft()
        command = self._queue[0]
        if command.word in _MOVES:
            if len(self._planner) >= self.settings.planner:
                return False
            start = max(now, self._planner_end)
            self._planner_end = start + self.settings.move_time
            self._planner.append(self._planner_end)
        elif is_unbuffered(command.text) and not command.started:
            if self._planner:
                return False  # wait until every planned move is done
            command.started = True
            self._busy_until = now + self._duration(command)
            if self._busy_until > now:
                return False
        elif not command.started and self.settings.command_time > 0:
            command.started = True
            self._busy_until = now + self.settings.command_time
            return False
        self._queue.popleft()
        self._on_execute(command.text)
        self._reply(self._answer(command), now)
        return True

    def _duration(self, command: _Command) -> float:
        if command.word == "G4":
            match = _DWELL.search(command.text[2:])
            if match is not None:
                value = float(match.group(2))
                return value / 1000.0 if match.group(1).upper() == "P" else value
            return 0.0
        return self.settings.command_time

    def _answer(self, command: _Command) -> bytes:
        if command.word == "M105":
            return b"ok T:21.0 /0.0 B:21.0 /0.0 @:0 B@:0\n"
        if command.word == "M115":
            return (
                b"FIRMWARE_NAME:repetrel-host fake controller (Marlin replies) "
                b"PROTOCOL_VERSION:1.0 MACHINE_TYPE:Fake\nok\n"
            )
        return b"ok\n"

    def _reply(self, data: bytes, now: float) -> None:
        start = max(now, self._out_wire_free)
        self._out_wire_free = start + self._wire_time(len(data))
        self._outbound.append((self._out_wire_free + self.settings.latency, data))

    def _wire_time(self, size: int) -> float:
        bandwidth = self.settings.bandwidth
        return 0.0 if bandwidth is None else size / bandwidth
