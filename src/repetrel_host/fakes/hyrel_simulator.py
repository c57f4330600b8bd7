"""The simulated controller speaking Hyrel's own link (docs/hyrel-link.md).

The machine is :class:`ControllerSimulator`'s (receive buffer, command slots, planner,
heaters, faults); the link is Hyrel's:

- an ACK byte (0x06) for every line received, sent while the receive buffer has
  ``ack_headroom`` bytes free, else owed until reading lines out of it frees them;
- no ``ok`` and no resend requests: a line that fails its additive checksum is reported
  (``>ER:``) and not run;
- control bytes act as they arrive: ping (answered ``>Hy: ...``), abort (everything held
  is dropped), pause at the end of the move or layer (held until end-wait), end-wait
  (ends a pause or a heat-up; echoed), status (``>ST: ...``), the watchdog byte;
  0x09 as a line's first byte runs it ahead of the queue;
- ``>MC:M<n>: ...:`` as the M-codes in :data:`~repetrel_host.protocol.hyrel.NOTICED` are
  processed (no others), ``M115`` answered with a ``>Hy:`` identity;
- the watchdog: after ``watchdog`` seconds without a byte from the host, every extruder
  stops (here: the head's heater target goes to 0) and ``>ER:`` says so;
- ``M0``/``M1`` wait until end-wait; ``M772 S<mask>`` resets the job metrics and, with
  bit 0, arms the ``M773`` report that ``M30`` sends (``M773`` sends it at once), in the
  reference's form (hyrel-gcode-reference.txt, M773): what ran since M772 (positions
  from X0 Y0 Z0, times at the feed rate);
- faults: ``corrupt`` and ``garble`` as on Marlin's link, ``drop_ok`` for ACK bytes,
  ``identity_twice`` (an M115 answered twice, the second line right after the first) and
  ``unasked_identity`` (after a G4's dwell, the identity unasked in an info line, ``>IN:
  FIRMWARE_NAME:...``); the others are Marlin's ways (or, ``duplicate_ok``, one no host
  can survive here) and refused.

Choices of this fake where the notes are silent (a real controller may differ): the
temperature report's form (``>ST: T:... B:...``), the messages' wording, a layer pause
held like a move pause, urgent lines run in the order they came (after the command in
hand; ``urgent_order newest`` on the control channel: newest first), owed ACKs still sent
after an abort, the ``>Hy:`` line it says when it restarts,
the report sent before M30's notice.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.fakes.simulator import T_WORD, ControllerSimulator, QueuedCommand
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol.hyrel import NOTICED, Control, read_line

ACK_HEADROOM = 2048  # bytes free in the receive buffer for a line's ACK to go
RX_BUFFER = 8192
ALL_HEADS = frozenset({40, 41, 47})  # v5 groups: all devices, yoke 1's heads, every head
WATCHDOG = 30.0  # seconds of a silent host before the extruders stop
M115_REPLY = (
    b"FIRMWARE_NAME:>Hy: repetrel-host-fake_1.0 PROTOCOL_VERSION:1.0 "
    b"MACHINE_TYPE:HYREL_HYDRA HYREL_PROTOCOL:1\n"
)
PING_REPLY = b">Hy: repetrel-host fake controller (Hyrel link)\n"
RESTART_REPLY = b">Hy: repetrel-host fake controller (Hyrel link) restarted\n"
_CONTROL_BYTES = frozenset(int(byte) for byte in Control) - {Control.URGENT, Control.ACK}
# Faults of this link: lines corrupted on the way, replies garbled, ACKs lost. (An ACK sent
# twice cannot be told from two: no host could keep the buffer from overflowing.)
LINK_FAULTS = frozenset(
    {"corrupt", "garble", "drop_ok", "identity_twice", "unasked_identity", "seed"}
)
_MOVES = frozenset({"G0", "G1", "G2", "G3"})
_AXIS = re.compile(r"([XYZEF])\s*(-?\d*\.?\d+)", re.IGNORECASE)


def check_faults(faults: Faults) -> None:
    """ValueError for a fault that is Marlin's way, not this link's."""
    default = Faults()
    for item in fields(Faults):
        if item.name not in LINK_FAULTS and getattr(faults, item.name) != getattr(
            default, item.name
        ):
            why = (
                "ACKs sent twice cannot be told from two by any host"
                if item.name == "duplicate_ok"
                else "it is Marlin's"
            )
            raise ValueError(
                f"'{item.name}' is not a fault of Hyrel's link: {why} "
                f"(its faults: {', '.join(sorted(LINK_FAULTS))})"
            )


@dataclass(slots=True)
class Metrics:
    """What M773 reports: moves' time (at their feed rate, without acceleration) and
    distance, printing (with E) or not, and E."""

    printing_time: float = 0.0
    printing_distance: float = 0.0  # mm
    travel_time: float = 0.0
    travel_distance: float = 0.0
    extruded: float = 0.0  # mm of E
    position: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    relative: bool = False  # G91
    relative_e: bool = False  # M83
    feed_rate: float = 0.0  # mm/min, as the last F said

    def move(self, command: str) -> None:
        x, y, z, e = self.position
        values = {axis.upper(): float(value) for axis, value in _AXIS.findall(command)}
        self.feed_rate = values.get("F", self.feed_rate)
        new = [x, y, z, e]
        for index, axis in enumerate("XYZE"):
            if axis in values:
                step = self.relative or (axis == "E" and self.relative_e)
                new[index] = (new[index] if step else 0.0) + values[axis]
        distance = math.dist((x, y, z), new[:3])
        seconds = distance / (self.feed_rate / 60) if self.feed_rate > 0 else 0.0
        if new[3] > e:
            self.printing_time += seconds
            self.printing_distance += distance
            self.extruded += new[3] - e
        else:
            self.travel_time += seconds
            self.travel_distance += distance
        self.position = (new[0], new[1], new[2], new[3])

    def set_mode(self, word: str, command: str) -> None:
        if word in ("G90", "G91"):
            self.relative = word == "G91"
        elif word in ("M82", "M83"):
            self.relative_e = word == "M83"
        elif word == "G92":
            values = {axis.upper(): float(value) for axis, value in _AXIS.findall(command)}
            x, y, z, e = self.position
            self.position = (
                values.get("X", x), values.get("Y", y), values.get("Z", z), values.get("E", e)
            )  # fmt: skip

    def report(self) -> list[str]:
        """The M773 report's lines, as the reference's sample shows them."""
        stars = "*" * 66
        total_time = self.printing_time + self.travel_time
        total_distance = (self.printing_distance + self.travel_distance) / 1000
        rows = [
            stars,
            "**  Begin M773 - print job metrics Report",
            stars,
            "",
            f"{'':22}Time (s)    Dist (m)",
            f"{'':22}--------    --------",
            f"{'Totals:':22}{total_time:8.1f}{total_distance:12.3f}",
            "",
            f"{'Printing moves:':22}{self.printing_time:8.1f}{self.printing_distance / 1000:12.3f}",
            f"{'Non-printing moves':22}{self.travel_time:8.1f}{self.travel_distance / 1000:12.3f}",
            "",
            f"{'approx filament (E)':26}{self.extruded / 1000:.3f} m",
            "",
            stars,
            "**  End M773 Report",
            stars,
        ]
        return [f">IN:  50: {row}" for row in rows]


class HyrelControllerSimulator(ControllerSimulator):
    """A :class:`ControllerSimulator` on Hyrel's link; ``ack_headroom`` and ``watchdog``
    as the firmware has them unless a test wants them smaller."""

    HYREL_CODE_CHART = True
    # What the notes say nothing of, kept as this fake always had it: a heat wait starts
    # once the moves before it ran, and says nothing while it waits; reports in tenths.
    HEAT_WAIT_AT_ONCE = False
    WAIT_REPORTS = False
    TEMPERATURE_DECIMALS = 1

    def __init__(
        self,
        settings: ControllerSettings | None = None,
        *,
        now: float = 0.0,
        on_execute: Callable[[str], None] | None = None,
        ack_headroom: int = ACK_HEADROOM,
        watchdog: float = WATCHDOG,
    ) -> None:
        self.ack_headroom = ack_headroom
        self.watchdog = watchdog
        self.owed_acks = 0
        self.acks_sent = 0
        self.watchdog_trips = 0
        self.metrics: Metrics | None = None  # counted from the first M772 on
        self._reports = 0  # M772's mask: bit 0, the M773 report at M30
        self._held = False  # a pause byte, an M0: nothing runs until end-wait
        self.urgent_newest_first = False  # urgent lines run newest first (urgent_order)
        self._heard_at: float | None = None  # the host's last byte (armed by the first)
        settings = settings or ControllerSettings(rx_buffer=RX_BUFFER, banner=False)
        if settings.keepalive is not None:  # Marlin's busy lines: not this link's
            settings = replace(settings, keepalive=None)
        check_faults(settings.faults)
        super().__init__(settings, now=now, on_execute=on_execute)

    def control(self, text: str, now: float) -> None:
        """As the base's, and ``urgent_order newest|oldest``: the order urgent lines run in
        (the notes promise none; a controller may run the newest first)."""
        verb, _, argument = text.strip().partition(" ")
        if verb == "urgent_order":
            if argument.strip() not in ("newest", "oldest"):
                raise ValueError("urgent_order takes newest or oldest")
            self.urgent_newest_first = argument.strip() == "newest"
            return
        super().control(text, now)
        check_faults(self.faults)

    # --- the link ------------------------------------------------------------------

    def _arrived(self, data: bytes, now: float) -> None:
        self._heard_at = now
        if not _CONTROL_BYTES.isdisjoint(data):
            # In the order they came: an abort drops what was received before it, not
            # what comes after it.
            start = 0
            for at, byte in enumerate(data):
                if byte in _CONTROL_BYTES:
                    self._received(data[start:at], now)
                    self._act(Control(byte), now)
                    start = at + 1
            data = data[start:]
        self._received(data, now)

    def _received(self, data: bytes, now: float) -> None:
        """Bytes between control bytes: lines, or part of one."""
        if not data:
            return
        self.owed_acks += data.count(b"\n")
        if data.startswith(b"\x09") and data.endswith(b"\n"):
            # An urgent line (lines arrive one by one): ahead of the buffer and the queue.
            self._take_line(data[:-1], now)
            self._pay_acks(now)
            return
        self._buffer(data)
        self._pay_acks(now)

    def _fill_slots(self, now: float) -> None:
        super()._fill_slots(now)
        self._pay_acks(now)  # reading lines out frees room

    def _pay_acks(self, now: float) -> None:
        free = self.settings.rx_buffer - 1 - len(self._rx)
        owed = self.owed_acks
        if not owed or free < self.ack_headroom:
            return
        self.owed_acks = 0
        self.acks_sent += owed
        drop = self.faults.drop_ok
        if drop:
            for _ in range(owed):
                if self._chance(drop):
                    self.counts.dropped_oks += 1
                    owed -= 1
        if owed:
            self._reply(bytes([Control.ACK]) * owed, now)

    def _take_line(self, raw: bytes, now: float) -> None:
        line = read_line(raw)
        if line is None or not line.command:
            return  # a comment, or a bare N<n> (it only sets the number reports use)
        if not line.checksum_ok:
            where = f" (line {line.number})" if line.number is not None else ""
            self._reply(f">ER: checksum mismatch{where}: not run\n".encode(), now)
            return
        word = command_word(line.command)
        self._count_command(word, now)
        command = QueuedCommand(line.command, word, line.number, urgent=line.urgent)
        self._plan(command)
        queue = self._queue
        if not line.urgent:
            queue.append(command)
            return
        # Ahead of the queue, after the command in hand and urgent lines that came before
        # (ahead of those too, newest first, with ``urgent_order newest``).
        place = 0
        while place < len(queue) and (
            queue[place].started or (queue[place].urgent and not self.urgent_newest_first)
        ):
            place += 1
        queue.insert(place, command)

    def _act(self, control: Control, now: float) -> None:
        if control is Control.PING:
            self._reply(PING_REPLY, now)
        elif control is Control.ABORT:
            self._queue.clear()
            self._planner.drop()
            self._rx.clear()
            self._line.clear()
            self._planner.end = self._busy_until = now
            self._held = False
            self._reply(b">IN: aborted: every queued command dropped\n", now)
        elif control in (Control.PAUSE_AT_MOVE_END, Control.PAUSE_AT_LAYER_END):
            self._held = True
            self._reply(b">IN: paused\n", now)
        elif control is Control.END_WAIT:
            self._reply(bytes([Control.END_WAIT]), now)
            if self._held:
                self._held = False
                self._reply(b">IN: resumed\n", now)
            else:
                self._break_heat_wait(now)
        elif control is Control.STATUS:
            self._reply(f">ST: {self._temperatures(now)} Q:{len(self._queue)}\n".encode(), now)

    # --- the firmware --------------------------------------------------------------

    def _holding(self) -> bool:
        return self._held

    def _heater_for(self, kind: str, command: QueuedCommand, now: float) -> str | None:
        """Hyrel's T words address heads and beds: with one head (``extruders``), every
        head address is it; with several, ``T<n>`` is head n (v5 addressing) and no T the
        active tool's. A group (T40 all devices, T41 yoke 1, T47 every head) is its first
        head here; :meth:`_set_heater` sets every one."""
        if kind == "C":
            return "C" if "C" in self.heaters else None
        if kind == "B" or self.settings.extruders == 1:
            return kind
        match = T_WORD.search(command.text[len(command.word) :])
        index = int(match.group(1)) if match else self.tool
        return "T" if index == 0 or index >= self.settings.extruders else f"T{index}"

    def _set_heater(self, command: QueuedCommand, now: float) -> None:
        """As the base does; a group address sets every head."""
        super()._set_heater(command, now)
        match = T_WORD.search(command.text[len(command.word) :])
        if command.word == "M104" and match and int(match.group(1)) in ALL_HEADS:
            for index in range(1, self.settings.extruders):
                self.heaters.set_target(f"T{index}", command.text, now)

    def _process_head(self, now: float) -> bool:
        if self._held:
            return False
        return super()._process_head(now)

    def _ok(self, line: bytes, now: float) -> None:
        """No oks on this link."""

    def _answer(self, command: QueuedCommand, now: float) -> None:
        word = command.word
        metrics = self.metrics
        if word in _MOVES:
            if metrics is not None:
                metrics.move(command.text)
            return
        self._set_heater(command, now)
        if word[:1] == "T" and word[1:].isdigit() and int(word[1:]) < self.settings.extruders:
            self.tool = int(word[1:])
        if metrics is not None:
            metrics.set_mode(word, command.text)
        if word == "M112":
            # The notes say nothing of what Hyrel's M112 does: this fake does the least a
            # host may count on. It drops what it holds and goes on answering, its heaters
            # as they were (a host must turn them off itself).
            self._queue.clear()
            self._planner.drop()
            self._rx.clear()
            self._reply(b">ER: M112: emergency stop: queued lines and moves dropped\n", now)
        elif word == "M105":
            self._reply(f">ST: {self._temperatures(now)}\n".encode(), now)
        elif word == "M115":
            twice = self._chance(self.faults.identity_twice)
            self._reply(M115_REPLY * (1 + twice), now)
        elif word == "G4" and self._chance(self.faults.unasked_identity):
            self._reply(b">IN: " + M115_REPLY, now)
        elif word == "M772":
            match = re.search(r"S\s*(\d+)", command.text)
            self._reports = int(match.group(1)) if match else 0
            self.metrics = Metrics()  # the counts start again, from X0 Y0 Z0 as this fake has it
        elif word == "M773" or (word == "M30" and self._reports & 1):
            lines = (metrics or Metrics()).report()
            self._reply("".join(f"{line}\n" for line in lines).encode(), now)
        if word in ("M0", "M1"):
            self._held = True  # until end-wait
        if word in NOTICED:
            fields = "".join(f" {part}:" for part in command.text.split()[1:] if part[:1] in "TSPE")
            self._reply(f">MC:{word}:{fields}\n".encode(), now)

    def _reboot(self, now: float) -> None:
        super()._reboot(now)
        self.owed_acks = 0
        self._held = False

    def _boot_banner(self) -> bytes:
        return RESTART_REPLY

    # --- the watchdog --------------------------------------------------------------

    def _next_internal_time(self) -> float | None:
        time = super()._next_internal_time()
        due = self._watchdog_due()
        if due is None:
            return time
        return due if time is None else min(time, due)

    def _watchdog_due(self) -> float | None:
        heard = self._heard_at
        return None if heard is None or self.hung else heard + self.watchdog

    def _step(self, now: float) -> None:
        super()._step(now)
        due = self._watchdog_due()
        if due is not None and now >= due:
            self._heard_at = None  # tripped: armed again by the host's next byte
            self.watchdog_trips += 1
            self.heaters.turn_off("T")  # the heads; the bed stays as it was
            self._reply(
                f">ER: host watchdog: no byte for {self.watchdog:g} s; "
                "every extruder stopped\n".encode(),
                now,
            )
