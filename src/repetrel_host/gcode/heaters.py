"""Which heaters a session's commands turned on, and a safe stop that turns every one off.

A safe stop's ``M104 S0`` turns off only the active hotend on Marlin: a job that heated T0
and T1 and stopped while T1 was active would leave T0 hot. :class:`HeaterLog` follows the
commands sent (a job's and the console's): each temperature command's heater by its kind
and T word (a hotend without one is the active tool's), the tool changes, and the fans.
:func:`complete_safe_stop` is the one place a safe stop is made whole, for every path that
sends one (a stop, a link lost and found, a restart): it names every hotend in place of a
bare ``M104 S0``, turns off a bed, a chamber and each numbered fan that was turned on.
:func:`safe_stop_commands` is the safe stop of Hyrel's reference footer (a profile's own,
unless it names one), :func:`turns_off` tells the lines that may run in any order. Pure: no
I/O.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from repetrel_host.gcode import addressing
from repetrel_host.gcode.commands import command_word

# What each temperature command sets, and whether it waits for it.
HEATING = {
    "M104": ("hotend", False), "M109": ("hotend", True),
    "M140": ("bed", False), "M190": ("bed", True),
    "M141": ("chamber", False), "M191": ("chamber", True),
}  # fmt: skip
WAITS = frozenset(word for word, (_, waits) in HEATING.items() if waits)
# Hyrel's group addresses (v5: all devices, yoke 1, every head, every bed; v4: every head,
# every bed): a confirmed 0 for one turns off every heater of its kind.
_GROUPS: dict[str, frozenset[int]] = {
    "hotend": frozenset({40, 41, 47, 100}),
    "bed": frozenset({40, 46, 90}),
    "chamber": frozenset({40, 46}),
}
# Lines that only turn something off: fans, a CO2 laser (M620 E0), a spindle (M5), and
# heaters set to 0.
_OFF_WORDS = frozenset({"M107", "M5", "M620"})
_WORD = re.compile(r"([A-Z])\s*(-?\d+(?:\.\d*)?)", re.IGNORECASE)


@dataclass(frozen=True, slots=True)
class TargetSet:
    """What a temperature command sets: its heater's kind, its T word (None: it names
    none) and the target."""

    kind: str  # hotend, bed, chamber
    index: int | None
    target: float


def target_set(command: str) -> TargetSet | None:
    """What ``command`` sets (M104/M109 a hotend, M140/M190 the bed, M141/M191 the
    chamber; the target is S, or Marlin's M109 R, which waits for cooling too); None for
    any other command, and for a wait for the target set before (Hyrel's M109 T# without
    S)."""
    word = command_word(command)
    heating = HEATING.get(word)
    if heating is None:
        return None
    words = {letter.upper(): value for letter, value in _WORD.findall(command[len(word) :])}
    target = words.get("S", words.get("R"))
    if target is None:
        return None
    index = int(float(words["T"])) if "T" in words else None
    return TargetSet(heating[0], index, float(target))


def is_group(kind: str, index: int | None) -> bool:
    """``index`` is one of Hyrel's group addresses of heaters of ``kind`` (every head, every
    bed...)."""
    return index in _GROUPS[kind]


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
        self.fans: set[int] = set()  # fans turned on by an M106 P<n> (n > 0)
        # Called whenever the heaters that may be on change (a server keeps them, so that
        # a safe stop after its restart still turns every one off).
        self.on_change: Callable[[], None] | None = None

    def restore(self, heaters: Iterable[Heater]) -> None:
        """Take ``heaters`` as set (kept from before a restart): each may be on."""
        for heater in heaters:
            self.heaters[(heater.kind, heater.index)] = heater

    def note(self, command: str, confirmed: bool = False) -> None:
        """A command sent (``confirmed``: the controller confirmed it). A heater counts as
        on as soon as a command that heats it is sent, and as off only once the
        controller confirmed the command that turned it off: while it may not have run,
        the heater may be on."""
        word = command_word(command)
        if word[:1] == "T" and word[1:].isdigit():
            self.tool = int(word[1:])
            return
        if word == "M106":
            fan = _word_value(command, "P")
            if fan is not None and int(fan) > 0:
                self.fans.add(int(fan))
            return
        found = target_set(command)
        if found is None:
            return
        kind, index, target = found.kind, found.index, found.target
        on_before = self._on_keys()
        if index is None and kind == "hotend":
            index = self.tool
        if is_group(kind, index) and target == 0 and confirmed:
            for key, heater in list(self.heaters.items()):
                if heater.kind == kind and heater.target > 0:
                    self.heaters[key] = Heater(kind, heater.index, 0.0, command)
        key = (kind, index)
        previous = self.heaters.get(key)
        if not confirmed and previous is not None and target < previous.target:
            return
        self.heaters[key] = Heater(kind, index, target, command)
        if self.on_change is not None and self._on_keys() != on_before:
            self.on_change()

    def _on_keys(self) -> set[tuple[str, int | None]]:
        return {key for key, heater in self.heaters.items() if heater.target > 0}

    def hotends(self) -> list[int]:
        """The hotends (by index) any command set, off or on."""
        return sorted({i for kind, i in self.heaters if kind == "hotend" and i is not None})

    def on(self) -> list[Heater]:
        """The heaters whose last target was above zero: hot, or heating."""
        return [heater for heater in self.heaters.values() if heater.target > 0]


def complete_safe_stop(commands: list[str], log: HeaterLog, hotends: int = 1) -> list[str]:
    """``commands`` made whole for what the log saw turned on: a bare ``M104 S0`` (the
    active hotend's, on Marlin) becomes one ``M104 T<i> S0`` for every hotend the log saw
    set and every one of the controller's ``hotends``, where there are several; a bare
    ``M107`` is followed by ``M107 P<n>`` for each numbered fan turned on; a bed and a
    chamber that were heated are turned off (unless the sequence does already)."""
    indices = sorted({*log.hotends(), *range(hotends)})
    done: list[str] = []
    for command in commands:
        if _is_bare_hotend_off(command) and indices != [0]:
            done.extend(f"M104 T{index} S0" for index in indices)
        else:
            done.append(command)
        if command_word(command) == "M107" and not {"T", "P"} & _letters(command):
            done.extend(f"M107 P{fan}" for fan in sorted(log.fans))
    words = {command_word(c) for c in commands}
    on = [h for h in log.heaters.values() if h.target > 0]
    offs: list[str] = []
    if any(h.kind == "hotend" for h in on) and not words & {"M104", "M109"}:
        offs += [f"M104 T{index} S0" for index in indices] if indices != [0] else ["M104 S0"]
    if any(h.kind == "bed" for h in on) and not words & {"M140", "M190"}:
        offs.append("M140 S0")
    if not words & {"M141", "M191"}:
        chambers = [h for h in on if h.kind == "chamber"]
        offs += [f"M141 T{h.index} S0" if h.index is not None else "M141 S0" for h in chambers]
    if offs:  # after the last heater line, before any move: heat off first
        heating = [i for i, c in enumerate(done) if command_word(c) in HEATING]
        at = heating[-1] + 1 if heating else _first_move(done)
        done[at:at] = offs
    return done


def safe_stop_commands(firmware: addressing.Firmware) -> list[str]:
    """The safe part of the reference's standard footer, with this firmware's group addresses:
    fans, lasers, heaters and spindles off, lift, motors off."""
    heads = addressing.all_heads_variable(firmware)
    beds = addressing.all_beds_variable(firmware)
    return [
        f"M107 T{heads}",  # fans, diodes: off
        f"M620 T{heads} E0",  # CO2 lasers: off
        f"M104 T{heads} S0",  # head temperatures: off
        f"M140 T{beds} S0",  # bed temperatures: off
        "M5",  # spindles: off
        "G91",  # relative coordinates
        "G0 Z10",  # drop the bed (lift the head) 10 mm
        "G90",  # absolute coordinates
        "M84",  # motors: off
    ]


def safe_stop_for_either() -> list[str]:
    """A safe stop for a controller whose firmware is not known: Hyrel's (v5 group
    addresses) with Marlin's heater lines beside its own. Each firmware takes the other's
    lines harmlessly: Marlin refuses ``M104 T47`` (no such hotend) and ignores the unknown
    ``M620`` and ``M5``; Hyrel's ``M104 S0`` and ``M140 S0`` turn off the current head and
    the primary bed. (A bare ``M104 S0`` names every hotend once Marlin says how many.)"""
    hyrel = safe_stop_commands("v5")
    either: list[str] = []
    for command in hyrel:
        either.append(command)
        if command.startswith(("M104 ", "M140 ")):
            either.append(command.split()[0] + " S0")
    return either


def turns_off(command: str) -> bool:
    """Whether ``command`` only turns something off (a fan, a laser, a spindle, a heater
    to 0): such lines may run in any order (Hyrel's urgent lines promise none)."""
    word = command_word(command)
    if word == "M620":
        return _word_value(command, "E") == 0
    if word in _OFF_WORDS:
        return True
    return word in HEATING and _word_value(command, "S") == 0


def off_lines(commands: list[str]) -> list[str]:
    """The lines of a safe stop that only turn something off (heaters, fans, a laser): what
    is owed after an emergency stop, whose controller may not have turned them off (no move:
    the machine may have lost its position)."""
    return [command for command in commands if turns_off(command)]


def _first_move(commands: list[str]) -> int:
    """Where the first move or mode change is (G91, G0...), else the end."""
    return next((i for i, c in enumerate(commands) if c[:1] in "Gg"), len(commands))


def _letters(command: str) -> set[str]:
    return {found.upper() for found, _ in _WORD.findall(command[len(command_word(command)) :])}


def _word_value(command: str, letter: str) -> float | None:
    for found, value in _WORD.findall(command[len(command_word(command)) :]):
        if found.upper() == letter:
            return float(value)
    return None


def _is_bare_hotend_off(command: str) -> bool:
    return (
        command_word(command) == "M104"
        and _word_value(command, "T") is None
        and _word_value(command, "S") == 0
    )
