"""The controller's motion state as the commands it ran left it: the axes homed, and the
speed and flow factors. A controller does not report them; Klipper's clients read them
(``toolhead.homed_axes`` enables their jog buttons, ``gcode_move``'s factors their
sliders), so the session keeps them from each command the controller acknowledged having
run, as it keeps a heater's target (:mod:`.targets`).

- ``G28``: the axes it names are homed; with none, Marlin homes X, Y and Z, while Hyrel's
  firmware homes only the axes named (its reference: "at least one axis listed").
- ``M84`` and ``M18`` turn motors off: the axes they name (all, with none) are no longer
  homed; with ``S`` alone Marlin only sets the idle timeout.
- ``M220 S`` and ``M221 S`` (Marlin's speed and flow percentages) set the factors; Hyrel's
  ``M221`` is a head's flow set-up, not a factor.

The session starts again from nothing homed when the link comes up again (the controller
may have been reset) and when a job starts (on Hyrel's link a job's own lines are not read
as they run: its acknowledgement says only that a line arrived). Pure: no I/O.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace

from repetrel_host.gcode.commands import command_rest, command_word

_AXES = "xyz"
MOTION_WORDS = frozenset({"G28", "M84", "M18", "M220", "M221"})  # what after() reads
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))?")


@dataclass(frozen=True, slots=True)
class MotionState:
    """What the commands the controller ran left: ``homed`` in Klipper's form ("xyz")."""

    homed: str = ""
    speed_factor: float = 1.0
    extrude_factor: float = 1.0


def after(state: MotionState, command: str, hyrel: bool) -> MotionState | None:
    """``state`` once ``command`` ran, or None when it changes nothing of it."""
    word = command_word(command.strip().upper())
    rest = command_rest(command.split(";", 1)[0].strip())
    words = dict(_WORD.findall(rest))  # a letter alone too: Marlin's "G28 X"
    named = {axis for axis in _AXES if axis.upper() in words}
    if word == "G28":
        homed = named or (set() if hyrel else set(_AXES))
        return _homed(state, set(state.homed) | homed) if homed else None
    if word in ("M84", "M18"):
        if not named and words.keys() & set("SEABC"):
            return None  # Marlin's idle timeout set, or only other motors turned off
        return _homed(state, set(state.homed) - (named or set(_AXES)))
    if word in ("M220", "M221") and not hyrel and words.get("S"):
        factor = float(words["S"]) / 100.0
        if word == "M220":
            return replace(state, speed_factor=factor)
        return replace(state, extrude_factor=factor)
    return None


def _homed(state: MotionState, axes: set[str]) -> MotionState:
    return replace(state, homed="".join(axis for axis in _AXES if axis in axes))
