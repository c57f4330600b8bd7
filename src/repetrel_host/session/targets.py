"""A heater's target as the controller took it: the readings the session keeps, with the
target a temperature command set, once the controller acknowledged that command; and the
heaters that may be on, from the commands and the readings (:func:`heaters_on`).

A controller tells its targets only in its next temperature report (a second or more
later); a caller that sets one and reads it back at once (Klipper has set it by the time
its call returns) would read the old one. Marlin answers ``ok`` once it ran the command
(``GCodeQueue::advance``: ``process_next_command``, then ``ok_to_send``), so its ok is the
moment the target is the controller's. Pure: no I/O.
"""

from __future__ import annotations

import re

from repetrel_host.gcode import addressing
from repetrel_host.gcode.heaters import HeaterLog, is_group, target_set

Readings = dict[str, tuple[float, float | None]]

_HOTEND = re.compile(r"T\d*")
_SENSORS = {"bed": ["B"], "chamber": ["C"]}


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
    found = target_set(command)
    if found is None or not readings:
        return None
    if found.kind == "hotend":
        sensors = _hotends(readings, found.index, tool, hyrel)
    else:
        sensors = _SENSORS[found.kind]
    read = [sensor for sensor in sensors if sensor in readings]
    if not read:
        return None
    changed = dict(readings)
    for sensor in read:
        changed[sensor] = (readings[sensor][0], found.target)
    return changed


def heaters_on(log: HeaterLog, readings: Readings) -> list[str]:
    """The heaters that may be on: set above zero by a command in ``log`` (and not turned
    off since, as far as the controller confirmed), or read with a target above zero."""
    named = {_heater_name(h.kind, h.index): h.describe() for h in log.on()}
    for sensor, (current, target) in readings.items():
        kind = {"T": "hotend", "B": "bed", "C": "chamber"}.get(sensor[:1])
        if not target or kind is None:
            continue
        index = int(sensor[1:]) if sensor[1:].isdigit() else None
        if kind == "hotend" and index is None:
            index = log.tool
        name = _heater_name(kind, index)
        named.setdefault(name, f"{name} (reported {current:g} °C, target {target:g} °C)")
    return list(named.values())


def _heater_name(kind: str, index: int | None) -> str:
    return kind if index is None else f"{kind} T{index}"


def _hotends(
    readings: Readings, address: int | None, tool: int, hyrel: addressing.Firmware | None
) -> list[str]:
    """The sensors of the hotend(s) a hotend command's T word names."""
    if address is None:
        index: int | None = tool
    else:
        if hyrel is not None and is_group("hotend", address):
            return [s for s in readings if _HOTEND.fullmatch(s)]  # a group: every head
        index = _tool_of(address, hyrel)
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
