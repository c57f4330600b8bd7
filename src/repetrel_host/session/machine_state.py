"""The machine's state where a job stood, read from its commands, and the lines that restore
it: the preamble of a print recovered from a source line (:mod:`.recovery`), and the way back
after commands moved the machine during a pause (:func:`back_to_job`).

For a recovery the state is read from the commands of the part of the file that is skipped,
as OctoPrint's recovery plug-ins do (OctoPrint-SkipTo keeps the skipped part's temperature
and set-up commands and drops its moves; OctoPrint-PowerFailure rebuilds the set-up from
the lines known to have printed). The preamble restores it in the order of Marlin's
power-loss recovery (``PrintJobRecovery::resume()`` in MarlinFirmware/Marlin,
Marlin/src/feature/powerloss.cpp, which ``M1000`` runs), which is also what OctoPrint's
"before print job is resumed" script and Cura's PauseAtHeight do after their pause:

1. the heaters: every target set first (they heat together), then the waits (Marlin waits for
   the chamber, the bed, then the hotends before anything moves);
2. units and absolute positioning for the moves that follow;
3. Z raised clear of the part, then X and Y homed (Marlin's ``G28 R0 X Y``: the safe stop
   turned the motors off, so X and Y may have been pushed); Z is never homed, the part is on
   the bed, and the controller is trusted to know Z (the lead screws hold it);
4. the tool (Marlin's ``T<e> S``), the flow and speed factors, the fans that were on;
5. back over the recovery point's X and Y, down to its Z, then ``G92 E`` (Marlin's ``G92.9 E``),
   the file's positioning and extrusion modes, and its feed rate last (Marlin's ``G1 F``).

Not restored: a ``G92`` of X, Y or Z in the skipped part (a shifted coordinate system cannot
be rebuilt once X and Y are homed), firmware retraction, and a purge: the file's next
extruding move goes on from the E it expects.

Pure: it reads the commands it is given and builds lines; nothing here touches a file or port.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum

from repetrel_host.gcode.commands import command_rest, command_word, command_words

LIFT = 10.0  # mm above the highest Z of the skipped part (the safe stop lifts 10 mm too)
Z_FEED = 600.0  # mm/min for the Z moves, XY_FEED for the XY one (Marlin's recovery's)
XY_FEED = 3000.0
MM_PER_INCH = 25.4
# Hyrel's group addresses (v5's T30..T48, v4's T90 and T100) can be set but not waited for:
# its reference says M109 fails on a group.
FIRST_GROUP_ADDRESS = 30

_HEATERS = {  # set command -> (heater kind, waits)
    "M104": ("hotend", False),
    "M109": ("hotend", True),
    "M140": ("bed", False),
    "M190": ("bed", True),
    "M141": ("chamber", False),
    "M191": ("chamber", True),
}
_SET = {"hotend": "M104", "bed": "M140", "chamber": "M141"}
_WAIT = {"hotend": "M109", "bed": "M190", "chamber": "M191"}
_KIND_ORDER = {"chamber": 0, "bed": 1, "hotend": 2}  # as Marlin waits for them
# Settings whose last command wins, replayed as the file wrote them, keyed by their T word:
# speed and flow factors, volumetric extrusion (Marlin's M200, Hyrel's M229 E-value mode),
# linear advance.
_REPLAYED = {
    "M220": "the speed factor",
    "M221": "the flow factor",
    "M200": "volumetric extrusion",
    "M229": "the E values' meaning (Hyrel)",
    "M900": "linear advance",
}


class HomeAxes(StrEnum):
    """What the preamble homes before it goes back to where the job stood."""

    XY = "xy"  # X and Y (default): their motors were off, the part stays on the bed
    NONE = "none"  # nothing: the controller still knows where X and Y are


@dataclass(frozen=True, slots=True)
class HeaterTarget:
    """A heater's target as the skipped part left it."""

    kind: str  # hotend, bed, chamber
    address: int | None  # its T word; None: the command named none (the current tool's)
    target: float
    waited: bool  # the skipped part waited for it (M109, M190, M191)
    line: int  # the source line that set it


@dataclass
class MachineState:
    """What the commands of the skipped part leave the machine in (None: not known)."""

    heaters: dict[tuple[str, int | None], HeaterTarget] = field(default_factory=dict)
    # Fans that are on: Marlin's by P (the fan's index), Hyrel's by T and duty (S: always,
    # P: during extrusion moves); the command that turned each on, and its line.
    fans: dict[tuple[str, int | None, str], tuple[str, int]] = field(default_factory=dict)
    fan_range: tuple[str, int] | None = None  # Hyrel's M106 C<range>, before any fan
    settings: dict[tuple[str, int | None], tuple[str, int]] = field(default_factory=dict)
    absolute: bool = True  # G90 / G91
    absolute_e: bool = True  # M82 / M83 (G90 and G91 set E too, as in Marlin)
    inches: bool = False  # G20 / G21
    tool: int | None = None
    feed: float | None = None
    x: float | None = None
    y: float | None = None
    z: float | None = None
    e: float | None = None
    highest_z: float | None = None

    def apply(self, number: int, command: str) -> None:
        """Take one command of the skipped part into account."""
        word = command_word(command)
        if word in ("G0", "G1", "G2", "G3"):
            self._move(command_words(command))
        elif word in _HEATERS:
            self._heater(number, word, command_words(command))
        elif word == "M106":
            self._fan(number, command, command_words(command))
        elif word == "M107":
            self._fan_off(command_words(command))
        elif word in _REPLAYED:
            self.settings[(word, _int(command_words(command).get("T")))] = (command, number)
        elif word == "G90":
            self.absolute = self.absolute_e = True
        elif word == "G91":
            self.absolute = self.absolute_e = False
        elif word == "M82":
            self.absolute_e = True
        elif word == "M83":
            self.absolute_e = False
        elif word in ("G20", "G21"):
            self.inches = word == "G20"
        elif word == "G92":
            self._set_position(command_words(command))
        elif word == "G28":
            self._homed(command)
        elif word[:1] == "T" and word[1:].isdigit():
            self.tool = int(word[1:])

    def _move(self, words: dict[str, float]) -> None:
        if "F" in words:
            self.feed = words["F"]
        for axis in "XYZ":
            if axis in words:
                self._axis(axis, words[axis], self.absolute)
        if "E" in words:
            self._axis("E", words["E"], self.absolute_e)
        if self.z is not None and (self.highest_z is None or self.z > self.highest_z):
            self.highest_z = self.z

    def _axis(self, axis: str, value: float, absolute: bool) -> None:
        name = axis.lower()
        current: float | None = getattr(self, name)
        if absolute:
            setattr(self, name, value)
        elif current is not None:
            setattr(self, name, current + value)

    def _heater(self, number: int, word: str, words: dict[str, float]) -> None:
        kind, waits = _HEATERS[word]
        address = _int(words.get("T"))
        if address is None and kind == "hotend":
            # The current tool's: named, since the preamble heats before it selects the tool.
            address = self.tool
        target = words.get("S", words.get("R"))  # Marlin's M109 R waits for cooling too
        key = (kind, address)
        previous = self.heaters.get(key)
        if target is None:  # a wait for the target set before (Hyrel's M109 T# without S)
            if previous is not None and waits:
                self.heaters[key] = HeaterTarget(
                    kind, address, previous.target, True, previous.line
                )
            return
        waited = waits or (previous is not None and previous.waited)
        self.heaters[key] = HeaterTarget(kind, address, target, waited, number)

    def _fan(self, number: int, command: str, words: dict[str, float]) -> None:
        if "C" in words and "S" not in words and "P" not in words:
            self.fan_range = (command, number)  # Hyrel: the range later M106s are read in
            return
        key, value = _fan_key(words)
        if value == 0:
            self.fans.pop(key, None)
        else:
            self.fans[key] = (command, number)

    def _fan_off(self, words: dict[str, float]) -> None:
        if "T" in words:  # Hyrel's M107 T#: that head's fan, both its duties
            head = _int(words["T"])
            for key in [k for k in self.fans if k[0] == "T" and k[1] == head]:
                del self.fans[key]
        else:
            self.fans.pop(("P", _int(words.get("P")), "S"), None)

    def _set_position(self, words: dict[str, float]) -> None:
        axes = [a for a in "XYZE" if a in words] or list("XYZE")  # a bare G92 zeroes them all
        for axis in axes:
            setattr(self, axis.lower(), words.get(axis, 0.0))

    def _homed(self, command: str) -> None:
        # Where home is, the file does not say: unknown until a move names the axis. The
        # axes are named with or without a value (G28 X, G28 X0).
        named = command_rest(command)
        for axis in [a for a in "XYZ" if a in named] or list("XYZ"):
            setattr(self, axis.lower(), None)


@dataclass(frozen=True, slots=True)
class PreambleLine:
    """One command of the preamble and why it is there."""

    command: str
    why: str


def track(commands: Iterable[tuple[int, str]]) -> MachineState:
    """The state the ``(source line, command)`` pairs leave the machine in."""
    state = MachineState()
    for number, command in commands:
        state.apply(number, command)
    return state


def preamble(state: MachineState, home: HomeAxes = HomeAxes.XY) -> list[PreambleLine]:
    """The commands that restore ``state`` before the job goes on (see the module's docstring)."""
    lines: list[PreambleLine] = []
    add = lines.append
    heaters = sorted(
        (h for h in state.heaters.values() if h.target > 0),
        key=lambda h: (_KIND_ORDER[h.kind], h.address if h.address is not None else -1),
    )
    for heater in heaters:
        why = f"heat {_name(heater)} to {_n(heater.target)} (as line {heater.line} did)"
        add(PreambleLine(_heat(_SET[heater.kind], heater), why))
    for heater in heaters:
        if heater.address is None or heater.address < FIRST_GROUP_ADDRESS:
            why = f"wait until {_name(heater)} is at {_n(heater.target)}"
            add(PreambleLine(_heat(_WAIT[heater.kind], heater), why))
    scale = MM_PER_INCH if state.inches else 1.0
    add(PreambleLine("G20" if state.inches else "G21", "the file's units"))
    add(PreambleLine("G90", "absolute positioning for the moves back"))
    if state.highest_z is not None:
        safe = state.highest_z + LIFT / scale
        add(PreambleLine(f"G0 Z{_n(safe)} F{_n(Z_FEED / scale)}", "raise Z clear of the part"))
    if home is HomeAxes.XY:
        add(PreambleLine("G28 X0 Y0", "home X and Y (never Z: the part is on the bed)"))
    if state.tool is not None:
        add(PreambleLine(f"T{state.tool}", "the tool the job was using"))
    for command, number in sorted(state.settings.values(), key=lambda s: s[1]):
        add(PreambleLine(command, f"{_REPLAYED[command_word(command)]} (line {number})"))
    if state.fan_range is not None:
        add(PreambleLine(state.fan_range[0], f"the fans' range (line {state.fan_range[1]})"))
    for command, number in sorted(state.fans.values(), key=lambda f: f[1]):
        add(PreambleLine(command, f"a fan the job had on (line {number})"))
    return lines + _where_it_stood(state)


def _where_it_stood(state: MachineState) -> list[PreambleLine]:
    """Back over the job's point and down to its Z, then its extruder position, its modes
    and its feed rate (absolute positioning first sent)."""
    scale = MM_PER_INCH if state.inches else 1.0
    lines: list[PreambleLine] = []
    add = lines.append
    if state.x is not None or state.y is not None:
        xy = " ".join(f"{a}{_n(v)}" for a, v in (("X", state.x), ("Y", state.y)) if v is not None)
        add(PreambleLine(f"G0 {xy} F{_n(XY_FEED / scale)}", "back over where the job stood"))
    if state.z is not None:
        add(PreambleLine(f"G0 Z{_n(state.z)} F{_n(Z_FEED / scale)}", "down to its Z"))
    if state.absolute_e and state.e is not None:
        add(PreambleLine(f"G92 E{_n(state.e)}", "the extruder's position where the job stood"))
    if not state.absolute:
        add(PreambleLine("G91", "the file's relative positioning"))
    add(
        PreambleLine("M82", "absolute extrusion, as the file")
        if state.absolute_e
        else PreambleLine("M83", "relative extrusion, as the file")
    )
    if state.feed is not None:
        add(PreambleLine(f"G1 F{_n(state.feed)}", "the feed rate the job was moving at"))
    return lines


# What a person may send during a pause without moving the machine or changing a mode the
# job's next lines rely on: reports, temperatures, fans, factors, messages.
KEEPS_THE_JOB_STATE = frozenset(
    "M105 M114 M115 M119 M503 M104 M109 M140 M190 M141 M191 M106 M107 M220 M221 M117 M118".split()
)


def back_to_job(
    state: MachineState, tool_changed: bool, motors_off: bool = False
) -> list[PreambleLine]:
    """After commands moved the machine (or changed its modes) during a pause: back over
    where the job stood and down to its Z, its tool (``tool_changed``: a T was sent), its
    extruder position, its positioning and extrusion modes and its feed rate, so that its
    next line means what the file meant (as Marlin comes back from M125's park). With
    ``motors_off`` (M84 or M18 was sent: X and Y may have been pushed by hand), Z is raised
    clear of the part and X and Y homed first, as a recovered job's preamble does."""
    scale = MM_PER_INCH if state.inches else 1.0
    lines = [PreambleLine("G90", "absolute positioning for the moves back")]
    add = lines.append
    if motors_off:
        if state.highest_z is not None:
            safe = state.highest_z + LIFT / scale
            add(PreambleLine(f"G0 Z{_n(safe)} F{_n(Z_FEED / scale)}", "raise Z clear of the part"))
        add(PreambleLine("G28 X0 Y0", "home X and Y: their motors were off (never Z)"))
    if tool_changed and state.tool is not None:
        add(PreambleLine(f"T{state.tool}", "the tool the job was using"))
    return lines + _where_it_stood(state)


def _heat(word: str, heater: HeaterTarget) -> str:
    address = f" T{heater.address}" if heater.address is not None else ""
    return f"{word}{address} S{_n(heater.target)}"


def _name(heater: HeaterTarget) -> str:
    which = f" T{heater.address}" if heater.address is not None else ""
    return f"the {heater.kind}{which}"


def _fan_key(words: dict[str, float]) -> tuple[tuple[str, int | None, str], float]:
    """Which fan an M106 sets, and to what (S defaults to full on)."""
    if "T" in words:
        duty = "P" if "P" in words and "S" not in words else "S"
        return ("T", _int(words["T"]), duty), words.get(duty, 100.0)
    return ("P", _int(words.get("P")), "S"), words.get("S", 255.0)


def _int(value: float | None) -> int | None:
    return None if value is None else int(value)


def _n(value: float) -> str:
    """A number as G-code writes it: no exponent, no trailing zeros."""
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text
