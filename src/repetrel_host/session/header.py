"""The Hyrel header: each loaded head's settings, sent before the job.

Repetrel sends, for every loaded head in slot order, M6 (offsets), M721
(unprime), M722 (prime), M221 (flow) and M728 (motor current boost) (T
addressing v5 page, "Default Mode"), and the reference asks for a ``G4 P1``
after changing flow, prime or unprime values.

It is made from a loadout the configuration resolved, so it sits above ``config`` (which
imports ``gcode``), beside the planning (:mod:`.planning`) that puts it before a job.
"""

from __future__ import annotations

from repetrel_host.config import Loadout, ResolvedHead

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
