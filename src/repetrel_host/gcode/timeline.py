"""A job's planned time at its lines, and the time it has left as it runs.

:class:`Timeline` keeps the estimator's time at the end of the job's lines (:mod:`repetrel_host.
gcode.estimate`'s ``on_time``) sparsely: a point a second or so apart, never more than
:data:`MOST_POINTS` (the spacing doubles when they would be), so a file of any size costs a
few hundred kilobytes at most. Heat waits are kept apart: their time is the heaters', not the
motion's; each wait is kept too, so that the heaters' live reports can say how long the wait
at hand has left.

:class:`TimeLeft` turns it into the seconds a running job has left at the move the controller
runs (the moves it holds behind the last one it acknowledged counted back): the plan's
remainder, its moving part scaled by how the run has gone so far
(actual ÷ planned time over the stretches it watched moving), blended in from a prior pace
(what this printer's past jobs took against their plans) as the print advances. The clock
is the caller's: nothing here reads the time.
"""

from __future__ import annotations

import bisect
import statistics
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from itertools import islice

from repetrel_host.gcode.estimate import HeatWait

MOST_POINTS = 4096
BLEND_SHARE = 0.1  # of the planned moving time: the run's own pace counts fully from there
# ...and, on a link that acknowledges lines as they arrive (Hyrel's), in proportion to what
# was watched against this many times what its buffer holds ahead of the move it runs: the
# run's pace is only as sure as where that move is (8 KB: up to minutes of slow moves).
SPREAD_WEIGHT = 2.0
PACE_JOBS = 5  # a printer's pace: the median of its last jobs' (one odd job does not sway it)
# Planned seconds not watched after the run starts or resumes: the controller's buffer fills
# in a burst, acknowledging lines well ahead of the motion (Hyrel's 8 KB hold up to about 20
# s of printing); from then on the lead is steady and cancels out of the pace.
SETTLE = 30.0
# A heater this close below its target has reached it (Marlin's M109 waits within a degree).
REACHED = 1.0
# An estimate of the time left above the clock's count by less than this (seconds, or this
# share of it) is not shown: the count goes on (a stretch's noise, a plan made finer).
RISE_SECONDS = 5.0
RISE_SHARE = 0.02
SMOOTHING = 10.0  # seconds over which the count is drawn to an estimate a little above it
UNREPORTED_WAIT = 30.0  # seconds (see TimeLeft._unfinished_wait)


@dataclass
class Countdown:
    """The time left as shown: an estimate below the clock's count from the figure shown
    last is shown at once; one above it by less than :data:`RISE_SECONDS` (or
    :data:`RISE_SHARE` of it) draws the count toward it over :data:`SMOOTHING` seconds,
    never above the figure shown last, so that a stretch's noise neither lifts it nor makes
    it run ahead; one that far above it is news (a slower printer, a longer heat-up), shown."""

    shown: float | None = None
    at: float = 0.0  # when it was shown (the caller's clock)

    def show(self, left: float, now: float, moving: bool = True) -> float:
        """The figure to give for ``left`` at ``now`` (``moving``: the count runs; not while
        the job is paused)."""
        if self.shown is not None:
            counted = max(0.0, self.shown - (now - self.at)) if moving else self.shown
            if counted < left < counted + max(RISE_SECONDS, RISE_SHARE * left):
                share = min(1.0, (now - self.at) / SMOOTHING)
                left = min(self.shown, counted + share * (left - counted))
        self.shown, self.at = left, now
        return left


@dataclass(frozen=True, slots=True)
class PlannedTime:
    """A job's planned time, split: its moves (and dwells), its heat waits, its tool
    changes' pauses (seconds, as the plan gives them)."""

    moving: float
    heating: float
    tool_changes: float = 0.0

    @classmethod
    def of(cls, total: float, heating: float, tool_changes: float) -> PlannedTime:
        """The split of a plan of ``total`` seconds, ``heating`` and ``tool_changes`` of them."""
        return cls(max(0.0, total - heating - tool_changes), heating, tool_changes)

    def total(self, pace: float = 1.0) -> float:
        """The whole job at ``pace`` (actual over planned moving time; heat waits as
        planned)."""
        return (self.moving + self.tool_changes) * pace + self.heating


def learned_pace(paces: Iterable[float]) -> float:
    """A printer's pace from its past jobs' (newest first): the median of the last
    :data:`PACE_JOBS`; 1 (as planned) when it has none."""
    recent = list(islice(paces, PACE_JOBS))
    return statistics.median(recent) if recent else 1.0


@dataclass
class Timeline:
    """The planned seconds at the end of a job's lines, kept sparsely (see the module)."""

    spacing: float = 1.0  # seconds between the points kept
    lines: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    heating: list[float] = field(default_factory=list)  # of the seconds, the heat waits'
    total: float = 0.0
    total_heating: float = 0.0
    tool_changes: float = 0.0  # of the total, the tool changes' pauses (the estimate's)
    command_bytes: int = 0  # the file's commands' bytes as they go (the estimate's)
    limits_from: str = ""  # where the plan's limits came from (the estimate's)
    moves: list[int] = field(default_factory=list)  # moves (and dwells) planned by each point
    total_moves: int = 0
    waits: list[HeatWait] = field(default_factory=list)  # the first MOST_POINTS, in order
    wait_moves: list[int] = field(default_factory=list)  # the moves planned before each
    _seen: tuple[int, float, float, int] | None = None  # the last point told, maybe not kept
    _heating: float = 0.0  # the heat waits' seconds so far, as last told

    @property
    def planned(self) -> PlannedTime:
        """The whole plan, split."""
        return PlannedTime.of(self.total, self.total_heating, self.tool_changes)

    def heated(self, wait: HeatWait) -> None:
        """A heat wait is planned (the estimator's ``on_heat``)."""
        self._heating = wait.heating
        if len(self.waits) < MOST_POINTS:
            self.waits.append(wait)
            self.wait_moves.append(self.total_moves)

    def few(self, most: int) -> tuple[tuple[int, float], ...]:
        """``most`` of the (line, planned seconds) kept, evenly spread, the last among them."""
        count = len(self.lines)
        step = max(1, -(-count // most))  # rounded up: never more than the most
        kept = [*range(step - 1, count - 1, step), count - 1] if count else []
        return tuple((self.lines[i], round(self.seconds[i], 2)) for i in kept)

    def heating_at(self, seconds: float) -> float:
        """The heat waits' planned seconds by ``seconds`` into the plan (at the point kept
        at or before it)."""
        index = bisect.bisect_right(self.seconds, seconds) - 1
        return self.heating[index] if index >= 0 else 0.0

    @property
    def wait_lines(self) -> list[int]:
        """The lines of the heat waits kept, in order."""
        return [wait.line for wait in self.waits]

    def waits_at(self, line: int, seconds: float) -> tuple[HeatWait | None, HeatWait | None]:
        """The heat wait the move at ``seconds`` (:meth:`running` at ``line``) may still be
        in (the last at or before ``line``, when it ends where that move is: a controller
        that acknowledges lines as it takes them keeps waiting after), and the next one."""
        index = bisect.bisect_right(self.wait_lines, line)
        last = self.waits[index - 1] if index > 0 else None
        if last is not None and seconds > last.starts + last.seconds + 1e-6:
            last = None
        return last, self.waits[index] if index < len(self.waits) else None

    def next_to(self, line: int, wait: HeatWait) -> bool:
        """No move is planned between ``line`` and ``wait``."""
        return self._moves_at(line) >= self.wait_moves[self.waits.index(wait)]

    def add(self, line: int, seconds: float) -> None:
        """The plan reaches ``seconds`` at the end of ``line`` (the estimator's ``on_time``);
        told in order."""
        heating = self._heating
        if heating != self.total_heating and self._seen is not None:
            self._keep(*self._seen)  # a wait: the point before it, so it is not spread
        self.total, self.total_heating = seconds, heating
        self.total_moves += 1
        self._seen = (line, seconds, heating, self.total_moves)
        if (
            not self.seconds
            or seconds - self.seconds[-1] >= self.spacing
            or heating != self.heating[-1]
        ):
            self._keep(*self._seen)

    def finish(self) -> None:
        """The plan is complete: its last point kept."""
        if self._seen is not None:
            self._keep(*self._seen)

    def _keep(self, line: int, seconds: float, heating: float, moves: int) -> None:
        if self.lines and line <= self.lines[-1]:  # the same line, later
            self.seconds[-1], self.heating[-1], self.moves[-1] = seconds, heating, moves
            return
        self.lines.append(line)
        self.seconds.append(seconds)
        self.heating.append(heating)
        self.moves.append(moves)
        if len(self.lines) > MOST_POINTS:  # every other one goes, the first and last stay
            keep = [*range(0, len(self.lines) - 1, 2), len(self.lines) - 1]
            self.lines = [self.lines[i] for i in keep]
            self.seconds = [self.seconds[i] for i in keep]
            self.heating = [self.heating[i] for i in keep]
            self.moves = [self.moves[i] for i in keep]
            self.spacing *= 2

    def running(self, line: int, held: float) -> tuple[float, float]:
        """:meth:`at` the move a controller runs when it acknowledged ``line`` and holds
        ``held`` moves (its planner's) behind the one it runs: that many moves earlier."""
        acknowledged = self.at(line)
        if held <= 0 or not self.lines:
            return acknowledged
        moves = self._moves_at(line) - held
        index = bisect.bisect_left(self.moves, moves)
        if index >= len(self.moves):
            return acknowledged
        if index <= 0 or self.heating[index - 1] != acknowledged[1]:
            if acknowledged[1] > 0:
                # A heat wait in between: it emptied the planner, so what runs is past it.
                first = bisect.bisect_left(self.heating, acknowledged[1])
                return min(self.seconds[first], acknowledged[0]), acknowledged[1]
            first_moves = self.moves[0]
            share = max(moves, 0.0) / first_moves if first_moves > 0 else 0.0
            return self.seconds[0] * share, 0.0
        before, after = self.moves[index - 1], self.moves[index]
        share = (moves - before) / (after - before) if after > before else 1.0
        start = self.seconds[index - 1]
        return start + share * (self.seconds[index] - start), self.heating[index - 1]

    def _moves_at(self, line: int) -> float:
        """The moves planned by the end of ``line``, in proportion between points."""
        index = bisect.bisect_left(self.lines, line)
        if index >= len(self.lines):
            return float(self.total_moves)
        if self.lines[index] == line:
            return float(self.moves[index])
        if index == 0:
            return self.moves[0] * line / self.lines[0] if self.lines[0] > 0 else 0.0
        before, after = self.lines[index - 1], self.lines[index]
        share = (line - before) / (after - before)
        return self.moves[index - 1] + share * (self.moves[index] - self.moves[index - 1])

    def at(self, line: int) -> tuple[float, float]:
        """The planned seconds at the end of ``line``, and the heat waits' share of them
        (between points kept, the line's share of the way)."""
        index = bisect.bisect_left(self.lines, line)
        if index >= len(self.lines):
            return self.total, self.total_heating
        if self.lines[index] == line or index == 0:
            if index == 0 and self.lines[0] != line:
                share = line / self.lines[0] if self.lines[0] > 0 else 1.0
                return self.seconds[0] * max(share, 0.0), 0.0
            return self.seconds[index], self.heating[index]
        before, after = self.lines[index - 1], self.lines[index]
        share = (line - before) / (after - before)
        heating = self.heating[index - 1]
        seconds = self.seconds[index - 1] + share * (self.seconds[index] - self.seconds[index - 1])
        return seconds, heating


@dataclass
class TimeLeft:
    """The seconds a running job has left (see the module). ``prior``: this printer's pace,
    actual over planned moving time, from its past jobs (1: as planned)."""

    timeline: Timeline
    prior: float = 1.0
    held: float = 0.0  # moves the controller holds acknowledged behind the one it runs
    watched_actual: float = 0.0  # seconds watched moving...
    watched_planned: float = 0.0  # ...and what the plan gave them
    _last: tuple[int, float] | None = None  # the last line seen and when
    _settled: float = 0.0  # the planned time from which it is watched (after a start or pause)
    _line: int = -1  # the line acknowledged last time the time left was asked
    # Every line acknowledged: when, and the time left then (the controller runs what it
    # holds, and no acknowledgement says how far it got).
    _drained: tuple[float, float] | None = None
    shown: Countdown = field(default_factory=Countdown)  # the time left given last
    # Acknowledgements say only that a line arrived (Hyrel's link): a heat wait among the
    # lines taken is over once its heater reports its target, not when lines after it go.
    received_only: bool = False
    _waits: dict[int, float | None] = field(default_factory=dict)  # by line: since / over
    _reckoned: tuple[float, float] | None = None  # the move that runs there, then (_reckon)
    _spread: float = 0.0  # planned seconds between the move that runs and the line taken last
    _spared: float = 0.0  # planned heat waits taken whose heaters are there already

    def observe(self, line: int, now: float, moving: bool = True, waiting: bool = False) -> None:
        """The controller acknowledged up to ``line`` by ``now``. ``moving``: False while the
        job is paused (the stretch around it is not watched, and the run settles again
        after). ``waiting``: it may be waiting for a heater (the stretch is not watched)."""
        last = self._last
        if waiting and last is not None:
            self._last = (line, now)
            return
        seconds, heating = self.timeline.running(line, self.held)
        if last is None or not moving:
            self._last = (line, now) if moving else None
            self._settled = seconds + SETTLE
            return
        if line == last[0]:
            return  # no line taken since: the stretch runs on until one is (acks come in bursts)
        self._last = (line, now)
        before, heating_before = self.timeline.running(last[0], self.held)
        if before < self._settled or line < last[0]:
            return  # watched from the first stretch that starts settled
        if heating != heating_before:  # a heat wait in between: the heaters' time, not watched
            return
        self.watched_actual += now - last[1]
        self.watched_planned += seconds - before

    @property
    def pace(self) -> float:
        """Actual over planned moving time: the run's own, blended in from the prior as it
        was watched (fully from :data:`BLEND_SHARE` of the plan's moving time)."""
        moving = self.timeline.total - self.timeline.total_heating
        if self.watched_planned <= 0 or moving <= 0:
            return self.prior
        weight = min(1.0, self.watched_planned / (BLEND_SHARE * moving))
        if self.received_only:  # where the move that runs is: anywhere in the buffer
            weight *= self.watched_planned / (self.watched_planned + SPREAD_WEIGHT * self._spread)
        run = self.watched_actual / self.watched_planned
        return (1 - weight) * self.prior + weight * run

    @property
    def corrected(self) -> bool:
        """The plan is no longer taken as it is: the run was watched, or the printer's past
        jobs said its pace."""
        return self.watched_planned > 0 or self.prior != 1.0

    def until(self, line: int, current: int) -> float:
        """The seconds until the end of ``line`` when the controller acknowledged up to
        ``current``: the plan between the move it runs and ``line``, its moving part at
        :attr:`pace` and its heat waits as planned; 0 for a line already run. It observes
        nothing (:meth:`left` does)."""
        ran, heated = self.timeline.running(current, self.held)
        seconds, heating = self.timeline.at(line)
        if seconds <= ran:
            return 0.0
        heat = max(0.0, heating - heated)
        return max(0.0, seconds - ran - heat) * self.pace + heat

    @property
    def measured(self) -> float | None:
        """The run's own pace, once a tenth of the plan's moving time was watched (what a
        printer's history learns from); None before."""
        moving = self.timeline.total - self.timeline.total_heating
        if moving <= 0 or self.watched_planned < 0.1 * moving:
            return None
        return self.watched_actual / self.watched_planned

    def left(
        self,
        line: int,
        now: float,
        moving: bool = True,
        heaters: Mapping[str, tuple[float, float | None]] | None = None,
    ) -> float:
        """The seconds left after ``line``, acknowledged by ``now`` (observed first): the
        plan's moving remainder at the pace, and its heat waits as planned. ``heaters``:
        the controller's latest reports ({"T0": (current, target)}, as the plan names
        them); the wait at hand then counts from where its heater is, and a wait is not
        watched as motion. Once every line is acknowledged, what the controller holds is
        counted down by the clock (no line moves then to tell the pace by). What is given
        counts down by the clock within :data:`RISE_SECONDS` of the estimate
        (:class:`Countdown`)."""
        if self.timeline.lines and line >= self.timeline.lines[-1] and moving:
            if self._drained is None:
                self._drained = (now, self._remainder(line, now, moving, heaters))
            self._last = (line, now)
            since, drained = self._drained
            left = max(0.0, drained - (now - since))
        else:
            self._drained = None
            left = self._remainder(line, now, moving, heaters)
        return self.shown.show(left, now, moving)

    def _remainder(
        self,
        line: int,
        now: float,
        moving: bool,
        heaters: Mapping[str, tuple[float, float | None]] | None,
    ) -> float:
        seconds, heating = self.timeline.running(line, self.held)
        if self.received_only:
            taken = self.timeline.at(line)[0]  # nothing after the line taken has arrived
            self._spread = max(0.0, taken - seconds)
            seconds = self._reckon(seconds, taken, now, moving)
            heating = self.timeline.heating_at(seconds)
        waiting, ahead = self.timeline.waits_at(line, seconds)
        waiting_short = _heating_to(waiting, heaters) if waiting is not None else None
        self._spared = 0.0
        if self.received_only and waiting_short is None:  # no report says where it is
            waiting, waiting_short = self._unfinished_wait(line, now, heaters)
        ahead_short = _heating_to(ahead, heaters) if ahead is not None else None
        # Maybe in a wait: the move that runs is at a wait's end (its line taken, lines after
        # it too), or the wait's line is next, and its heater is not reported there; then no
        # line taken since is no slow move.
        stalled = line == self._line and (
            (waiting is not None and waiting_short != 0.0)
            or (ahead is not None and ahead_short != 0.0 and self.timeline.next_to(line, ahead))
        )
        self._line = line
        if waiting is not None and waiting_short:  # still heating: in it
            seconds, heating = waiting.starts, waiting.heating - waiting.seconds
            ahead, ahead_short = waiting, waiting_short
            stalled = True
            self._reckoned = (seconds, now) if self.received_only else None
        self.observe(line, now, moving, waiting=stalled)
        heat_left = self.timeline.total_heating - heating
        moving_left = max(0.0, self.timeline.total - seconds - heat_left) * self.pace
        heat_left -= self._spared
        if ahead is not None and ahead_short is not None:  # counted from the heater's report
            before = max(0.0, ahead.starts - seconds) * self.pace  # it heats during those
            heat_left += max(0.0, ahead_short / ahead.rate - before) - ahead.seconds
        return max(0.0, moving_left + heat_left)

    def _reckon(self, lower: float, upper: float, now: float, moving: bool) -> float:
        """On a link that acknowledges lines as they arrive (in bursts, as its buffer frees):
        the planned seconds of the move that runs, counted on by the clock at the pace since
        last asked, kept between the move :attr:`held` back from the line taken last
        (``lower``) and that line's end (``upper``)."""
        last = self._reckoned
        position = lower
        if last is not None:
            position = last[0] + (now - last[1]) / self.pace if moving else last[0]
        position = min(max(position, lower), upper)
        self._reckoned = (position, now)
        return position

    def _unfinished_wait(
        self, line: int, now: float, heaters: Mapping[str, tuple[float, float | None]] | None
    ) -> tuple[HeatWait | None, float | None]:
        """On a link that acknowledges lines as they arrive: the first heat wait at or before
        ``line`` whose heater has not reported its target (a bed's before a hotend's), and
        the degrees it has still to climb (the plan's, until its report tells). One never
        reported at its target is over after twice its planned time and
        :data:`UNREPORTED_WAIT` seconds from when it was the one at hand. The waits taken
        after it whose heaters are there already will not wait (:attr:`_spared`)."""
        at_hand: tuple[HeatWait | None, float | None] = (None, None)
        for wait in self.timeline.waits[: bisect.bisect_right(self.timeline.wait_lines, line)]:
            if at_hand[0] is not None:
                self._spared += wait.seconds if _heating_to(wait, heaters) == 0.0 else 0.0
                continue
            since = self._waits.setdefault(wait.line, now)
            if since is None:
                continue  # over
            short = _heating_to(wait, heaters)
            if short == 0.0 or (short is None and now - since > 2 * wait.seconds + UNREPORTED_WAIT):
                self._waits[wait.line] = None
                continue
            at_hand = wait, short if short is not None else wait.seconds * wait.rate
        return at_hand


def _heating_to(
    wait: HeatWait, heaters: Mapping[str, tuple[float, float | None]] | None
) -> float | None:
    """The degrees ``wait``'s heater has still to climb, as it reports (0 when there), when
    it is set to the wait's target; None otherwise (the plan's figure stands)."""
    heard = heaters.get(wait.heater) if heaters else None
    if heard is None or heard[1] is None or wait.rate <= 0 or abs(heard[1] - wait.target) > 0.5:
        return None
    short = wait.target - heard[0]
    return short if short > REACHED else 0.0
