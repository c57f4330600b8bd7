"""Classify one line received from a controller.

Reply strings are Marlin's and RepRap's (docs/protocol.md), plus Hyrel's tagged lines
(docs/hyrel-link.md).
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Ok:
    """``ok``, with optional data (``ok T:200.0 /200.0``) or ADVANCED_OK fields."""

    data: str = ""
    line_number: int | None = None
    planner_free: int | None = None
    slots_free: int | None = None


@dataclass(frozen=True, slots=True)
class ResendRequest:
    """The controller asks for every line from ``line_number`` on again."""

    line_number: int


@dataclass(frozen=True, slots=True)
class Error:
    """``Error:...`` or ``!!...``; ``line_error`` when it is about framing, which a resend fixes."""

    text: str
    line_error: bool


@dataclass(frozen=True, slots=True)
class Busy:
    """``echo:busy: processing``: a long command is running, the controller is alive."""

    text: str


@dataclass(frozen=True, slots=True)
class Wait:
    """``wait``: the controller is idle (Marlin with NO_TIMEOUTS)."""


@dataclass(frozen=True, slots=True)
class Start:
    """``start``: the controller (re)booted."""


@dataclass(frozen=True, slots=True)
class HyrelReport:
    """A Hyrel tagged line such as ``>IN:  50: ...``; ``tag`` is ``IN``, ``ER``, ``GB``..."""

    tag: str
    text: str


@dataclass(frozen=True, slots=True)
class OtherReply:
    """Anything else: ``echo:`` lines, ``//`` comments, unknown text."""

    text: str


PLAIN_OK = Ok()  # the reply nearly every line draws: one shared instance

Reply = Ok | ResendRequest | Error | Busy | Wait | Start | HyrelReport | OtherReply

# The whole line must match: a garbled number ("Resend: 16?9") must not pass for another.
_RESEND = re.compile(r"^(?:resend|rs)\s*:?\s*N?\s*(\d+)\s*$", re.IGNORECASE)
_ADVANCED_OK = re.compile(r"^N(\d+)\s+P(\d+)\s+B(\d+)")
_HYREL = re.compile(r"^>([A-Za-z]{2}):\s?(.*)$")
# Marlin's errors about a line's framing: answered by a resend request, not fatal.
# OctoPrint's virtual printer says "expected line <n> got <m>".
_LINE_ERRORS = ("checksum", "line number", "last line", "format error", "expected line")


def classify(line: str) -> Reply:
    """Classify one received line (without its line ending)."""
    text = line.strip()
    lower = text.lower()
    if lower == "ok":
        return PLAIN_OK
    if lower.startswith("ok "):
        data = text[3:].strip()
        advanced = _ADVANCED_OK.match(data)
        if advanced is not None:
            n, p, b = (int(g) for g in advanced.groups())
            return Ok(data, line_number=n, planner_free=p, slots_free=b)
        return Ok(data)
    resend = _RESEND.match(text)
    if resend is not None:
        return ResendRequest(int(resend.group(1)))
    if lower.startswith("error") or text.startswith("!!"):
        body = text[6:].strip() if lower.startswith("error") else text[2:].strip()
        return Error(body, line_error=any(key in body.lower() for key in _LINE_ERRORS))
    if lower.startswith("echo:busy:") or lower.startswith("busy:"):
        return Busy(text)
    if lower == "wait":
        return Wait()
    if lower == "start":
        return Start()
    hyrel = _HYREL.match(text)
    if hyrel is not None:
        return HyrelReport(hyrel.group(1).upper(), hyrel.group(2))
    return OtherReply(text)
