"""The simulated controller's heaters: each one's temperature and target, moving toward
the target at the heat rate (degrees a second; None: at once), and the temperature report
as Marlin writes it. When a heat wait begins and ends, and which heater a command sets, is
the controller's (:mod:`.simulator`)."""

from __future__ import annotations

import re

AMBIENT = 21.0
# A command's S value: a heater's target (M104 S200), seconds (M155 S1)...
S_WORD = re.compile(r"\bS\s*(-?\d+(?:\.\d*)?)", re.IGNORECASE)


class SimulatedHeaters:
    """The hotends (the first ``T``, as a one-hotend Marlin reports it, the others ``T1``,
    ``T2``...), the bed ``B`` and, where there is one, the chamber ``C``."""

    def __init__(self, extruders: int, chamber: bool, rate: float | None, now: float) -> None:
        self._extruders = extruders
        self.rate = rate
        # Heater: [current, target, when current was last moved toward target].
        names = ["T", *(f"T{i}" for i in range(1, extruders)), "B"]
        self._heaters = {name: [AMBIENT, 0.0, now] for name in names}
        if chamber:
            self._heaters["C"] = [AMBIENT, 0.0, now]

    def __contains__(self, name: str) -> bool:
        return name in self._heaters

    def target(self, name: str) -> float:
        """The heater's target (0: off)."""
        return self._heaters[name][1]

    def turn_off(self, *names: str) -> None:
        """Those heaters' targets (else every one's) go to 0."""
        for name in names or self._heaters:
            self._heaters[name][1] = 0.0

    def heat(self, name: str, now: float) -> list[float]:
        """The heater's state at ``now``, moved toward its target since last asked."""
        heater = self._heaters[name]
        current, target, since = heater
        rate = self.rate
        goal = max(target, AMBIENT)
        if rate is None:
            current = goal
        else:
            step = rate * max(0.0, now - since)
            current = min(goal, current + step) if current < goal else max(goal, current - step)
        heater[0], heater[2] = current, now
        return heater

    def set_target(self, name: str, command: str, now: float) -> float:
        """Set a heater's target (``command``'s S); return how long until it is reached
        (for M109/M190)."""
        match = S_WORD.search(command)
        heater = self.heat(name, now)
        if match is not None:
            heater[1] = float(match.group(1))
        rate = self.rate
        if rate is None or heater[1] <= heater[0]:
            self.heat(name, now)
            return 0.0
        return (heater[1] - heater[0]) / rate

    def set_rate(self, rate: float | None, now: float) -> None:
        """From ``now`` on, they move at ``rate`` (up to ``now`` at the old one)."""
        for name in self._heaters:
            self.heat(name, now)
        self.rate = rate

    def readings(self, now: float) -> dict[str, tuple[float, float]]:
        """Each heater's (current, target) at ``now``."""
        return {name: (self.heat(name, now)[0], self._heaters[name][1]) for name in self._heaters}

    def report(self, now: float, tool: int, places: int) -> str:
        """As Marlin reports them: the active hotend (``tool``) as T, the bed, the chamber,
        then each hotend by its index where there are several; ``places`` decimals."""
        active = "T" if tool == 0 else f"T{tool}"
        hotend, bed = self.heat(active, now), self.heat("B", now)

        def reading(name: str, current: float, target: float) -> str:
            return f"{name}:{current:.{places}f} /{target:.{places}f}"

        text = f"{reading('T', *hotend[:2])} {reading('B', *bed[:2])}"
        if "C" in self._heaters:
            text += " " + reading("C", *self.heat("C", now)[:2])
        if self._extruders > 1:
            for index in range(self._extruders):
                current, target, _ = self.heat("T" if index == 0 else f"T{index}", now)
                text += " " + reading(f"T{index}", current, target)
        return text + " @:0 B@:0"
