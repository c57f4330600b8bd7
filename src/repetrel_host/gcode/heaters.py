"""Which heaters a session's commands turned on, and a safe stop that turns every one off.

A safe stop's ``M104 S0`` turns off only the active hotend on Marlin: a job that heated T0
and T1 and stopped while T1 was active would leave T0 hot. :class:`HeaterLog` follows the
commands sent (a job's and the console's): each temperature command's heater by its kind
and T word (a hotend without one is the active tool's), and the tool changes.
:func:`complete_safe_stop` then names every hotend in place of a bare ``M104 S0``, and
adds the chamber when one was heated. Pure: no I/O.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from repetrel_host.gcode.commands import command_word

# What each temperature command sets, and whether it waits for it.
HEATING = {
    "M104": ("hotend", False), "M109": ("hotend", True),
    "M140": ("bed", False), "M190": ("bed", True),
    "M141": ("chamber", False), "M191": ("chamber", True),
}  # fmt: skip
WAITS = frozenset(word for word, (_, waits) in HEATING.items() if waits)
_WORD = re.compile(r"([A-Z])\s*(-?\d+(?:\.\d*)?)", re.IGNORECASE)


@dataclass(frozen=True, slots=True)
class Heater:
    """A heater a command set: its kind, its T word (None: the default bed or chamber),
    the target it was set to last, and that command."""

    kind: str  # hotend, bed, chamber
    index: int | None
    target: float
    command: str

    def describe(self) -> str:
        """``hotend T1 at 210 °C (M104 T1 S210)``."""
        name = self.kind if self.index is None else f"{self.kind} T{self.index}"
        return f"{name} at {self.target:g} °C ({self.command})"


class HeaterLog:
    """The heaters set by the commands fed to :meth:`note`, in the order they were sent."""

    def __init__(self) -> None:
        self.tool = 0
        self.heaters: dict[tuple[str, int | None], Heater] = {}

    def note(self, command: str, confirmed: bool = False) -> None:
        """A command sent (``confirmed``: the controller confirmed it). A heater counts as
        on as soon as a command that heats it is sent, and as off only once the
        controller confirmed the command that turned it off: while it may not have run,
        the heater may be on."""
        word = command_word(command)
        if word[:1] == "T" and word[1:].isdigit():
            self.tool = int(word[1:])
            return
        heating = HEATING.get(word)
        if heating is None:
            return
        kind = heating[0]
        words = {letter.upper(): value for letter, value in _WORD.findall(command[len(word) :])}
        target = words.get("S", words.get("R"))  # Marlin's M109 R waits for cooling too
        if target is None:
            return  # a wait for the target set before (Hyrel's M109 T# without S)
        index = int(float(words["T"])) if "T" in words else None
        if index is None and kind == "hotend":
            index = self.tool
        key = (kind, index)
        previous = self.heaters.get(key)
        if not confirmed and previous is not None and float(target) < previous.target:
            return
        self.heaters[key] = Heater(kind, index, float(target), command)

    def hotends(self) -> list[int]:
        """The hotends (by index) any command set, off or on."""
        return sorted({i for kind, i in self.heaters if kind == "hotend" and i is not None})

    def on(self) -> list[Heater]:
        """The heaters whose last target was above zero: hot, or heating."""
        return [heater for heater in self.heaters.values() if heater.target > 0]


def complete_safe_stop(commands: list[str], log: HeaterLog, hotends: int = 1) -> list[str]:
    """``commands`` with a bare ``M104 S0`` (the active hotend's, on Marlin) in place of
    one ``M104 T<i> S0`` for every hotend the log saw set and every one of the
    controller's ``hotends``, where there are several; and a chamber that was heated
    turned off after the bed (unless the sequence does already)."""
    indices = sorted({*log.hotends(), *range(hotends)})
    done: list[str] = []
    for command in commands:
        if _is_bare_hotend_off(command) and indices != [0]:
            done.extend(f"M104 T{index} S0" for index in indices)
        else:
            done.append(command)
    chambers = [h for h in log.heaters.values() if h.kind == "chamber" and h.target > 0]
    if chambers and not any(command_word(c) in ("M141", "M191") for c in commands):
        offs = [f"M141 T{h.index} S0" if h.index is not None else "M141 S0" for h in chambers]
        beds = [i for i, c in enumerate(done) if command_word(c) == "M140"]
        at = beds[-1] + 1 if beds else len(done)
        done[at:at] = offs
    return done


def _is_bare_hotend_off(command: str) -> bool:
    words = {letter.upper(): value for letter, value in _WORD.findall(command)}
    return command_word(command) == "M104" and "T" not in words and float(words.get("S", -1)) == 0
