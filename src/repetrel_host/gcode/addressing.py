"""Hyrel T addressing: tool-change commands and T variables, for firmware v4 and v5.

Sources: the T addressing v5 page (charts of addresses) and the G-code
reference (the M703 table for v4 head variables, the standard footer's T100
and T90 groups).

- A tool change ``T<n>`` selects the head in one position: yoke ``y``, slot ``s``
  (both from 1) is ``T(5 * (y - 1) + s - 1)``, T0..T19. Every yoke has five
  addresses; on four-position machines (ESR, 30M) the fifth is unused.
- A T variable inside an M-code (``M104 T1 S200``) names a device. In v5 it is
  the same number as the tool change, plus special devices T20..T25 and groups
  T30..T48. In v4 the heads of yoke 1 are T11..T15, all heads T100, all beds T90.
"""

from __future__ import annotations

import re
from typing import Literal

Firmware = Literal["v4", "v5"]

ADDRESSES_PER_YOKE = 5
MAX_YOKES = 4

SPECIAL_DEVICES_V5 = {
    20: "3-phase spindle",
    21: "CO2 laser",
    22: "Aux1",
    23: "Aux2",
    24: "Bed1 / Chamber1",
    25: "Bed2 / Chamber2",
}
GROUPS_V5 = {
    **{n: f"virtual head / group / squad {n}" for n in range(30, 40)},
    40: "all devices",
    41: "yoke 1, all heads",
    42: "yoke 2, all heads",
    43: "yoke 3, all heads",
    44: "yoke 4, all heads",
    45: "all aux devices",
    46: "all beds / chambers",
    47: "all non-bed / non-chamber devices",
    48: "all virtual devices (T30-T39)",
}
GROUPS_V4 = {100: "all heads", 90: "all beds"}
# v4 names the heads of yoke 1 T11..T15 (the M703 table's clone addresses).
V4_HEAD_BASE = 10

_TOOL_CHANGE = re.compile(r"^T(\d+)$", re.IGNORECASE)
_T_PARAMETER = re.compile(r"(?<![A-Za-z])T(\d+)", re.IGNORECASE)


def tool_number(yoke: int, slot: int) -> int:
    """The tool-change number of a position: yoke 1 slot 1 is 0, yoke 2 slot 1 is 5."""
    _check_position(yoke, slot)
    return ADDRESSES_PER_YOKE * (yoke - 1) + slot - 1


def position_of_tool(number: int) -> tuple[int, int] | None:
    """(yoke, slot) selected by ``T<number>``, or None outside T0..T19."""
    if 0 <= number < ADDRESSES_PER_YOKE * MAX_YOKES:
        return number // ADDRESSES_PER_YOKE + 1, number % ADDRESSES_PER_YOKE + 1
    return None


def head_variable(firmware: Firmware, yoke: int, slot: int) -> int:
    """The T value that names the head at (yoke, slot) inside M-codes."""
    _check_position(yoke, slot)
    if firmware == "v5":
        return tool_number(yoke, slot)
    if yoke != 1:
        raise ValueError("v4 head addresses are known for yoke 1 only (T11..T15)")
    return V4_HEAD_BASE + slot


def position_of_variable(firmware: Firmware, value: int) -> tuple[int, int] | None:
    """(yoke, slot) of the head a T variable names, or None for other devices and groups."""
    if firmware == "v5":
        return position_of_tool(value)
    if V4_HEAD_BASE + 1 <= value <= V4_HEAD_BASE + ADDRESSES_PER_YOKE:
        return 1, value - V4_HEAD_BASE
    return None


def all_heads_variable(firmware: Firmware) -> int:
    """The group address of every head (the footer's T100 in v4)."""
    return 100 if firmware == "v4" else 47


def all_beds_variable(firmware: Firmware) -> int:
    """The group address of every bed (the footer's T90 in v4)."""
    return 90 if firmware == "v4" else 46


def describe_variable(firmware: Firmware, value: int) -> str:
    """A short name for what a T variable addresses."""
    position = position_of_variable(firmware, value)
    if position is not None:
        return f"the head in yoke {position[0]}, slot {position[1]}"
    names = {**SPECIAL_DEVICES_V5, **GROUPS_V5} if firmware == "v5" else GROUPS_V4
    return names.get(value, "no known device")


def tool_change(command: str) -> int | None:
    """The number of a tool-change command (``T3`` gives 3), else None."""
    match = _TOOL_CHANGE.match(command.strip())
    return int(match.group(1)) if match else None


def t_parameter(command: str) -> int | None:
    """The T parameter of a command such as ``M104 T1 S200``, else None."""
    parts = command.split(" ", 1)
    if len(parts) < 2:
        return None
    match = _T_PARAMETER.search(parts[1])
    return int(match.group(1)) if match else None


def _check_position(yoke: int, slot: int) -> None:
    if not 1 <= yoke <= MAX_YOKES:
        raise ValueError(f"yoke must be 1 to {MAX_YOKES}, not {yoke}")
    if not 1 <= slot <= ADDRESSES_PER_YOKE:
        raise ValueError(f"slot must be 1 to {ADDRESSES_PER_YOKE}, not {slot}")
