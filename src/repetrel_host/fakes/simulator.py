"""A Marlin-style controller as a pure simulation with explicit time.

The same engine runs behind the pty fake controller (real time) and in
in-memory tests (simulated time). It models the link (bandwidth and latency
each way), the receive buffer in bytes (dropping bytes on overflow like a UART,
or pushing back like USB), the command slots, the planner, and how long each
command takes: a fixed time per move, or (``time_scale``) the time the firmware's
planner would give it, scaled. It acknowledges a buffered command once it is planned, an
unbuffered one once it finished (G4, G28, M400 once the planner drained; a heat wait
while the moves before it still run, as Marlin's M109 does). The planner's moves are
:mod:`.planned`'s, the heaters' temperatures :mod:`.heating`'s.

What it writes is Marlin 2.1's (docs/fake-controller.md): its error and ``Resend:``
strings, every line error answered by emptying the receive buffer, ``echo:busy:
processing`` every 2 s while a command holds the queue, a temperature report every second
of a heat wait (with ``W:``, the residency left), M155's reports. It counts every error
line it writes (``link.errors``): a host that keeps a healthy link healthy draws none.

Faults (:class:`Faults`) are seeded and reproducible. They can also be switched
while running by a line of the job: ``!!DEBUG:set corrupt=0.02 drop_ok=0.01``,
``!!DEBUG:reset`` (reboot: says ``start``), ``!!DEBUG:hang`` (never answer
again), ``!!DEBUG:link_drop 2`` (the pty disappears for 2 s), as OctoPrint's
virtual printer does. Such lines are not logged as executed.
"""

from __future__ import annotations

import random
import re
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

from repetrel_host.fakes.heating import S_WORD, SimulatedHeaters
from repetrel_host.fakes.planned import MovePlanner
from repetrel_host.fakes.settings import (
    ControllerSettings,
    FaultCounts,
    Faults,
    LinkCounters,
    Overflow,
)
from repetrel_host.gcode.commands import command_word, is_unbuffered
from repetrel_host.protocol.controller import Accepted, ControllerProtocol, Rejected

_MOVES = frozenset({"G0", "G1", "G2", "G3", "G5"})
_DWELL = re.compile(r"\b([PS])\s*(\d+(?:\.\d*)?)", re.IGNORECASE)
# What each temperature command sets: a hotend (T), the bed (B) or the chamber (C), and
# whether it waits for it.
_HEATERS = {
    "M104": ("T", False), "M109": ("T", True),
    "M140": ("B", False), "M190": ("B", True),
    "M141": ("C", False), "M191": ("C", True),
}  # fmt: skip
# A tool (T) word in a command: which head or heater it addresses.
T_WORD = re.compile(r"\bT\s*(\d+)", re.IGNORECASE)
# Marlin's M115: the identity line (its EXTRUDER_COUNT filled in), then its capabilities.
M115_REPLY = (
    "FIRMWARE_NAME:repetrel-host fake controller (Marlin replies) "
    "PROTOCOL_VERSION:1.0 MACHINE_TYPE:Fake EXTRUDER_COUNT:{extruders}\n"
    "Cap:AUTOREPORT_TEMP:{autoreport}\n"
    "Cap:EMERGENCY_PARSER:{parser}\n"
)
KILLED = b"Error:Printer halted. kill() called!\n"
DEBUG_PREFIX = "!!DEBUG:"
WAIT_REPORT_INTERVAL = 1.0  # Marlin's heat wait prints the temperatures every second
_ERROR_PREFIXES = (b"Error", b">ER:")  # Marlin's error lines, and Hyrel's
# What a host's session sends before a job: the greeting and its question "who are you?".
_SESSION_WORDS = frozenset({"M110", "M115"})
MAX_CMD_SIZE = 96  # Marlin's line buffer


@dataclass(slots=True)
class QueuedCommand:
    """A command the controller took, waiting for or in execution."""

    text: str
    word: str
    number: int | None
    started: bool = False
    urgent: bool = False  # Hyrel's link: ahead of the queue
    planned: int | None = None  # its number in the planned times (with time_scale)


class ControllerSimulator:
    """Feed bytes with :meth:`receive`, run with :meth:`advance`, read :meth:`take_output`."""

    HYREL_CODE_CHART = False  # its moves planned as Hyrel's firmware runs them (time_scale)
    # Marlin's M109/M190/M191 wait for the heater at once, while the moves before them run
    # on; False: only once the planner drained, as G4 and M400 do.
    HEAT_WAIT_AT_ONCE = True
    TEMPERATURE_DECIMALS = 2  # Marlin reports "T:21.00 /0.00"
    WAIT_REPORTS = True  # a heat wait reports the temperatures every second

    def __init__(
        self,
        settings: ControllerSettings | None = None,
        *,
        now: float = 0.0,
        on_execute: Callable[[str], None] | None = None,
    ) -> None:
        self.settings = settings or ControllerSettings()
        self.faults = self.settings.faults
        self._rng = random.Random(self.faults.seed)
        self.protocol = self._new_protocol()
        self.executed: list[str] = []
        self._on_execute = on_execute or self.executed.append
        # With the default log: each command's line number (None: unnumbered), in step.
        self.executed_numbers: list[int | None] | None = None if on_execute else []
        self.counts = FaultCounts()
        self.hung = False
        self.link_drop_requested: float | None = None  # seconds, for the pty pump
        self._inbound: deque[tuple[float, bytes]] = deque()
        self._inbound_bytes = 0
        self._in_wire_free = now
        self._rx = bytearray()
        self._line = bytearray()  # the line being read out of the receive buffer
        self._queue: deque[QueuedCommand] = deque()
        self._planner = MovePlanner(self.settings, now, hyrel=self.HYREL_CODE_CHART)
        self._busy_until = now
        self._last_step = now
        self._keepalive = self.settings.keepalive  # M113 S<n> changes it
        self._next_busy: float | None = None  # the next busy line, while a command holds on
        self._reached_at: float | None = None  # the heat wait in hand reached its target then
        self._next_wait_report = now
        self._outbound: deque[tuple[float, bytes]] = deque()
        self._out_wire_free = now
        bandwidth = self.settings.bandwidth
        blocking = self.settings.overflow is Overflow.BLOCK
        self._wire_capacity = (
            int(bandwidth * self.settings.latency) if blocking and bandwidth else 0
        )
        self._idle_from = now  # when the last piece of work finished
        self.link = LinkCounters()
        settings = self.settings
        self.heaters = SimulatedHeaters(
            settings.extruders, settings.chamber, settings.heat_rate, now
        )
        self.tool = 0  # the active hotend (T0, T1...)
        self._report_every: float | None = None  # M155 S<n>
        self._next_report = now
        self._identify_slowly = self.settings.identify_time > 0  # the next M115
        if self.settings.banner:
            self._reply(b"start\n", now)

    # --- link ---------------------------------------------------------------

    def room(self) -> int:
        """Bytes the link can take now without dropping any: the receive buffer's free
        space plus, with back-pressure, what the wire itself holds (bandwidth x latency),
        as a USB link keeps packets in flight and holds the rest at the sender."""
        free = self.settings.rx_buffer - 1 - len(self._rx)
        return max(0, free + self._wire_capacity - self._inbound_bytes)

    def receive_from(self, wire: bytearray, now: float) -> None:
        """Take from ``wire`` (written, not yet taken) what the link lets through at ``now``:
        all of it, or with back-pressure what there is :meth:`room` for; the rest stays."""
        if not wire:
            return
        blocked = self.settings.overflow is Overflow.BLOCK
        taken = min(len(wire), self.room()) if blocked else len(wire)
        self.receive(bytes(wire[:taken]), now)
        del wire[:taken]

    def receive(self, data: bytes, now: float) -> None:
        """Bytes the host wrote at ``now``; they reach the receive buffer after the wire's delay.

        Each line arrives on its own, so the firmware can take a line out of the
        buffer before the next one lands, as it does on a real wire.
        """
        if self.hung:
            return
        start = max(now, self._in_wire_free)
        begin = 0
        while begin < len(data):
            end = data.find(b"\n", begin) + 1 or len(data)
            piece = self._maybe_corrupt(data[begin:end])
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

    def unplug(self) -> None:
        """The cable is pulled: whatever was on the wire either way is lost."""
        self._inbound.clear()
        self._inbound_bytes = 0
        self._outbound.clear()

    # --- firmware -----------------------------------------------------------

    def advance(self, now: float) -> None:
        """Run the firmware up to ``now``."""
        if self.hung:
            return
        while True:
            next_time = self._next_internal_time()
            if next_time is None or next_time > now:
                break
            self._step(max(next_time, self._last_step))
        self._step(max(now, self._last_step))

    def _next_internal_time(self) -> float | None:
        if self.hung:
            return None
        times: list[float] = []
        if self._report_every is not None:
            times.append(self._next_report)
        if self._inbound and self._rx_free() > 0:
            times.append(self._inbound[0][0])
        if self._queue and not self._holding():
            head = self._queue[0]
            if self._busy_until > self._last_step:
                times.append(self._busy_until)
            elif head.word in _MOVES and self._planner.full and self._planner.finishes:
                times.append(self._planner.finishes[0])
            elif is_unbuffered(head.text) and not head.started and self._planner.finishes:
                times.append(self._planner.end)
            if self._next_busy is not None:
                times.append(self._next_busy)
            if self.WAIT_REPORTS and self._heat_waiting():
                times.append(self._next_wait_report)
        if self._planner.untimed:
            times.append(self._planner.end)  # idle then: the moves waiting get their times
        return min(times) if times else None

    def _holding(self) -> bool:
        """The queue waits whatever it holds (a Hyrel pause byte); never on Marlin."""
        return False

    def _holds_queue(self) -> bool:
        """The oldest command holds the queue (a move waiting for the planner, a command
        waiting for the moves or for itself to finish), a heat wait aside: Marlin's busy
        state, in which it says ``busy: processing`` now and then."""
        if not self._queue or self._holding():
            return False
        head = self._queue[0]
        if head.started:
            return self._busy_until > self._last_step and not self._heat_waiting()
        if head.word in _MOVES:
            return self._planner.full
        return is_unbuffered(head.text) and self._planner.holds

    def _heat_waiting(self) -> bool:
        """The oldest command is a heat wait under way (M109, M190, M191)."""
        if not self._queue or self._busy_until <= self._last_step:
            return False
        head = self._queue[0]
        return head.started and _HEATERS.get(head.word, ("", False))[1]

    def _step(self, now: float) -> None:
        self._last_step = now
        while not self.hung:
            self._fill_slots(now)
            self._planner.time_moves(now)
            if self._process_head(now):
                continue
            if self._inbound and self._inbound[0][0] <= now and self._rx_free() > 0:
                self._deliver(now)
                continue
            if self._planner.settle(now):  # it ran dry and nothing more came
                continue
            break
        if self._report_every is not None and now >= self._next_report:
            self._reply(b" " + self._temperatures(now).encode() + b"\n", now)
            self._next_report = now + self._report_every
        self._keep_alive(now)
        if self.WAIT_REPORTS and self._heat_waiting() and now >= self._next_wait_report:
            self._wait_report(now)

    def _wait_report(self, now: float) -> None:
        self._next_wait_report = now + WAIT_REPORT_INTERVAL
        self._reply(f" {self._temperatures(now)}{self._residency_left(now)}\n".encode(), now)

    def _keep_alive(self, now: float) -> None:
        """Marlin's host keepalive: the first busy line once a command held the queue for the
        interval, then one each interval, while it holds it."""
        interval = self._keepalive
        if not interval or not self._holds_queue():
            self._next_busy = None
        elif self._next_busy is None:
            self._next_busy = now + interval
        elif now >= self._next_busy:
            self._reply(b"echo:busy: processing\n", now)
            self._next_busy = now + interval

    def _residency_left(self, now: float) -> str:
        """A heat wait report's `` W:``: ``?`` until the target is reached, then the whole
        seconds of residency left; nothing without a residency."""
        if not self.settings.residency:
            return ""
        if self._reached_at is None or now < self._reached_at:
            return " W:?"
        return f" W:{max(0, int(self._busy_until - now))}"

    def _rx_free(self) -> int:
        """Free receive buffer; a UART delivers into a full one too (and loses bytes)."""
        if self.settings.overflow is Overflow.DROP:
            return 1
        return self.settings.rx_buffer - 1 - len(self._rx)

    def _deliver(self, now: float) -> None:
        arrival, data = self._inbound.popleft()
        free = self.settings.rx_buffer - 1 - len(self._rx)
        link = self.link
        if len(data) > free and self.settings.overflow is Overflow.BLOCK:
            # Held at the door until the firmware reads the buffer out.
            self._inbound.appendleft((arrival, data[free:]))
            data = data[:free]
        self._inbound_bytes -= len(data)
        link.bytes_received += len(data)
        if len(data) > free:
            link.bytes_dropped += len(data) - free
            data = data[:free]
        self._arrived(data, now)

    def _arrived(self, data: bytes, now: float) -> None:
        """Bytes that reached the receive buffer."""
        # Marlin's emergency parser acts on these as the bytes arrive; M108's and M410's
        # lines then go on into the buffer, to run in their turn and draw their ok.
        if self.settings.emergency_parser:
            head = data.lstrip()
            if head.startswith(b"M112"):
                self._kill(now)
                return
            if head.startswith(b"M108"):
                self._break_heat_wait(now)
            elif head.startswith(b"M410"):
                self._quick_stop(now)
        self._buffer(data)

    def _buffer(self, data: bytes) -> None:
        """Into the receive buffer, its peak counted."""
        self._rx += data
        if len(self._rx) > self.link.peak_rx_buffer:
            self.link.peak_rx_buffer = len(self._rx)

    def _fill_slots(self, now: float) -> None:
        # While a command slot is free the firmware reads the receive buffer into
        # its line buffer, keeping at most MAX_CMD_SIZE bytes of a line (Marlin):
        # a line that lost its newline cannot wedge the buffer.
        while len(self._queue) < self.settings.slots:
            end = self._rx.find(b"\n")
            if end < 0:
                self._line += self._rx[: max(0, MAX_CMD_SIZE - len(self._line))]
                self._rx.clear()
                return
            self._line += self._rx[: max(0, min(end, MAX_CMD_SIZE - len(self._line)))]
            del self._rx[: end + 1]
            raw = bytes(self._line).rstrip(b"\r")
            self._line.clear()
            self._take_line(raw, now)

    def _take_line(self, raw: bytes, now: float) -> None:
        """One line read out of the receive buffer (without its newline)."""
        drop = self._chance(self.faults.drop_with_error)
        outcome = self.protocol.handle_line(raw, drop)
        if isinstance(outcome, Accepted):
            command = outcome.command
            word = command_word(command)
            self._count_command(word, now)
            queued = QueuedCommand(command, word, outcome.number)
            self._plan(queued)
            self._queue.append(queued)
        elif isinstance(outcome, Rejected):
            self._reply(outcome.reply.removesuffix(b"ok\n"), now)
            if outcome.reply.endswith(b"ok\n") and not self.faults.resend_without_ok:
                self._ok(b"ok\n", now)
            if outcome.reason == "dropped":
                self.counts.dropped_with_error += 1
            if self.faults.flush_on_error:
                self.counts.flushed_bytes += len(self._rx)
                self._rx.clear()

    def _count_command(self, word: str, now: float) -> None:
        link = self.link
        if not self._queue and link.commands:
            idle_from = max(self._idle_from, self._planner.end, self._busy_until)
            if now > idle_from:
                link.starved += now - idle_from
        if link.first_command_at is None:
            link.first_command_at = now
        if link.first_job_command_at is None and word not in _SESSION_WORDS:
            link.first_job_command_at = now
            link.bytes_at_first_job_command = link.bytes_received
        link.last_command_at = now
        link.bytes_at_last_command = link.bytes_received
        link.commands += 1
        link.peak_slots = max(link.peak_slots, len(self._queue) + 1)

    def _process_head(self, now: float) -> bool:
        """Work on the oldest command; True when it finished and the next may start."""
        if not self._queue or self._busy_until > now:
            return False
        self._planner.ran(now)
        command = self._queue[0]
        if command.text.startswith(DEBUG_PREFIX):
            self._queue.popleft()
            self._debug(command.text[len(DEBUG_PREFIX) :], now)
            return True
        if not command.text[:1].isalpha():
            # What is left of a line whose '*' became a newline: its checksum digits.
            # Marlin runs nothing and says so.
            self._queue.popleft()
            self._reply(f'echo:Unknown command: "{command.text}"\n'.encode(), now)
            self._ok(b"ok\n", now)
            return True
        if command.word in _MOVES:
            if self._planner.full:
                return False
            self._planner.add(command.planned, now)
        elif is_unbuffered(command.text) and not command.started:
            heat_wait = _HEATERS.get(command.word, ("", False))[1]
            if self._planner.holds and not (heat_wait and self.HEAT_WAIT_AT_ONCE):
                return False  # wait until every planned move is done
            command.started = True
            self._reached_at = None
            self._busy_until = now + self._duration(command)
            if heat_wait and self.WAIT_REPORTS:
                # Marlin's first report comes at once, its heater there already or not.
                self._wait_report(now)
            if self._busy_until > now:
                return False
        elif command.word == "M115" and not command.started and self._identify_slowly:
            command.started = True
            self._identify_slowly = False
            self._busy_until = now + self.settings.identify_time
            return False
        elif not command.started and self.settings.command_time > 0:
            command.started = True
            self._busy_until = now + self.settings.command_time
            return False
        self._queue.popleft()
        self._idle_from = now
        self._log_execution(command.text, command.number)
        self._answer(command, now)
        return True

    def _log_execution(self, text: str, number: int | None) -> None:
        self._on_execute(text)
        if self.executed_numbers is not None:
            self.executed_numbers.append(number)

    def _plan(self, command: QueuedCommand) -> None:
        """A command entering the queue goes to the planner's planned times (its number
        kept: :meth:`MovePlanner.queued`)."""
        if not command.text.startswith(DEBUG_PREFIX):
            text = command.text
            command.planned = self._planner.queued(
                text, command.word in _MOVES, is_unbuffered(text)
            )

    def _duration(self, command: QueuedCommand) -> float:
        heater = _HEATERS.get(command.word)
        if heater is not None and heater[1]:
            name = self._heater_for(heater[0], command, self._last_step)
            if name is None:
                return 0.0
            now = self._last_step
            return self._wait_for(self.heaters.set_target(name, command.text, now), now)
        if command.word == "G4":
            match = _DWELL.search(command.text[2:])
            if match is not None:
                value = float(match.group(2))
                seconds = value / 1000.0 if match.group(1).upper() == "P" else value
                return seconds / (self.settings.time_scale or 1.0)  # part of the plan
            return 0.0
        return self.settings.command_time

    def _wait_for(self, reach: float, now: float) -> float:
        """A heat wait's length from ``now``: until its heater reaches the target (``reach``
        seconds), then the residency."""
        self._reached_at = now + reach
        return reach + self.settings.residency

    def _set_heater(self, command: QueuedCommand, now: float) -> None:
        """M104, M140 and M141 set their heater's target as they run (M109, M190 and M191
        did as they began to wait)."""
        heater = _HEATERS.get(command.word)
        if heater is not None and not heater[1]:
            name = self._heater_for(heater[0], command, now)
            if name is not None:
                self.heaters.set_target(name, command.text, now)

    def _heater_for(self, kind: str, command: QueuedCommand, now: float) -> str | None:
        """The heater a temperature command sets, as Marlin reads it: a hotend by its T word
        (else the active tool's; one it does not have is refused), the bed whatever T says,
        the chamber if there is one."""
        if kind == "C":
            return "C" if "C" in self.heaters else None
        if kind == "B":
            return "B"
        match = T_WORD.search(command.text[len(command.word) :])
        index = int(match.group(1)) if match else self.tool
        if index >= self.settings.extruders:
            self._reply(f"echo:{command.word} Invalid extruder {index}\n".encode(), now)
            return None
        return "T" if index == 0 else f"T{index}"

    def _answer(self, command: QueuedCommand, now: float) -> None:
        word = command.word
        self._set_heater(command, now)
        if word == "M105":
            self._ok(f"ok {self._temperatures(now)}\n".encode(), now)
            return
        if word == "M112":  # in its turn: without the emergency parser
            self._kill(now)
            return
        if word[:1] == "T" and word[1:].isdigit():
            if int(word[1:]) < self.settings.extruders:
                self.tool = int(word[1:])
            else:
                self._reply(f"echo:{word} Invalid extruder {word[1:]}\n".encode(), now)
        if word == "M115":
            settings = self.settings
            parser = int(settings.emergency_parser)
            reply = M115_REPLY.format(
                extruders=settings.extruders, parser=parser, autoreport=int(settings.autoreport)
            )
            if not settings.extruder_count:
                reply = reply.replace(f" EXTRUDER_COUNT:{settings.extruders}", "")
            self._reply(reply.encode(), now)
        elif word == "M155" and not self.settings.autoreport:
            self._reply(f'echo:Unknown command: "{command.text}"\n'.encode(), now)
        elif word == "M155":
            match = S_WORD.search(command.text)
            seconds = float(match.group(1)) if match else 0.0
            self._report_every = seconds if seconds > 0 else None
            self._next_report = now + seconds
        elif word == "M113" and self.settings.keepalive is not None:
            match = S_WORD.search(command.text)
            if match is not None:  # the busy lines' interval; 0: none
                self._keepalive = float(match.group(1)) or None
        if command.number is not None and self._chance(self.faults.spurious_resend):
            self.counts.spurious_resends += 1
            self._reply(f"Resend: {command.number}\n".encode(), now)
        self._ok(b"ok\n", now)

    def _debug(self, text: str, now: float) -> None:
        """A ``!!DEBUG:`` line of the job: acts as :meth:`control`, answered with an ok."""
        try:
            self.control(text, now)
        except ValueError as exc:
            self._reply(f"echo:{DEBUG_PREFIX} {exc}\n".encode(), now)
        if not self.hung and not text.strip().startswith("reset"):
            self._ok(b"ok\n", now)

    def control(self, text: str, now: float) -> None:
        """Switch something from outside the wire (the fake's ``--control`` channel, and
        ``!!DEBUG:`` lines): ``set corrupt=0.02 ...``, ``reset``, ``hang``, ``link_drop S``,
        ``heat_rate R`` (degrees a second; ``none``: at once). ValueError on bad input."""
        verb, _, argument = text.strip().partition(" ")
        if verb == "set":
            self.faults = Faults.parse(argument, self.faults)
            self.protocol.drop_duplicates = self.faults.drop_duplicates
            self.protocol.counted_resend = self.faults.counted_resend
        elif verb == "reset":
            self._reboot(now)
        elif verb == "hang":
            self.hung = True
        elif verb == "link_drop":
            self.link_drop_requested = _number(argument or "1", "link_drop")
        elif verb == "heat_rate":
            rate = None if argument.strip() in ("", "none") else _number(argument, "heat_rate")
            self.heaters.set_rate(rate, now)
            self.settings = replace(self.settings, heat_rate=rate)
            head = self._queue[0] if self._queue else None
            heater = _HEATERS.get(head.word) if head is not None else None
            if head is not None and head.started and heater is not None and heater[1]:
                # The wait under way lasts as long as the new rate takes to its target.
                waited = self._heater_for(heater[0], head, now)
                left = self.heaters.set_target(waited, head.text, now) if waited else 0.0
                self._busy_until = now + self._wait_for(left, now)
        else:
            raise ValueError(
                f"unknown control '{verb}' (known: set, reset, hang, link_drop, heat_rate)"
            )

    def temperatures(self, now: float) -> dict[str, tuple[float, float]]:
        """Each heater's (current, target) at ``now``."""
        return self.heaters.readings(now)

    def _new_protocol(self) -> ControllerProtocol:
        faults = self.faults
        return ControllerProtocol(faults.drop_duplicates, faults.counted_resend)

    # --- heaters -------------------------------------------------------------

    def _temperatures(self, now: float) -> str:
        """The temperature report, as this firmware writes it (:meth:`SimulatedHeaters.report`)."""
        return self.heaters.report(now, self.tool, self.TEMPERATURE_DECIMALS)

    def _break_heat_wait(self, now: float) -> None:
        """M108: an M109, M190 or M191 waiting for its heater stops waiting (its ok goes now)."""
        head = self._queue[0] if self._queue else None
        if head is not None and head.started and _HEATERS.get(head.word, ("", False))[1]:
            self._busy_until = min(self._busy_until, now)

    def _quick_stop(self, now: float) -> None:
        """M410: the moves in the planner are dropped, the motion stops where it is."""
        self._planner.drop()
        self._planner.end = now

    def _kill(self, now: float) -> None:
        """M112: Marlin's kill(): heaters off, nothing more until a reset."""
        self._log_execution("M112", None)
        self.heaters.turn_off()
        self._queue.clear()
        self._planner.drop()
        self._rx.clear()
        self._reply(KILLED, now)
        self.hung = True

    def _reboot(self, now: float) -> None:
        self.hung = False  # a halt (M112's kill) lasts until a reset
        self.protocol = self._new_protocol()
        self.heaters.turn_off()  # a reset turns every heater off
        self.tool = 0
        self._queue.clear()
        self._planner.drop()
        self._rx.clear()
        self._line.clear()
        self._planner.end = self._busy_until = now
        self._identify_slowly = self.settings.identify_time > 0
        self._reply(self._boot_banner(), now)

    def _boot_banner(self) -> bytes:
        return b"start\n"

    # --- replies ------------------------------------------------------------

    def _ok(self, line: bytes, now: float) -> None:
        if self._chance(self.faults.drop_ok):
            self.counts.dropped_oks += 1
            return
        if self.settings.advanced_ok and line == b"ok\n":
            planner_free = self._planner.free
            slots_free = self.settings.slots - len(self._queue)
            last = self.protocol.last_line
            line = f"ok N{last} P{planner_free} B{slots_free}\n".encode()
        self._reply(line, now)
        if self._chance(self.faults.duplicate_ok):
            self.counts.duplicated_oks += 1
            self._reply(line, now)

    def _reply(self, data: bytes, now: float) -> None:
        if data.startswith(_ERROR_PREFIXES):  # each error is written on its own
            self.link.errors += 1
        if self.faults.garble > 0:
            data = b"".join(self._maybe_garble(line) for line in data.splitlines(keepends=True))
        start = max(now, self._out_wire_free)
        self._out_wire_free = start + self._wire_time(len(data))
        self._outbound.append((self._out_wire_free + self.settings.latency, data))

    def _maybe_corrupt(self, piece: bytes) -> bytes:
        if not self._chance(self.faults.corrupt):
            return piece
        self.counts.corrupted_lines += 1
        return self._change_one_byte(piece)

    def _maybe_garble(self, line: bytes) -> bytes:
        if not self._chance(self.faults.garble):
            return line
        self.counts.garbled_replies += 1
        return self._change_one_byte(line)

    def _change_one_byte(self, data: bytes) -> bytes:
        position = self._rng.randrange(len(data))
        value = (data[position] + self._rng.randrange(1, 256)) % 256
        return data[:position] + bytes([value]) + data[position + 1 :]

    def _chance(self, share: float) -> bool:
        return share > 0 and self._rng.random() < share

    def _wire_time(self, size: int) -> float:
        bandwidth = self.settings.bandwidth
        return 0.0 if bandwidth is None else size / bandwidth


def _number(text: str, name: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{name}: '{text}' is not a number") from None
