"""A file's print time from its moves, as the firmware's planner would run them.

Each move becomes a block with a trapezoid speed profile (accelerate, cruise, decelerate),
as Marlin's planner makes it: its feed rate capped per axis (``M203``), its acceleration the
print, retract or travel one (``M204``) capped per axis (``M201``), its speed at each
junction limited by the classic jerk (``M205 X Y Z E``: the largest instant change of an
axis's speed). Lookahead runs a reverse pass (a block must be able to slow down to what the
next one may enter at) and a forward pass (a block cannot enter faster than the one before
could accelerate to) over the blocks not yet done, then each done block's time is its
trapezoid's. This follows the estimator in PrusaSlicer's ``GCodeProcessor`` (itself
Marlin's planner), whose figure a slicer writes as "estimated printing time (normal mode)".

Beyond Marlin's moves: ``M205 J`` (junction deviation) in place of the classic jerk; ``G2``/
``G3`` arcs in Marlin's straight pieces; the heat waits (``M109``, ``M190``, ``M191``) from
where each heater is, at the profile's rates, counted apart (a slicer's figure leaves them
out); a tool change's time; and Hyrel's code chart where the caller says so (see
:meth:`Estimator.feed`).

Streaming and bounded: blocks are finished in batches, keeping :data:`LOOKAHEAD` behind the
newest for the passes, so memory does not grow with the file. The time at the end of each
move's source line is told as it is known (``on_time``), for a time left at any line.

The limits, first found wins: the file's own ``M201``-``M205`` lines (as they come), the
slicer's configuration block (:func:`slicer_limits`), the machine profile the caller gives,
else Marlin's defaults (:data:`DEFAULT_LIMITS`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path

from repetrel_host.gcode.commands import command_rest, command_word, command_words

AXES = "XYZE"
LOOKAHEAD = 64  # blocks kept behind the newest for the passes (PrusaSlicer keeps 64)
_EPSILON = 1e-9


@dataclass(frozen=True)
class Limits:
    """The planner's limits, in mm and seconds, and where they came from."""

    max_feedrate: dict[str, float]  # mm/s per axis (M203)
    max_acceleration: dict[str, float]  # mm/s² per axis (M201)
    jerk: dict[str, float]  # mm/s per axis (M205 X Y Z E)
    print_acceleration: float  # mm/s² (M204 P, or S)
    retract_acceleration: float  # M204 R
    travel_acceleration: float  # M204 T
    source: str = "defaults"
    # M205 J: Marlin's junction deviation (mm) in place of the classic jerk for X, Y and Z.
    junction_deviation: float = 0.0
    # Hyrel's rapid (G0) speed per axis, mm/s (its M203, written in mm/min); an axis not
    # given moves a G0 at its max_feedrate.
    rapid: dict[str, float] = field(default_factory=dict)
    # Degrees per second a heater gains, for the waits (M109, M190, M191): by "hotend",
    # "bed", "chamber".
    heat_rates: dict[str, float] = field(default_factory=dict)
    tool_change: float = 0.0  # seconds a tool change takes beyond its moves

    def with_words(self, word: str, values: dict[str, float]) -> Limits:
        """These limits after an ``M201``-``M205`` line of the file (``values``: its words; a
        value that is not above zero is no limit, and is left out)."""
        values = {letter: v for letter, v in values.items() if v > 0.0}
        per_axis = {letter: v for letter, v in values.items() if letter in AXES}
        if word == "M201":
            return replace(self, max_acceleration={**self.max_acceleration, **per_axis})
        if word == "M203":
            return replace(self, max_feedrate={**self.max_feedrate, **per_axis})
        if word == "M205":
            deviation = values.get("J", self.junction_deviation)
            return replace(self, jerk={**self.jerk, **per_axis}, junction_deviation=deviation)
        if word == "M204":
            printing = values.get("P", values.get("S", self.print_acceleration))
            return replace(
                self,
                print_acceleration=printing,
                retract_acceleration=values.get("R", self.retract_acceleration),
                travel_acceleration=values.get("T", values.get("S", self.travel_acceleration)),
            )
        return self


# How fast heaters gain when nothing better is known, in degrees per second: a 40 W hotend
# heats from 25 to 215 degrees in about a minute and a half, a 24 V bed from 25 to 60 in
# about a minute, a chamber far slower. A printer's history corrects what is off.
HOTEND_RATE = 2.0
BED_RATE = 0.5
CHAMBER_RATE = 0.1
AMBIENT = 25.0  # a heater's temperature at the start, when the caller does not say
MINIMUM_PLANNER_SPEED = 0.05  # mm/s: Marlin's, where junction deviation starts and ends
MM_PER_ARC_SEGMENT = 1.0  # Marlin cuts G2/G3 into straight pieces of this length

# Marlin's defaults for a Cartesian printer (Configuration.h: DEFAULT_MAX_FEEDRATE,
# DEFAULT_MAX_ACCELERATION, DEFAULT_ACCELERATION, DEFAULT_RETRACT_ACCELERATION,
# DEFAULT_TRAVEL_ACCELERATION, DEFAULT_XJERK..., DEFAULT_EJERK).
DEFAULT_LIMITS = Limits(
    max_feedrate={"X": 300.0, "Y": 300.0, "Z": 5.0, "E": 25.0},
    max_acceleration={"X": 3000.0, "Y": 3000.0, "Z": 100.0, "E": 10000.0},
    jerk={"X": 10.0, "Y": 10.0, "Z": 0.3, "E": 5.0},
    print_acceleration=3000.0,
    retract_acceleration=3000.0,
    travel_acceleration=3000.0,
    source="Marlin's defaults",
    heat_rates={"hotend": HOTEND_RATE, "bed": BED_RATE, "chamber": CHAMBER_RATE},
)


@dataclass
class _Block:
    line: int
    distance: float
    acceleration: float
    cruise: float  # nominal speed, mm/s
    safe: float  # speed it may start or end at from standstill (the jerk allows)
    max_entry: float
    entry: float
    nominal_length: bool
    axis_speed: tuple[float, float, float, float]  # signed, mm/s, at cruise

    def time(self, exit_speed: float) -> float:
        """Its trapezoid's duration, from ``entry`` to ``exit_speed``."""
        a, entry, cruise, d = self.acceleration, self.entry, self.cruise, self.distance
        accelerate = max(0.0, (cruise * cruise - entry * entry) / (2 * a))
        decelerate = max(0.0, (cruise * cruise - exit_speed * exit_speed) / (2 * a))
        cruising = d - accelerate - decelerate
        if cruising < 0.0:  # never reaches its cruise speed: up, then straight down
            accelerate = min(max((2 * a * d - entry * entry + exit_speed**2) / (4 * a), 0.0), d)
            cruising = 0.0
            cruise = math.sqrt(max(0.0, entry * entry + 2 * a * accelerate))
            decelerate = d - accelerate
        up = (cruise - entry) / a if accelerate > 0 else 0.0
        down = (cruise - exit_speed) / a if decelerate > 0 else 0.0
        return up + (cruising / cruise if cruise > 0 else 0.0) + max(down, 0.0)


def _max_allowable(acceleration: float, target: float, distance: float) -> float:
    """The speed from which ``distance`` at ``acceleration`` still reaches ``target``."""
    return math.sqrt(target * target + 2 * acceleration * distance)


@dataclass
class Estimate:
    """A file's estimated print time, and what it was found with."""

    seconds: float
    moves: int
    limits_from: str
    heating: float = 0.0  # of the seconds, those spent waiting for heaters
    tool_changes: int = 0
    tool_change_seconds: float = 0.0  # of the seconds, the tool changes' own pauses
    command_bytes: int = 0  # the file's commands' bytes, comments left out (estimate_file's)

    @property
    def moving(self) -> float:
        """The seconds without the heat waits: what a slicer's figure counts."""
        return self.seconds - self.heating


@dataclass(frozen=True, slots=True)
class HeatWait:
    """A heat wait as planned: its ``line``, ``heater`` ("T0", "B", "C"), ``target`` and the
    heater's ``rate`` (degrees a second), the planned seconds it ``starts`` at and the
    ``seconds`` it waits; ``heating``: every wait's seconds so far, its own counted."""

    line: int
    heater: str
    target: float
    rate: float
    starts: float
    seconds: float
    heating: float


_HEATER_WAITS = {"M109": "hotend", "M190": "bed", "M191": "chamber"}
_HEATER_SETS = {"M104": "hotend", "M140": "bed", "M141": "chamber"}


@dataclass
class _Heater:
    """A heater as the estimate follows it: where it was at ``since``, and its target."""

    temperature: float
    since: float
    target: float
    rate: float

    def at(self, now: float) -> float:
        if self.temperature >= self.target:
            return self.target  # cooling does not hold a print up
        return min(self.target, self.temperature + self.rate * (now - self.since))


@dataclass
class Estimator:
    """Feed it a file's commands in order; :meth:`finish` gives the estimate.

    ``on_time(line, seconds)``: called as the time at the end of each move's (and dwell's)
    source line becomes known, in order. ``hyrel``: the file runs on a Hyrel controller,
    whose code chart differs from Marlin's (see :meth:`feed`). ``temperatures``: each
    heater's temperature at the start ("T0", "B", "C"; else :data:`AMBIENT`)."""

    limits: Limits = DEFAULT_LIMITS
    on_time: Callable[[int, float], None] | None = None
    lookahead: int = LOOKAHEAD  # blocks kept behind the newest (a firmware's planner size)
    # Told each heat wait as it is planned (before its on_time).
    on_heat: Callable[[HeatWait], None] | None = None
    hyrel: bool = False
    temperatures: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    moves: int = 0
    heating: float = 0.0
    tool_changes: int = 0
    _position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    _absolute: bool = True
    _absolute_e: bool = True
    _scale: float = 1.0  # 25.4 after G20
    _feed: float = 25.0  # mm/s (F1500, Marlin's start)
    _feed_factor: float = 1.0  # M220
    _flow_factor: float = 1.0  # M221 (the E axis's speed)
    _tool: str = "0"
    _heaters: dict[str, _Heater] = field(default_factory=dict)
    _blocks: list[_Block] = field(default_factory=list)
    _previous: _Block | None = None
    _previous_unit: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Hyrel: M674's turbo threshold (mm; None: off), each head's prime dwell (M722 P, s),
    # and whether the last move printed (a prime dwells where printing starts again).
    _turbo: float | None = None
    _prime: dict[str, float] = field(default_factory=dict)
    _printing: bool = False

    def feed(self, line: int, command: str) -> None:
        """One command of the file (its source ``line``), comments already removed.

        On a Hyrel controller a G0 without F runs at the rapid speed (M203 sets it per axis,
        in mm/min) and one with F does not keep it; M674 S runs a G1 that does not print, and
        is longer than S, as a G0; E never holds the motion back (the head extrudes as the
        motion goes); and each start of printing after a move that did not print dwells the
        head's prime time (M722 P, in ms)."""
        text = command.strip()
        if not text:
            return
        head = command_word(text)
        if head in ("G0", "G1"):
            self._move(line, head, _finite_words(text))
        elif head in ("G2", "G3"):
            self._arc(line, head == "G2", _finite_words(text))
        elif head == "G4":
            words = command_words(text)
            self._pause(line, words.get("S", 0.0) + words.get("P", 0.0) / 1000.0)
        elif head == "G90":
            self._absolute = self._absolute_e = True
        elif head == "G91":
            self._absolute = self._absolute_e = False
        elif head == "M82":
            self._absolute_e = True
        elif head == "M83":
            self._absolute_e = False
        elif head == "G20":
            self._scale = 25.4
        elif head == "G21":
            self._scale = 1.0
        elif head == "G92":
            given = {a: v for a, v in _finite_words(text).items() if a in AXES}
            for letter, value in (given or dict.fromkeys(AXES, 0.0)).items():  # bare: all 0
                self._position[AXES.index(letter)] = value * self._scale
        elif head == "M400":  # the moves end; the next one starts from rest
            self._pause(line, 0.0)
        elif head == "G28":
            rest = command_rest(text)
            named = [a for a in "XYZ" if a in rest] or list("XYZ")
            for axis in named:
                self._position[AXES.index(axis)] = 0.0
        elif head == "M220":
            self._feed_factor = command_words(text).get("S", 100.0) / 100.0
        elif head == "M221":
            self._flow_factor = command_words(text).get("S", 100.0) / 100.0
        elif head in _HEATER_SETS or head in _HEATER_WAITS:
            self._heat(line, head, _finite_words(text))
        elif head[0] == "T" and head[1:].isdigit():
            self._tool_change(line, head[1:])
        elif self.hyrel and head == "M203":
            speeds = {a: v / 60.0 for a, v in command_words(text).items() if a in AXES and v > 0}
            rapid = {**self.limits.rapid, **speeds}
            self.limits = replace(self.limits, rapid=rapid, source="the file's M201-M205 lines")
        elif self.hyrel and head == "M674":
            self._turbo = command_words(text).get("S")
        elif self.hyrel and head == "M722":
            words = _finite_words(text)
            if "P" in words:
                self._prime[str(int(words.get("T", 0)))] = max(words["P"], 0.0) / 1000.0
        elif head in ("M201", "M203", "M204", "M205"):
            limits = self.limits.with_words(head, command_words(text))
            self.limits = replace(limits, source="the file's M201-M205 lines")

    def finish(self) -> Estimate:
        """Every block done: the estimate."""
        self.flush()
        return Estimate(
            self.seconds,
            self.moves,
            self.limits.source,
            self.heating,
            self.tool_changes,
            self.tool_changes * self.limits.tool_change,
        )

    def flush(self) -> None:
        """Every block waiting done now, as when no move follows for a while (each one's
        time told); the next move still joins the last one at the jerk's speed."""
        self._plan(keep=0)

    def _pause(self, line: int, seconds: float) -> None:
        """The planner empties, then ``seconds`` pass (a dwell, a wait, a tool change)."""
        self._plan(keep=0)
        self._previous = None
        self.seconds += seconds
        if self.on_time is not None:
            self.on_time(line, self.seconds)

    def _heater(self, name: str, kind: str) -> _Heater:
        heater = self._heaters.get(name)
        if heater is None:
            start = self.temperatures.get(name, AMBIENT)
            rate = self.limits.heat_rates.get(kind, DEFAULT_LIMITS.heat_rates[kind])
            heater = self._heaters[name] = _Heater(start, 0.0, start, rate)
        return heater

    def _heat(self, line: int, head: str, words: dict[str, float]) -> None:
        kind = _HEATER_SETS.get(head) or _HEATER_WAITS[head]
        if kind == "hotend":
            name = f"T{int(words['T'])}" if "T" in words else f"T{self._tool}"
        else:
            name = "B" if kind == "bed" else "C"
        heater = self._heater(name, kind)
        target = words.get("S", words.get("R"))
        if head in _HEATER_WAITS:
            self._plan(keep=0)  # the moves before it run while it is read: counted first
        now = self.seconds
        if target is not None:
            heater.temperature, heater.since, heater.target = heater.at(now), now, target
        if head in _HEATER_WAITS and heater.rate > 0:
            wait = max(0.0, heater.target - heater.at(now)) / heater.rate
            self.heating += wait
            if self.on_heat is not None:
                told = HeatWait(line, name, heater.target, heater.rate, now, wait, self.heating)
                self.on_heat(told)
            self._pause(line, wait)

    def _tool_change(self, line: int, tool: str) -> None:
        tool = tool.lstrip("0") or "0"  # T01 is T1 (and no T of 8,000 digits is an int)
        if tool == self._tool:
            return
        self._tool = tool
        self.tool_changes += 1
        if self.limits.tool_change > 0:
            self._pause(line, self.limits.tool_change)

    def _target(self, words: dict[str, float]) -> list[float]:
        """Where a move's words take the axes, in mm from the origin."""
        target = list(self._position)
        for index, axis in enumerate(AXES):
            if axis in words:
                value = words[axis] * self._scale
                relative = not (self._absolute_e if axis == "E" else self._absolute)
                target[index] = self._position[index] + value if relative else value
        return target

    def _move(self, line: int, head: str, words: dict[str, float]) -> None:
        feed = self._feed
        if "F" in words:
            feed = words["F"] * self._scale / 60.0
            if not (self.hyrel and head == "G0"):  # Hyrel's G0 F is for that move only
                self._feed = feed
        target = self._target(words)
        if self.hyrel:
            rapid = head == "G0" and "F" not in words
            if self._turbo is not None and head == "G1" and "E" not in words:
                span = math.dist(target[:3], self._position[:3])
                rapid = span > self._turbo
            if rapid:
                feed = math.inf
        self._segment(line, target, feed)

    def _arc(self, line: int, clockwise: bool, words: dict[str, float]) -> None:
        """G2/G3 as Marlin runs it: straight pieces of about :data:`MM_PER_ARC_SEGMENT`."""
        if "F" in words:
            self._feed = words["F"] * self._scale / 60.0
        start = self._position
        end = self._target(words)
        x0, y0 = start[0], start[1]
        dx, dy = end[0] - x0, end[1] - y0
        if "R" in words:  # the centre on the chord's bisector, R's sign choosing the side
            radius = words["R"] * self._scale
            chord = math.hypot(dx, dy)
            if chord < _EPSILON or abs(radius) * 2 < chord:
                self._segment(line, end, self._feed)
                return
            h = math.sqrt(radius * radius - chord * chord / 4) / chord
            h = -h if clockwise == (radius > 0) else h
            cx, cy = x0 + dx / 2 - h * dy, y0 + dy / 2 + h * dx
        else:
            cx = x0 + words.get("I", 0.0) * self._scale
            cy = y0 + words.get("J", 0.0) * self._scale
        radius = math.hypot(x0 - cx, y0 - cy)
        begin = math.atan2(y0 - cy, x0 - cx)
        sweep = math.atan2(end[1] - cy, end[0] - cx) - begin
        if clockwise and sweep >= -_EPSILON:
            sweep -= 2 * math.pi
        elif not clockwise and sweep <= _EPSILON:
            sweep += 2 * math.pi
        travel = math.hypot(sweep * radius, end[2] - start[2])
        pieces = max(1, int(travel / MM_PER_ARC_SEGMENT))
        z0, e0 = start[2], start[3]
        for piece in range(1, pieces):
            share = piece / pieces
            angle = begin + sweep * share
            point = [
                cx + radius * math.cos(angle),
                cy + radius * math.sin(angle),
                z0 + (end[2] - z0) * share,
                e0 + (end[3] - e0) * share,
            ]
            self._segment(line, point, self._feed)
        self._segment(line, end, self._feed)

    def _segment(self, line: int, target: list[float], feed: float) -> None:
        """One straight move to ``target`` at ``feed`` mm/s (inf: as fast as allowed)."""
        delta = [t - p for t, p in zip(target, self._position, strict=True)]
        self._position = target
        if self.hyrel:
            printing = delta[3] > _EPSILON
            if printing and not self._printing:
                dwell = self._prime.get(self._tool)
                if dwell is None and len(self._prime) == 1:
                    dwell = next(iter(self._prime.values()))
                if dwell:
                    self._pause(line, dwell)
            self._printing = printing
            delta[3] = 0.0  # the head extrudes as the motion goes: E holds nothing back
        if not any(abs(d) > _EPSILON for d in delta):
            return
        limits = self.limits
        dx, dy, dz, de = delta
        xyz = math.sqrt(dx * dx + dy * dy + dz * dz)
        distance = xyz if xyz > _EPSILON else abs(de)
        moves_xyz = xyz > _EPSILON
        if not moves_xyz:
            acceleration = limits.retract_acceleration
        elif de > _EPSILON and (abs(dx) > _EPSILON or abs(dy) > _EPSILON):
            acceleration = limits.print_acceleration
        else:
            acceleration = limits.travel_acceleration
        units = [d / distance for d in delta]
        if math.isinf(feed):  # as fast as every axis's rapid (else top) speed allows
            tops = [
                limits.rapid.get(axis, limits.max_feedrate.get(axis, 0.0)) / abs(u)
                for axis, u in zip(AXES, units, strict=True)
                if abs(u) > _EPSILON and limits.rapid.get(axis, limits.max_feedrate.get(axis))
            ]
            cruise = min(tops, default=self._feed)
            speeds = [cruise * u for u in units]
        else:
            cruise = feed * self._feed_factor
            speeds = [cruise * u for u in units]
            speeds[3] *= self._flow_factor
            factor = 1.0
            for axis, speed in zip(AXES, speeds, strict=True):
                top = limits.max_feedrate.get(axis, 0.0)
                if speed != 0.0 and top > 0.0:
                    factor = min(factor, top / abs(speed))
            if factor < 1.0:
                cruise *= factor
                speeds = [s * factor for s in speeds]
        for axis, d in zip(AXES, delta, strict=True):
            top = limits.max_acceleration.get(axis, 0.0)
            if abs(d) > _EPSILON and top > 0.0 and acceleration * abs(d) / distance > top:
                acceleration = top / (abs(d) / distance)
        deviation = limits.junction_deviation
        if deviation > 0.0:
            safe = min(MINIMUM_PLANNER_SPEED, cruise)
        else:
            safe = cruise
            for axis, speed in zip(AXES, speeds, strict=True):
                jerk = limits.jerk.get(axis, 0.0)
                if abs(speed) > jerk:
                    safe = min(safe, jerk)
        junction = safe
        previous = self._previous
        unit = (units[0], units[1], units[2]) if moves_xyz else (0.0, 0.0, 0.0)
        if previous is not None and previous.cruise > 1e-4:
            if deviation > 0.0:
                junction = _deviation_junction(
                    previous, self._previous_unit, unit, cruise, acceleration, limits
                )
            else:
                junction = _junction(previous, cruise, speeds, safe, limits.jerk)
        allowable = _max_allowable(acceleration, safe, distance)
        block = _Block(
            line,
            distance,
            acceleration,
            cruise,
            safe,
            junction,
            min(junction, allowable),
            cruise <= allowable,
            (speeds[0], speeds[1], speeds[2], speeds[3]),
        )
        self._blocks.append(block)
        self._previous = block
        self._previous_unit = unit
        self.moves += 1
        if len(self._blocks) >= 2 * self.lookahead:
            self._plan(keep=self.lookahead)

    def _plan(self, keep: int) -> None:
        """The passes over the blocks waiting, then every one but the last ``keep`` done."""
        blocks = self._blocks
        if not blocks:
            return
        for before, after in pairwise(blocks):  # forward
            if not before.nominal_length and before.entry < after.entry:
                reach = _max_allowable(before.acceleration, before.entry, before.distance)
                after.entry = min(after.entry, reach)
        for index in range(len(blocks) - 1, 0, -1):  # reverse
            block, after = blocks[index - 1], blocks[index]
            if block.entry != block.max_entry:
                if not block.nominal_length and block.max_entry > after.entry:
                    reach = _max_allowable(block.acceleration, after.entry, block.distance)
                    block.entry = min(block.max_entry, reach)
                else:
                    block.entry = block.max_entry
        done = len(blocks) - keep
        on_time = self.on_time
        for index in range(done):
            block = blocks[index]
            exit_speed = blocks[index + 1].entry if index + 1 < len(blocks) else block.safe
            self.seconds += block.time(exit_speed)
            if on_time is not None:
                on_time(block.line, self.seconds)
        del blocks[:done]


def _junction(
    previous: _Block, cruise: float, speeds: list[float], safe: float, jerks: dict[str, float]
) -> float:
    """The speed the new block may enter at after ``previous``: Marlin's classic jerk."""
    larger = previous.cruise > cruise
    smaller_factor = cruise / previous.cruise if larger else previous.cruise / cruise
    junction = cruise if larger else previous.cruise
    factor = 1.0
    limited = False
    for axis, exit_speed, entry_speed in zip(AXES, previous.axis_speed, speeds, strict=True):
        v_exit = exit_speed * smaller_factor if larger else exit_speed
        v_entry = entry_speed
        if limited:
            v_exit *= factor
            v_entry *= factor
        if v_exit > v_entry:
            jerk = v_exit - v_entry if (v_entry > 0 or v_exit < 0) else max(v_exit, -v_entry)
        else:
            jerk = v_entry - v_exit if (v_entry < 0 or v_exit > 0) else max(-v_exit, v_entry)
        allowed = jerks.get(axis, 0.0)
        if jerk > allowed:
            factor *= allowed / jerk
            limited = True
    if limited:
        junction *= factor
    threshold = junction * 0.99
    if previous.safe > threshold and safe > threshold:  # not coasting: each starts afresh
        junction = safe
    return junction


def _finite_words(command: str) -> dict[str, float]:
    """A command's words that are numbers a machine can go to (``X1e999`` is none)."""
    return {
        letter: value for letter, value in command_words(command).items() if math.isfinite(value)
    }


def _deviation_junction(
    previous: _Block,
    previous_unit: tuple[float, float, float],
    unit: tuple[float, float, float],
    cruise: float,
    acceleration: float,
    limits: Limits,
) -> float:
    """The speed the new block may enter at after ``previous``: Marlin's junction deviation
    (the corner taken as an arc that strays ``M205 J`` from it, at the acceleration)."""
    cos_theta = -sum(a * b for a, b in zip(previous_unit, unit, strict=True))
    if cos_theta > 0.999999:  # straight back: a stop
        return MINIMUM_PLANNER_SPEED
    if cos_theta < -0.999999:  # straight on
        return min(previous.cruise, cruise)
    corner = [b - a for a, b in zip(previous_unit, unit, strict=True)]
    length = math.sqrt(sum(c * c for c in corner)) or 1.0
    for axis, part in zip("XYZ", corner, strict=True):  # the axes' own acceleration limits
        top = limits.max_acceleration.get(axis, 0.0)
        if abs(part) > _EPSILON and top > 0.0:
            acceleration = min(acceleration, top * length / abs(part))
    sin_half = math.sqrt(0.5 * (1.0 - cos_theta))
    speed = math.sqrt(acceleration * limits.junction_deviation * sin_half / (1.0 - sin_half))
    return min(speed, previous.cruise, cruise)


def estimate(commands: Iterable[tuple[int, str]], limits: Limits = DEFAULT_LIMITS) -> Estimate:
    """The estimate of ``(source line, command)`` pairs."""
    estimator = Estimator(limits)
    for line, command in commands:
        estimator.feed(line, command)
    return estimator.finish()


_SETTING = re.compile(r";\s*(machine_max_[a-z_]+)\s*=\s*([-\d.]+)")


def slicer_limits(comments: Iterable[str], base: Limits = DEFAULT_LIMITS) -> Limits | None:
    """The limits a slicer's configuration block gives (PrusaSlicer, SuperSlicer and Orca
    write ``; machine_max_feedrate_x = 500,200``: the normal mode's first), over ``base``;
    None when it gives none."""
    found: dict[str, float] = {}
    for text in comments:
        match = _SETTING.match(text)
        if match is not None:
            found[match.group(1)] = float(match.group(2))
    if not found:
        return None

    def per_axis(prefix: str, known: dict[str, float]) -> dict[str, float]:
        given = {a: found[prefix + a.lower()] for a in AXES if prefix + a.lower() in found}
        return {**known, **given}

    def acceleration(setting: str, known: float) -> float:
        value = found.get(setting, 0.0)
        return value if value > 0.0 else known

    printing = acceleration("machine_max_acceleration_extruding", base.print_acceleration)
    return replace(  # the rest (heat rates, tool changes, rapids) stays the machine's
        base,
        max_feedrate=per_axis("machine_max_feedrate_", base.max_feedrate),
        max_acceleration=per_axis("machine_max_acceleration_", base.max_acceleration),
        jerk=per_axis("machine_max_jerk_", base.jerk),
        print_acceleration=printing,
        retract_acceleration=acceleration(
            "machine_max_acceleration_retracting", base.retract_acceleration
        ),
        # A slicer that gives no travel acceleration plans travel at the print one.
        travel_acceleration=acceleration("machine_max_acceleration_travel", printing),
        source="the file's slicer settings",
    )


TAIL_BYTES = 256 * 1024  # where a slicer's configuration block is: the file's end


def file_limits(path: Path, machine: Limits | None = None) -> Limits:
    """The limits the file's slicer settings give (read from its last :data:`TAIL_BYTES`),
    over ``machine``'s, else over the defaults; ``machine``'s (or the defaults) when it has
    none. The file's own ``M201``-``M205`` lines act later, as they come."""
    base = machine or DEFAULT_LIMITS
    with path.open("rb") as file:
        file.seek(0, 2)
        file.seek(max(0, file.tell() - TAIL_BYTES))
        tail = file.read().decode("utf-8", "replace").splitlines()
    comments = [line for line in tail if line.startswith(";")]
    return slicer_limits(comments, base) or base


@dataclass(frozen=True, slots=True)
class PlanSettings:
    """How a file is planned: the machine's limits (None: the defaults), Hyrel's code chart
    or not, and the commands that run before it (a job's header). One printer plans a file
    the same way for its list, its check and its job; only where its heaters start differs."""

    limits: Limits | None = None
    hyrel: bool = False
    first: tuple[str, ...] = ()

    def estimate(
        self,
        path: Path,
        temperatures: dict[str, float] | None = None,
        on_time: Callable[[int, float], None] | None = None,
        on_heat: Callable[[HeatWait], None] | None = None,
    ) -> Estimate:
        """:func:`estimate_file` of ``path`` planned so."""
        return estimate_file(
            path,
            self.limits,
            hyrel=self.hyrel,
            temperatures=temperatures,
            on_time=on_time,
            on_heat=on_heat,
            first=self.first,
        )


def estimate_file(
    path: Path,
    machine: Limits | None = None,
    *,
    hyrel: bool = False,
    temperatures: dict[str, float] | None = None,
    on_time: Callable[[int, float], None] | None = None,
    on_heat: Callable[[HeatWait], None] | None = None,
    first: Iterable[str] = (),
) -> Estimate:
    """The estimate of the file at ``path``, read line by line (memory flat in its size),
    with the limits of its slicer's settings, else ``machine``'s, else the defaults.
    ``first``: commands that run before the file (a job's header; their line is 0).
    ``hyrel``, ``temperatures``, ``on_time``, ``on_heat``: as :class:`Estimator` takes them."""
    estimator = Estimator(
        file_limits(path, machine),
        on_time,
        on_heat=on_heat,
        hyrel=hyrel,
        temperatures=dict(temperatures or {}),
    )
    for command in first:
        estimator.feed(0, command)
    sent = 0  # the commands' bytes, as they go (without comments, with a line end)
    with path.open(encoding="utf-8", errors="replace") as file:
        for number, line in enumerate(file, 1):
            command = line.split(";", 1)[0]
            if command and not command.isspace():
                estimator.feed(number, command)
                sent += len(command.strip()) + 1
    return replace(estimator.finish(), command_bytes=sent)
