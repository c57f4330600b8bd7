"""Why a controller is silent: what it was given, read before a silence is suspected.

A Marlin-style controller answers a line (``ok``) once it took it to run: a move once its
planner had room for it, so nothing at all while the planner is full of long moves; G4,
M400 and G28 once the moves before them ran and they finished; a heat wait (M109, M190,
M191) once its heater got there, reporting the temperatures meanwhile; and a command that
holds the queue long says ``busy: processing`` every 2 s. A lost ``ok`` looks like each of
these silences. :class:`Silence` says until when a silence is explained by what the host
sent, so that the host asks (a probe) only after that: on a healthy link it never has to.

The moves' time is the planner estimate's (:mod:`~repetrel_host.gcode.estimate`), run on
the lines as they were sent, lazily: only when a silence needs explaining are the lines
sent since fed to it, so a link whose controller answers at once never pays for it. It is
scaled by the *pace* the controller keeps (its acknowledgements against the plan: a
printer slower than Marlin's defaults, a fake that runs its moves a hundred times faster),
and what the plan timed by a *margin* that grows each time the silence after a probe ends
with the very ``ok`` that was suspected lost (the probe was needless). What the plan cannot
time has bounds of its own, not stretched: a heat wait holds while its reports say so (the
residency their ``W:`` counts down, or until its heaters got there), a command that holds
the queue a few seconds, or as long as its busy lines keep coming.
"""

from __future__ import annotations

import math
from collections import deque

from repetrel_host.gcode.commands import UNBUFFERED, command_word, command_words
from repetrel_host.gcode.estimate import DEFAULT_LIMITS, Estimator, Limits

KEPT = 512  # lines kept for the estimate: the newest of them are what explains a silence
# Lines the estimate starts again from, when more were sent since it last ran (a fast
# stretch): fed at once when a silence comes, a few milliseconds of CPU at most.
RESTART_LINES = 256
PACE_LINES = 128  # acknowledged lines the pace and the planner's content are read over
# The most planner blocks a firmware holds (Marlin: 16 on an AVR, up to 64 on 32-bit
# boards): moves answered as they enter it, not yet run.
PLANNER_BLOCKS = 64
PACE_PLANNED = 1.0  # planned seconds of moves run before the pace is read from them
# A controller taken as at most this much slower than the plan, and as that slow until its
# answers tell its pace.
MAX_PACE = 2.0
MARGIN = 1.5  # the explanation's time is stretched this much, at first
MAX_MARGIN = 4.0
MARGIN_STEP = 1.25  # a needless probe's silence, stretched this much, is the new margin
LEARNED_FROM = 0.05  # explanations shorter than this teach no margin (nothing explained)
# A command that waits without saying how long (G28, G29, M600...): after the moves before
# it, this long before it is suspected; its busy lines explain more.
UNBUFFERED_GRACE = 5.0
BUSY_INTERVAL = 2.0  # Marlin's "busy: processing" interval (M113), until two tell it
MAX_BUSY_INTERVAL = 60.0  # M113's longest
BUSY_GAPS = 2.0  # a busy line explains this many intervals of silence
# A heat wait holds HEAT_SETTLE at least (Marlin's residency, 10 s by default, restarted
# when the heater leaves its window), and longer while reports keep coming (a heat wait's
# every second, or M155's every few: one within REPORT_GAP) that show a heater it waits for
# off its target by more than HEAT_WINDOW (Marlin's hysteresis), or not back for long.
REPORT_GAP = 5.0
HEAT_WINDOW = 3.0
HEAT_SETTLE = 30.0
# The heaters each heat wait waits for, by the first letter of their report's name.
_WAITS_FOR = {"M109": "T", "M190": "B", "M191": "C", "M116": "TBC"}
_MOVES = frozenset({"G0", "G1", "G2", "G3", "G5"})
# Lines that change how the estimate reads the moves after them, kept (the last of each
# word's group) for a restart: modes, units, limits, factors.
_MODE_GROUPS = {
    "G90": "G90", "G91": "G90", "M82": "M82", "M83": "M82", "G20": "G20", "G21": "G20",
    "M201": "M201", "M203": "M203", "M204": "M204", "M205": "M205", "M220": "M220",
    "M221": "M221",
}  # fmt: skip
_MODE_PREFIXES = ("G9", "G2", "M8", "M2")  # a cheap test before the word is read


class _Kind:
    """What a line is to a silence (small ints: one is kept per line)."""

    MOVE = 0
    ARC = 1  # many planner blocks: its ok comes once most of it ran
    DWELL = 2  # G4
    DRAIN = 3  # M400: the moves before it
    HEAT = 4  # M109, M190, M191, M116
    HOLD = 5  # any other command that waits (G28, G29, M0, M600...)
    OTHER = 6  # answered at once

    @staticmethod
    def of(command: str) -> int:
        word = command_word(command)
        if word in _MOVES:
            return _Kind.ARC if word in ("G2", "G3") else _Kind.MOVE
        if word not in UNBUFFERED:
            return _Kind.OTHER
        if word == "G4":
            return _Kind.DWELL
        if word == "M400":
            return _Kind.DRAIN
        return _Kind.HEAT if word in _WAITS_FOR else _Kind.HOLD


_WAITS = frozenset({_Kind.DWELL, _Kind.DRAIN, _Kind.HEAT, _Kind.HOLD})
_PLANNED = frozenset({_Kind.MOVE, _Kind.ARC, _Kind.DWELL, _Kind.DRAIN})  # timed by the plan


class Silence:
    """What the controller was given and what it said: what explains a silence.

    The dialect tells it each of the caller's lines as it first goes on the wire
    (:meth:`sent`), each as it is first acknowledged (:meth:`acknowledged`, in the same
    order), and the busy lines and temperature reports it reads. ``limits``: the
    machine's, before the file's own M201-M205 (None: Marlin's defaults)."""

    def __init__(self, limits: Limits | None = None) -> None:
        self.limits = limits or DEFAULT_LIMITS
        self.margin = MARGIN
        self._commands: deque[str] = deque(maxlen=KEPT)  # sent, the newest last
        self._acked_at: deque[float] = deque(maxlen=KEPT)  # when each was acknowledged
        self._sent = 0  # lines sent: the next one's index
        self._acked = 0  # lines acknowledged: the index of the oldest one not
        self._modes: dict[str, tuple[int, str]] = {}  # group: (index, command), the last
        self._estimator: Estimator | None = None
        self._fed = 0  # lines fed to the estimate
        self._kinds: deque[int] = deque()  # of the lines fed, from index _base
        self._seconds: deque[float] = deque()  # their planned seconds
        self._base = 0
        self._told = 0.0  # the estimate's running total at its last word
        # A probe's: (the line awaited, the silence's start, its explanation's end)
        self._suspected: tuple[int, float, float] | None = None
        self._busy_at: float | None = None  # the last busy line since the last ok
        self._busy_interval = BUSY_INTERVAL
        self._report_at: float | None = None
        self._residency: tuple[float, float] | None = None  # a heat wait report's W:, when
        self._off_target: dict[str, float] = {}  # heater: when last seen off its target

    # --- what happened --------------------------------------------------------------

    def sent(self, command: str) -> None:
        """A line of the caller's went on the wire for the first time."""
        self._commands.append(command)
        if command.startswith(_MODE_PREFIXES):
            group = _MODE_GROUPS.get(command_word(command))
            if group is not None:
                self._modes[group] = (self._sent, command)
        self._sent += 1

    def acknowledged(self, now: float, counted: bool = True) -> None:
        """The oldest line not yet acknowledged was, at ``now``: by its own ok
        (``counted``), or by the controller's numbers (a probe's answer)."""
        if self._acked == self._sent:
            return
        suspected = self._suspected
        if suspected is not None and suspected[0] == self._acked:
            self._suspected = None
            if counted:  # its own ok came after all: the probe was needless
                self._learn(now - suspected[1], suspected[2] - suspected[1])
        self._acked_at.append(now)
        self._acked += 1
        self._busy_at = None

    def busy(self, now: float) -> None:
        """A ``busy:`` line: a command holds the queue. Two in a row tell the interval."""
        if self._busy_at is not None:
            self._busy_interval = min(max(now - self._busy_at, 0.1), MAX_BUSY_INTERVAL)
        self._busy_at = now

    def temperatures(
        self,
        readings: dict[str, tuple[float, float | None]],
        now: float,
        residency: float | None = None,
    ) -> None:
        """A temperature report (an auto-report, a heat wait's, an M105's answer);
        ``residency``: the seconds a heat wait's report says it still holds (its ``W:``;
        inf for ``W:?``), None when it says none."""
        self._report_at = now
        if residency is not None:
            self._residency = (now, residency)
        off = self._off_target
        for name, (current, target) in readings.items():
            if target and abs(current - target) > HEAT_WINDOW:
                off[name] = now
            elif not target:
                off.pop(name, None)

    def suspected(self, since: float, until: float) -> None:
        """A probe went: the silence since ``since`` outlasted its explanation ``until``
        (:meth:`explained_until`). Should the line awaited get its own ok after all, the
        margin grows; only where the plan timed the wait (a heat-up or a homing teaches
        nothing of the motion)."""
        index = self._acked
        if self._base <= index < self._fed and self._kinds[index - self._base] in _PLANNED:
            self._suspected = (index, since, (until - since) / self.margin + since)

    # --- the explanation -----------------------------------------------------------------

    def explained_until(self, since: float, now: float) -> float:
        """Until when a silence since ``since`` (the last answer) is explained by what the
        controller was given and said, the margin included; ``since`` when nothing
        explains it."""
        until = since
        if self._acked < self._sent:
            planned, more = self._awaited(since, now)
            until = since + self.margin * (planned - since) + more
        if self._busy_at is not None:
            until = max(until, self._busy_at + BUSY_GAPS * self._busy_interval)
        return until

    def _awaited(self, since: float, now: float) -> tuple[float, float]:
        """When the oldest line not acknowledged is due, at the latest: the time the plan
        gives (the margin stretches it) and the seconds a wait the plan cannot time holds
        after that, at most (a bound of its own)."""
        self._catch_up()
        index = self._acked
        if index < self._base:  # more in flight than the estimate keeps
            return since, 0.0
        kind = self._kinds[index - self._base]
        pace, drain, next_end = self._motion(since)
        if kind == _Kind.MOVE:
            return next_end, 0.0  # once the block in hand ends, there is room for it
        if kind == _Kind.ARC:  # its pieces go in as the planner's blocks end
            return next_end + pace * self._seconds[index - self._base], 0.0
        if kind == _Kind.OTHER:
            return since, 0.0
        start = max(drain, since)
        if kind == _Kind.DWELL:  # a dwell's time is the clock's, whatever the pace
            return start + self._seconds[index - self._base], 0.0
        if kind == _Kind.DRAIN:
            return start, 0.0
        if kind == _Kind.HOLD:
            return start, UNBUFFERED_GRACE
        until = start + HEAT_SETTLE
        command = self._commands[index - self._first_kept()]
        heard, residency = self._report_at, self._residency
        if heard is not None and heard >= since:
            # Reports since the silence began (Marlin's heat wait reports at once, then each
            # second) tell how long it holds: the residency its W: says, or, no W: said and
            # its heaters there, nothing more once they got there.
            told = residency is not None and residency[0] >= since
            reached = self._reached(command)
            if told and residency is not None and residency[1] != math.inf:
                until = residency[0] + residency[1] + REPORT_GAP
            elif not told and reached is not None:
                until = max(since, reached) + REPORT_GAP
        if self._heating(command, now):
            assert heard is not None
            until = max(until, heard + REPORT_GAP)
        return start, max(0.0, until - start)

    def _reached(self, command: str) -> float | None:
        """When the heaters ``command`` (a heat wait) waits for were last seen off their
        targets (-inf: never); None while the latest report shows one off."""
        letters = _WAITS_FOR[command_word(command)]
        last = -math.inf
        for name, seen in self._off_target.items():
            if name[0] in letters:
                if seen == self._report_at:
                    return None
                last = max(last, seen)
        return last

    def _heating(self, command: str, now: float) -> bool:
        """A recent report shows a heater that ``command`` (a heat wait) waits for still off
        its target, or not there for long."""
        if self._report_at is None or now - self._report_at > REPORT_GAP:
            return False
        letters = _WAITS_FOR[command_word(command)]
        return any(
            name[0] in letters and now - seen < HEAT_SETTLE
            for name, seen in self._off_target.items()
        )

    def _motion(self, since: float) -> tuple[float, float, float]:
        """The pace, when the acknowledged moves end (the planner drained), and when the
        first of them to end after ``since`` ends (the block in hand then)."""
        acked_at = self._acked_at
        first = max(self._acked - len(acked_at), self._acked - PACE_LINES, self._base)
        kinds, seconds, base = self._kinds, self._seconds, self._base
        start_at = self._acked - len(acked_at)
        # The moves answered in the window ran in its time, all but the newest, which a
        # planner may still hold (PLANNER_BLOCKS at most): their plan against that time is
        # a pace the controller keeps at most (a starved controller's is slower still).
        elapsed = planned = 0.0
        moves = 0
        for index in range(self._acked - 1, first, -1):
            kind = kinds[index - base]
            if kind <= _Kind.ARC:
                moves += 1
                if moves > PLANNER_BLOCKS:
                    planned += seconds[index - base]
                if kinds[index - 1 - base] not in _WAITS:
                    elapsed += acked_at[index - start_at] - acked_at[index - 1 - start_at]
        pace = min(elapsed / planned, MAX_PACE) if planned >= PACE_PLANNED else MAX_PACE
        end = -math.inf
        next_end = since
        for index in range(first, self._acked):
            kind = kinds[index - base]
            at = acked_at[index - start_at]
            if kind <= _Kind.ARC:
                end = max(end, at) + pace * seconds[index - base]
                if next_end == since and end > since:
                    next_end = end
            elif kind == _Kind.HEAT:
                end = max(end, at)  # Marlin's heat waits let the moves before them run on
            elif kind in _WAITS:
                end = at  # answered once the moves before it ran
        return pace, end, next_end

    def _learn(self, lasted: float, explained: float) -> None:
        if explained >= LEARNED_FROM:
            needed = MARGIN_STEP * lasted / explained
            self.margin = min(MAX_MARGIN, max(self.margin, needed))

    # --- the estimate, fed lazily ----------------------------------------------------

    def _first_kept(self) -> int:
        return self._sent - len(self._commands)

    def _catch_up(self) -> None:
        """Feed the estimate every line sent since it last ran; each gets its time."""
        if self._fed == self._sent:
            return
        if self._estimator is None or self._sent - self._fed > RESTART_LINES:
            start = min(self._acked - PACE_LINES, self._sent - RESTART_LINES)
            self._restart(max(self._first_kept(), start))
        estimator = self._estimator
        assert estimator is not None
        commands, first_kept = self._commands, self._first_kept()
        for index in range(self._fed, self._sent):
            command = commands[index - first_kept]
            self._kinds.append(_Kind.of(command))
            self._seconds.append(0.0)
            estimator.feed(index, command)
        self._fed = self._sent
        estimator.flush()  # the newest moves end as if nothing followed: an upper bound
        while len(self._kinds) > KEPT:
            self._kinds.popleft()
            self._seconds.popleft()
            self._base += 1

    def _tell(self, index: int, seconds: float) -> None:
        """The estimate's word: the running total at the end of line ``index``."""
        spent = seconds - self._told
        self._told = seconds
        if index >= self._base:
            self._seconds[index - self._base] += spent

    def _restart(self, start: int) -> None:
        """A new estimate from line ``start``: the modes, units and limits last set before
        it, and the position and feed rate the lines before it left (those not known: the
        first the lines after it name, so that no move is made up)."""
        estimator = Estimator(self.limits, on_time=self._tell, lookahead=16)
        for index, command in sorted(self._modes.values()):
            if index < start:
                estimator.feed(-1, command)
        if start > 0:  # else from where the estimate starts, as the connection did
            for command in self._position_before(start):
                estimator.feed(-1, command)
        self._estimator = estimator
        self._told = 0.0
        self._fed = self._base = start
        self._kinds.clear()
        self._seconds.clear()

    def _position_before(self, start: int) -> list[str]:
        """``G92 X.. Y.. Z.. E..`` and ``G1 F..``: where the kept lines before ``start`` left
        each axis and the feed rate, else the first value after it."""
        commands, first_kept = self._commands, self._first_kept()
        found: dict[str, float] = {}
        before = range(start - 1, first_kept - 1, -1)
        after = range(start, self._sent)
        for indices in (before, after):
            for index in indices:
                command = commands[index - first_kept]
                if command_word(command) not in _MOVES and not command.startswith("G92"):
                    continue
                for axis, value in command_words(command).items():
                    if axis in "XYZEF":
                        found.setdefault(axis, value)
                if len(found) == 5:
                    break
        position = " ".join(f"{axis}{found[axis]:g}" for axis in "XYZE" if axis in found)
        lines = [f"G92 {position}"] if position else []
        return lines + ([f"G1 F{found['F']:g}"] if "F" in found else [])
