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
            return replace(self, jerk={**self.jerk, **per_axis})
        if word == "M204":
            printing = values.get("P", values.get("S", self.print_acceleration))
            return replace(
                self,
                print_acceleration=printing,
                retract_acceleration=values.get("R", self.retract_acceleration),
                travel_acceleration=values.get("T", values.get("S", self.travel_acceleration)),
            )
        return self


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


@dataclass
class Estimator:
    """Feed it a file's commands in order; :meth:`finish` gives the estimate.

    ``on_time(line, seconds)``: called as the time at the end of each move's (and dwell's)
    source line becomes known, in order."""

    limits: Limits = DEFAULT_LIMITS
    on_time: Callable[[int, float], None] | None = None
    lookahead: int = LOOKAHEAD  # blocks kept behind the newest (a firmware's planner size)
    seconds: float = 0.0
    moves: int = 0
    _position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    _absolute: bool = True
    _absolute_e: bool = True
    _scale: float = 1.0  # 25.4 after G20
    _feed: float = 25.0  # mm/s (F1500, Marlin's start)
    _feed_factor: float = 1.0  # M220
    _flow_factor: float = 1.0  # M221 (the E axis's speed)
    _blocks: list[_Block] = field(default_factory=list)
    _previous: _Block | None = None

    def feed(self, line: int, command: str) -> None:
        """One command of the file (its source ``line``), comments already removed."""
        text = command.strip()
        if not text:
            return
        head = command_word(text)
        if head in ("G0", "G1"):
            self._move(line, command_words(text))
        elif head == "G4":
            words = command_words(text)
            seconds = words.get("S", 0.0) + words.get("P", 0.0) / 1000.0
            self._dwell(line, seconds)
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
            for letter, value in command_words(text).items():
                if letter in AXES:
                    self._position[AXES.index(letter)] = value * self._scale
        elif head == "G28":
            rest = command_rest(text)
            named = [a for a in "XYZ" if a in rest] or list("XYZ")
            for axis in named:
                self._position[AXES.index(axis)] = 0.0
        elif head == "M220":
            self._feed_factor = command_words(text).get("S", 100.0) / 100.0
        elif head == "M221":
            self._flow_factor = command_words(text).get("S", 100.0) / 100.0
        elif head in ("M201", "M203", "M204", "M205"):
            limits = self.limits.with_words(head, command_words(text))
            self.limits = replace(limits, source="the file's M201-M205 lines")

    def finish(self) -> Estimate:
        """Every block done: the estimate."""
        self.flush()
        return Estimate(self.seconds, self.moves, self.limits.source)

    def flush(self) -> None:
        """Every block waiting done now, as when no move follows for a while (each one's
        time told); the next move still joins the last one at the jerk's speed."""
        self._plan(keep=0)

    def _dwell(self, line: int, seconds: float) -> None:
        # The planner empties before a dwell (Marlin's G4 waits for the moves).
        self._plan(keep=0)
        self._previous = None
        self.seconds += seconds
        if self.on_time is not None:
            self.on_time(line, self.seconds)

    def _move(self, line: int, words: dict[str, float]) -> None:
        if "F" in words:
            self._feed = words["F"] * self._scale / 60.0
        target = list(self._position)
        for index, axis in enumerate(AXES):
            if axis in words:
                value = words[axis] * self._scale
                relative = not (self._absolute_e if axis == "E" else self._absolute)
                target[index] = self._position[index] + value if relative else value
        delta = [t - p for t, p in zip(target, self._position, strict=True)]
        self._position = target
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
        cruise = self._feed * self._feed_factor
        speeds = [cruise * d / distance for d in delta]
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
        safe = cruise
        for axis, speed in zip(AXES, speeds, strict=True):
            jerk = limits.jerk.get(axis, 0.0)
            if abs(speed) > jerk:
                safe = min(safe, jerk)
        junction = safe
        previous = self._previous
        if previous is not None and previous.cruise > 1e-4:
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
    return Limits(
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


def estimate_file(path: Path, machine: Limits | None = None) -> Estimate:
    """The estimate of the file at ``path``, read line by line (memory flat in its size),
    with the limits of its slicer's settings, else ``machine``'s, else the defaults."""
    with path.open("rb") as file:
        file.seek(0, 2)
        file.seek(max(0, file.tell() - TAIL_BYTES))
        tail = file.read().decode("utf-8", "replace").splitlines()
    comments = [line for line in tail if line.startswith(";")]
    limits = slicer_limits(comments, machine or DEFAULT_LIMITS)
    estimator = Estimator(limits or machine or DEFAULT_LIMITS)
    with path.open(encoding="utf-8", errors="replace") as file:
        for number, line in enumerate(file, 1):
            command = line.split(";", 1)[0]
            if command and not command.isspace():
                estimator.feed(number, command)
    return estimator.finish()
