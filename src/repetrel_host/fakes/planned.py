"""Each move's planned time, for a fake controller whose moves take it (``time_scale``).

The fake feeds every command it queues to an :class:`~repetrel_host.gcode.estimate.Estimator`,
the firmware's planner as the estimate models it. The estimator tells the time at the end
of each move once its lookahead has settled it; :class:`PlannedTimes` turns those running
totals into each move's own time, for the fake to run it in (scaled). What the estimator
does with each command is its own: a command it does not time gets none here.
"""

from __future__ import annotations

from repetrel_host.gcode.estimate import Estimator, Limits


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
