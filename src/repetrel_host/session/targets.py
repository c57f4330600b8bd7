"""A heater's target as the controller took it: the readings the session keeps, with the
target a temperature command set, once the controller acknowledged that command.

A controller tells its targets only in its next temperature report (a second or more
later); a caller that sets one and reads it back at once (Klipper has set it by the time
its call returns) would read the old one. Marlin answers ``ok`` once it ran the command
(``GCodeQueue::advance``: ``process_next_command``, then ``ok_to_send``), so its ok is the
moment the target is the controller's. Pure: no I/O.
"""

from __future__ import annotations

import re

from repetrel_host.gcode import addressing
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heaters import HEATING

Readings = dict[str, tuple[float, float | None]]

_WORD = re.compile(r"([A-Z])\s*(-?\d+(?:\.\d*)?)", re.IGNORECASE)
_HOTEND = re.compile(r"T\d*")
# Hyrel's group addresses that name every head (v5: all devices, yoke 1, every head that
# is not a bed; v4: every head).
_ALL_HEADS = {"v5": frozenset({40, 41, 47}), "v4": frozenset({100})}


def with_target(
    readings: Readings, command: str, tool: int, hyrel: addressing.Firmware | None = None
) -> Readings | None:
    """``readings`` with the target ``command`` sets (M104/M109 a hotend, M140/M190 the
    bed, M141/M191 the chamber), or None when it sets none of the sensors read.

    ``tool`` is the active one (a hotend command without T sets it); ``hyrel`` the Hyrel
    firmware whose T addressing the T word follows (None: a RepRap controller's, where T
    is the tool's number). A hotend is read as ``T<n>`` and, where it is the active one
    (or the only one), as ``T``; only sensors already read are set, so that a reading
    never shows a target without its temperature."""
    word = command_word(command)
    heating = HEATING.get(word)
    if heating is None or not readings:
        return None
    words = {letter.upper(): value for letter, value in _WORD.findall(command[len(word) :])}
    given = words.get("S", words.get("R"))  # Marlin's M109 R waits for cooling too
    if given is None:
        return None  # a wait for the target set before (Hyrel's M109 T# without S)
    target = float(given)
    kind = heating[0]
    if kind == "bed":
        sensors = ["B"]
    elif kind == "chamber":
        sensors = ["C"]
    else:
        sensors = _hotends(readings, words.get("T"), tool, hyrel)
    found = {sensor: readings[sensor] for sensor in sensors if sensor in readings}
    if not found:
        return None
    changed = dict(readings)
    for sensor, (current, _) in found.items():
        changed[sensor] = (current, target)
    return changed


def _hotends(
    readings: Readings, address: str | None, tool: int, hyrel: addressing.Firmware | None
) -> list[str]:
    """The sensors of the hotend(s) a hotend command's T word names."""
    if address is None:
        index: int | None = tool
    else:
        value = int(float(address))
        if hyrel is not None and value in _ALL_HEADS[hyrel]:
            return [s for s in readings if _HOTEND.fullmatch(s)]  # a group: every head
        index = _tool_of(value, hyrel)
        if index is None:
            return []  # a device that is not a head (a spindle, a laser, a bed)
    numbered = any(s[1:] and _HOTEND.fullmatch(s) for s in readings)
    sensors = [f"T{index}"]
    # T is the active hotend's (Marlin), or the first's where no T0 is read (one hotend,
    # or a fake that reports the first as T).
    if index == tool or not numbered or (index == 0 and "T0" not in readings):
        sensors.append("T")
    return sensors


def _tool_of(value: int, hyrel: addressing.Firmware | None) -> int | None:
    """The tool number a T word names: itself on a RepRap controller; on Hyrel's, the head
    its address names (v4's yoke 1 is T11..T15)."""
    if hyrel is None:
        return value
    position = addressing.position_of_variable(hyrel, value)
    return None if position is None else addressing.tool_number(*position)
