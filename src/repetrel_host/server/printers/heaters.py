"""A printer's heaters as the page charts and sets them: its loadout's heads first, then
what its temperature reports show (a bed, a chamber), each with the command that sets it."""

from __future__ import annotations

import re
from typing import Any

from repetrel_host.server.printers.service import PrinterService


def heaters(service: PrinterService) -> list[dict[str, Any]]:
    """What the page charts and sets: each heater's sensor (as reports name it), a label
    (a Hyrel head by its slot and type), its kind, and the command that sets its target
    (``{target}`` in it). The loadout's heads first, then what the reports show."""
    printer = service.printer
    readings = dict(printer.temperatures) if printer is not None else {}
    hyrel = printer is not None and printer.settings.protocol == "hyrel"
    found: list[dict[str, Any]] = []
    loadout = service.plan_loadout()
    for head in loadout.heads if loadout is not None else ():
        sensor = f"T{head.tool}"
        if sensor not in readings and head.tool == 0 and "T" in readings:
            sensor = "T"  # a single hotend reported as T
        address = head.variable if hyrel else head.tool
        found.append(
            {
                "sensor": sensor,
                "label": f"T{head.tool} · slot {head.slot} · {head.name}",
                "kind": "head",
                "tool": head.tool,
                "command": f"M104 T{address} S{{target}}",
            }
        )
    known = {heater["sensor"] for heater in found}
    several = any(re.fullmatch(r"T\d+", sensor) for sensor in readings)
    # Heads by number, then the bed, then the chamber.
    for sensor in sorted(readings, key=lambda s: (s[0] != "T", s != "T", len(s), s)):
        if sensor in known or (sensor == "T" and several):
            continue  # "T" beside T0, T1...: the active one, shown by its number
        if sensor.startswith("T"):
            tool = int(sensor[1:] or 0)
            command = f"M104 T{tool} S{{target}}" if sensor != "T" else "M104 S{target}"
            found.append(
                {
                    "sensor": sensor,
                    "label": sensor,
                    "kind": "head",
                    "tool": tool,
                    "command": command,
                }
            )
        elif sensor in ("B", "C"):
            kind, command = ("bed", "M140") if sensor == "B" else ("chamber", "M141")
            found.append(
                {"sensor": sensor, "label": kind, "kind": kind, "command": f"{command} S{{target}}"}
            )
    return found
