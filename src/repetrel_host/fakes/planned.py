"""The fake controller's planner (:class:`MovePlanner`): the moves it holds and when each
finishes, a fixed time each, or each move's planned time for a fake whose moves take it
(``time_scale``).

The fake feeds every command it queues to an :class:`~repetrel_host.gcode.estimate.Estimator`,
the firmware's planner as the estimate models it. The estimator tells the time at the end
of each move once its lookahead has settled it; :class:`PlannedTimes` turns those running
totals into each move's own time, for the fake to run it in (scaled). What the estimator
does with each command is its own: a command it does not time gets none here.
"""

from __future__ import annotations

from collections import deque

from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.gcode.estimate import DEFAULT_LIMITS, Estimator, Limits


class MovePlanner:
    """The moves the fake's planner holds, each finishing after the one before it:
    ``move_time`` each, or (``time_scale``) its planned time divided by the scale, once the
    planned times know it (until then it waits, untimed)."""

    def __init__(self, settings: ControllerSettings, now: float, hyrel: bool) -> None:
        self._size = settings.planner
        self._move_time = settings.move_time
        self._scale = settings.time_scale
        self.finishes: deque[float] = deque()  # finish time of each planned move
        # With time_scale: planned moves waiting for their time (numbers in self._planned).
        self._untimed: deque[int] = deque()
        self._planned = (
            PlannedTimes(
                settings.limits or DEFAULT_LIMITS, planner_lookahead(settings), hyrel=hyrel
            )
            if self._scale is not None
            else None
        )
        self.end = now  # when the last move with its time finishes

    @property
    def full(self) -> bool:
        """No block is free for another move."""
        return len(self.finishes) + len(self._untimed) >= self._size

    @property
    def free(self) -> int:
        """Blocks free (ADVANCED_OK's P)."""
        return self._size - len(self.finishes) - len(self._untimed)

    @property
    def holds(self) -> bool:
        """Moves still to run, timed or not."""
        return bool(self.finishes or self._untimed)

    @property
    def untimed(self) -> bool:
        """Moves wait for their planned time."""
        return bool(self._untimed)

    def queued(self, command: str, move: bool, unbuffered: bool) -> int | None:
        """With time_scale: a command entering the queue goes to the planned times; its
        number there. Before a command that waits for the moves to finish (``unbuffered``),
        every move before it gets its time: the firmware stops there, whatever follows."""
        planned = self._planned
        if planned is None:
            return None
        number = planned.queued(command, move)
        if unbuffered:
            planned.settle()
        return number

    def add(self, planned: int | None, now: float) -> None:
        """A move leaves the queue for the planner (``planned``: its number in the planned
        times, None without time_scale)."""
        if planned is not None:
            self._untimed.append(planned)
            self.time_moves(now)
        else:
            start = max(now, self.end)
            self.end = start + self._move_time
            self.finishes.append(self.end)

    def time_moves(self, now: float) -> None:
        """The moves whose planned time is known run, in order, each after the one before
        (its time divided by time_scale)."""
        planned, scale = self._planned, self._scale
        if planned is None or scale is None:
            return
        while self._untimed and planned.known(self._untimed[0]):
            seconds = planned.take(self._untimed.popleft()) / scale
            self.end = max(now, self.end) + seconds
            self.finishes.append(self.end)

    def ran(self, now: float) -> None:
        """The moves finished by ``now`` leave the planner."""
        while self.finishes and self.finishes[0] <= now:
            self.finishes.popleft()

    def settle(self, now: float) -> bool:
        """The planner ran dry and nothing more came: the moves waiting run now, as a
        firmware runs what it has, planned without the moves still to come. True when
        there were any."""
        if self._untimed and self.end <= now and self._planned is not None:
            self._planned.settle()
            return True
        return False

    def drop(self) -> None:
        """The planner is emptied (a kill, a reset, an abort): its moves never run."""
        self.finishes.clear()
        self._untimed.clear()
        if self._planned is not None:
            self._planned.reset()


def planner_lookahead(settings: ControllerSettings) -> int:
    """The lookahead the planned times use: half the planner. The estimator settles its
    blocks in batches, keeping ``lookahead`` behind the newest once twice that many wait;
    this fake holds at most its planner and command slots, so with half the planner a move
    is settled (with between half and all the planner's blocks behind it, as the firmware
    looks ahead over what its planner holds) before the planner runs dry."""
    return max(1, settings.planner // 2)


class PlannedTimes:
    """The planned time of each queued move, known once the lookahead behind it settled.

    Commands are numbered as they are queued (:meth:`queued`); a move's time is
    :meth:`known` once the estimator has told a later command's time, or after
    :meth:`settle`. A command the estimator tells several times (an arc's segments)
    gets the sum, which is why a time counts as known only once a later one is told.
    """

    def __init__(self, limits: Limits, lookahead: int, hyrel: bool = False) -> None:
        self._limits = limits
        self._lookahead = lookahead
        self._hyrel = hyrel  # Hyrel's code chart (the estimator's ``hyrel``)
        self._queued = 0  # commands fed so far: the next one's number
        self._known_through = -1  # every command numbered up to this has its time
        self._told = 0.0  # the estimator's running total at its last word
        self._moves: dict[int, float] = {}  # planned seconds of each move not yet taken
        self._estimator = self._new_estimator()

    def queued(self, command: str, move: bool) -> int:
        """Feed one command (without comment, line number or checksum) as the fake queues
        it; its number. ``move``: the fake runs it as a move and will :meth:`take` its time."""
        number = self._queued
        self._queued += 1
        if move:
            self._moves[number] = 0.0
        self._estimator.feed(number, command)
        return number

    def known(self, number: int) -> bool:
        """True once the queued command ``number`` has its planned time."""
        return number <= self._known_through

    def take(self, number: int) -> float:
        """The planned seconds of move ``number`` (known), forgotten after."""
        return self._moves.pop(number, 0.0)

    def settle(self) -> None:
        """Every command queued so far gets its time now, as when no move follows for a
        while: the last one waiting ends at the speed it may stop from."""
        self._estimator.flush()
        self._known_through = self._queued - 1

    def reset(self) -> None:
        """Forget everything queued (the controller rebooted or dropped its queue)."""
        self._moves.clear()
        self._known_through = self._queued - 1
        self._told = 0.0
        self._estimator = self._new_estimator()

    def _new_estimator(self) -> Estimator:
        return Estimator(
            self._limits, on_time=self._tell, lookahead=self._lookahead, hyrel=self._hyrel
        )

    def _tell(self, number: int, seconds: float) -> None:
        """The estimator's word: the running total at the end of command ``number``.
        What it adds to the one before is that command's time (a dwell's and any other's
        too, which the fake times itself, so only moves keep theirs)."""
        spent = seconds - self._told
        self._told = seconds
        if number in self._moves:
            self._moves[number] += spent
        self._known_through = max(self._known_through, number - 1)
