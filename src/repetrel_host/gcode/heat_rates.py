"""How fast a printer's heaters climb, learned as its jobs run, so that its next job's heat
waits are planned at its own rates rather than its machine profile's.

A climb is timed from the first report that shows a heater set :data:`CLIMB` degrees or
more above where it is, to the first that shows it within a degree of that target (or the
last before the job ended, once it rose :data:`CLIMB` degrees): the degrees it rose over the
seconds it took (the straight line the plan draws; reports come a second or two apart, so a
heater that reaches its target at once reads as that fast). A job keeps each kind of
heater's largest climb (its heat-up, not a later step of a few degrees); a printer's rates
are the median of its last jobs' (as its pace is). The clock is the caller's.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Mapping

CLIMB = 10.0  # degrees: a smaller step is mostly the heater's settling, not its rate
REACHED = 1.0  # degrees below the target that count as there (Marlin's M109 window)
RATE_JOBS = 5  # a printer's rates: the median of its last jobs' (as its pace)
_KINDS = {"B": "bed", "C": "chamber"}  # by the report's name; the rest are hotends


def kind_of(heater: str) -> str:
    """The kind of heater a report's name is (``T0``, ``B``, ``C``...), as the plan's limits
    name their rates: ``hotend``, ``bed``, ``chamber``."""
    return _KINDS.get(heater[:1], "hotend")


class HeatClimbs:
    """The climbs of a printer's heaters, timed from its reports (see the module)."""

    def __init__(self) -> None:
        self.rates: dict[str, float] = {}  # degrees a second, by kind: the largest climb's
        self._degrees: dict[str, float] = {}  # by kind: how far that climb rose
        self._climbing: dict[str, tuple[float, float, float]] = {}  # since, from, target

    def observe(self, heaters: Mapping[str, tuple[float, float | None]], now: float) -> None:
        """The heaters' latest reports (``{"T0": (current, target)}``) at ``now``."""
        for name, (current, target) in heaters.items():
            climb = self._climbing.get(name)
            if climb is not None and target != climb[2]:
                del self._climbing[name]  # set elsewhere: that climb is not timed
                climb = None
            if climb is None:
                if target is not None and target - current >= CLIMB:
                    self._climbing[name] = (now, current, target)
                continue
            since, start, goal = climb
            kind, rose = kind_of(name), current - start
            # So far (a job may end before), unless a larger climb of its kind said more (a
            # heat-up, not a later step of a few degrees).
            if rose >= max(CLIMB, self._degrees.get(kind, 0.0)) and now > since:
                self.rates[kind], self._degrees[kind] = rose / (now - since), rose
            if current >= goal - REACHED:
                del self._climbing[name]


def learned_heat_rates(jobs: Iterable[Mapping[str, float] | None]) -> dict[str, float]:
    """A printer's heat rates from its past jobs' (newest first): by kind, the median of the
    last :data:`RATE_JOBS` that timed one; a kind none timed is left to the machine's."""
    found: dict[str, list[float]] = {}
    for rates in jobs:
        for kind, rate in (rates or {}).items():
            kept = found.setdefault(kind, [])
            if len(kept) < RATE_JOBS and rate > 0:
                kept.append(rate)
    return {kind: statistics.median(rates) for kind, rates in found.items()}
