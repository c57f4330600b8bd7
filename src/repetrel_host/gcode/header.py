"""The Hyrel header: each loaded head's settings, sent before the job.

Repetrel sends, for every loaded head in slot order, M6 (offsets), M721
(unprime), M722 (prime), M221 (flow) and M728 (motor current boost) (T
addressing v5 page, "Default Mode"), and the reference asks for a ``G4 P1``
after changing flow, prime or unprime values.
"""

from __future__ import annotations

from repetrel_host.config import Loadout, ResolvedHead
from repetrel_host.gcode import addressing

PAUSE_AFTER_FLOW_CHANGES = "G4 P1"


def format_number(value: int | float) -> str:
    """A number as the reference writes it: ints bare (``P-15``), floats with a point (``S1.0``)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"not a number: {value!r}")
    if isinstance(value, int):
        return str(value)
    text = repr(value)
    if "e" in text or "E" in text:  # G-code has no exponents
        text = f"{value:.10f}".rstrip("0")
        text = text + "0" if text.endswith(".") else text
    return text


def head_commands(loaded: ResolvedHead) -> list[str]:
    """The five header commands for one head."""
    n = format_number
    t = f"T{loaded.variable}"
    head, offset = loaded.head, loaded.offset
    m6 = f"M6 {t} O{loaded.register} X{n(offset.x)} Y{n(offset.y)} Z{n(offset.z)}"
    if offset.a is not None:
        m6 += f" A{n(offset.a)}"
    if offset.b is not None:
        m6 += f" B{n(offset.b)}"
    unprime, prime, flow = head.unprime, head.prime, head.flow
    return [
        m6,
        f"M721 S{n(unprime.speed)} E{n(unprime.pulses)} P{n(unprime.time)} {t}",
        f"M722 S{n(prime.speed)} E{n(prime.pulses)} P{n(prime.time)} {t}",
        f"M221 S{n(flow.multiplier)} {t} P{n(flow.pulses_per_ul)} "
        f"W{n(flow.width)} Z{n(flow.layer)}",
        f"M728 {t} S{n(head.current_boost)}",
    ]


def header_commands(loadout: Loadout) -> list[tuple[str, str]]:
    """(command, origin) for the whole header; origin reads ``header: head T1``."""
    lines: list[tuple[str, str]] = []
    for loaded in loadout.heads:
        origin = f"header: head T{loaded.tool} ({loaded.name})"
        lines.extend((command, origin) for command in head_commands(loaded))
    if lines:
        lines.append((PAUSE_AFTER_FLOW_CHANGES, "header"))
    return lines


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
