"""What controllers report: temperatures (M105, auto-reports) and identity (M115)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

# A line that is a temperature report (M105's answer, an auto-report, a heat-up's):
# it starts with a reading.
_REPORT = re.compile(r"^\s*(?:ok\s+)?[TBC]\d*:\s*-?\d")
_READING = re.compile(r"(?<![\w@])([TBC]\d*):\s*(-?\d+(?:\.\d+)?)(?:\s*/\s*(-?\d+(?:\.\d+)?))?")
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
