"""What controllers report: temperatures (M105, auto-reports) and identity (M115)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

# A line that is a temperature report (M105's answer, an auto-report, a heat-up's, a
# Hyrel status report ">ST: T:..."): it starts with a reading.
_REPORT = re.compile(r"^\s*(?:ok\s+|>[A-Z]{2}:\s*)?[TBC]\d*:\s*-?\d")
_READING = re.compile(r"(?<![\w@])([TBC]\d*):\s*(-?\d+(?:\.\d+)?)(?:\s*/\s*(-?\d+(?:\.\d+)?))?")
# A heat wait's report on Marlin built with a residency: " W:?" until its heater is in the
# window, then " W:<seconds it still holds>".
_RESIDENCY = re.compile(r"\sW:(\?|\d+)")
# "FIRMWARE_NAME:Marlin 2.1.2 (Jan 1 2024) SOURCE_CODE_URL:... PROTOCOL_VERSION:1.0 ..."
_FIELD = re.compile(r"(?:^|\s)([A-Z][A-Z0-9_]+):")
_CAPABILITY = re.compile(r"^Cap:([A-Z0-9_]+):\s*([01])\s*$")


def parse_temperatures(text: str) -> dict[str, tuple[float, float | None]]:
    """``T:21.0 /200.0 B:60.0 /60.0 @:0`` as {sensor: (current, target)}; {} if the line
    is not a temperature report."""
    readings: dict[str, tuple[float, float | None]] = {}
    if _REPORT.match(text) is None:
        return readings
    for sensor, current, target in _READING.findall(text):
        readings[sensor] = (float(current), float(target) if target else None)
    return readings


def residency_left(text: str) -> float | None:
    """A heat wait report's ``W:``: the seconds the wait still holds (inf for ``W:?``, its
    heater not there yet); None when the report says none."""
    match = _RESIDENCY.search(text)
    if match is None:
        return None
    return math.inf if match.group(1) == "?" else float(match.group(1))


@dataclass(frozen=True, slots=True)
class Firmware:
    """What M115 said: ``fields`` (FIRMWARE_NAME, PROTOCOL_VERSION, MACHINE_TYPE...) and
    ``capabilities`` (Marlin's ``Cap:NAME:1`` lines)."""

    fields: dict[str, str]
    capabilities: dict[str, bool] = field(default_factory=dict)
    lines: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return self.fields.get("FIRMWARE_NAME", "")

    @property
    def identity(self) -> str:
        """The line that names the firmware, for choosing a machine profile."""
        return next((line for line in self.lines if "FIRMWARE_NAME" in line), self.name)

    def can(self, capability: str) -> bool:
        return self.capabilities.get(capability, False)

    @classmethod
    def parse(cls, lines: list[str]) -> Firmware | None:
        """The answer to M115, or None when it names no firmware."""
        fields: dict[str, str] = {}
        capabilities: dict[str, bool] = {}
        for line in lines:
            capability = _CAPABILITY.match(line.strip())
            if capability is not None:
                capabilities[capability.group(1)] = capability.group(2) == "1"
                continue
            matches = list(_FIELD.finditer(line))
            if not matches:
                continue
            ends = [m.start() for m in matches[1:]] + [len(line)]
            for match, end in zip(matches, ends, strict=True):
                fields[match.group(1)] = line[match.end() : end].strip()
        if "FIRMWARE_NAME" not in fields:
            return None
        return cls(fields, capabilities, tuple(lines))


_REPORT_LEVEL = re.compile(r"^>IN:\s*(?:\d+:\s?)?")
_COLUMNS = re.compile(r"\s{2,}")
_FIGURE = re.compile(r"-?\d")


@dataclass(frozen=True, slots=True)
class JobReport:
    """The M773 job report a Hyrel controller sends at M30 after ``M772 S1``: its rows as
    text, and the rows that hold figures as {label: [values]}, e.g. ``"Totals":
    ["12.5", "0.317"]`` (time in seconds, distance in metres) or
    ``"approx filament (PI*d)": ["0.132 m"]``."""

    lines: tuple[str, ...]
    complete: bool = True  # its "End M773" line came

    @property
    def fields(self) -> dict[str, list[str]]:
        found: dict[str, list[str]] = {}
        for line in self.lines:
            label, *values = _COLUMNS.split(line.strip())
            if label and values and _FIGURE.match(values[0]):
                found[label.rstrip(":")] = values
        return found

    @property
    def text(self) -> str:
        return "\n".join(self.lines)


class ReportReader:
    """Picks the M773 report out of the controller's lines as they come: the ``>IN:`` lines
    from ``Begin M773`` to ``End M773``, and the rows of stars around them."""

    def __init__(self) -> None:
        self.report: JobReport | None = None  # the latest, complete or as far as it came
        self._rows: list[str] | None = None  # the report's rows while it comes
        self._closing = False  # its End came: a row of stars may follow
        self._held: tuple[str, str] | None = None  # a row of stars: the report's, if Begin follows

    def feed(self, text: str) -> list[str]:
        """The lines that are not the report's, to be shown as they are."""
        if not text.startswith(">IN:"):
            if self._held is None:
                return [text]
            held, self._held = self._held[0], None  # a row of stars of something else
            return [held, text]
        body = _REPORT_LEVEL.sub("", text)
        stars = bool(body) and set(body) == {"*"}
        rows = self._rows
        if rows is not None:
            ended = self._closing
            if not ended or stars:
                rows.append(body)
                self._closing = ended or "End M773" in body
                self.report = JobReport(tuple(rows), complete=self._closing)
                if ended:
                    self._rows = None  # that was its last row of stars
                return []
            self._rows = None  # the report is over: this line is not its
        if "Begin M773" in body:
            self._rows = [self._held[1], body] if self._held is not None else [body]
            self._held = None
            self._closing = False
            self.report = JobReport(tuple(self._rows), complete=False)
            return []
        passed = [self._held[0]] if self._held is not None else []
        self._held = (text, body) if stars else None
        return passed if stars else [*passed, text]


# Sensors in the order people read them: hotends, then bed and chamber.
_SENSOR_ORDER = {"T": 0, "B": 2, "C": 3}


def format_temperatures(readings: dict[str, tuple[float, float | None]]) -> list[str]:
    """``T 200.1/200``, ``B 60.0/60``... in the order hotends, bed, chamber."""

    def order(sensor: str) -> tuple[int, str]:
        return _SENSOR_ORDER.get(sensor[:1], 1), sensor

    shown = []
    for sensor in sorted(readings, key=order):
        current, target = readings[sensor]
        aim = f"/{target:g}" if target is not None else ""
        shown.append(f"{sensor} {current:.1f}{aim}")
    return shown
