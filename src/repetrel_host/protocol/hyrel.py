"""Hyrel's own controller link, both sides of the wire: pure, no I/O (docs/hyrel-link.md).

What the notes give (from a public port of the Hyrel "Hydra" firmware; Repetrel itself is
closed): every line the controller receives earns one ACK byte (0x06) while its receive
buffer has headroom; an ACK is credit, not "done". A line may start with ``N<n>`` (the
controller's line number for its reports) and end with ``*<sum>``, an *additive* checksum of
the bytes before ``*``; a mismatch is only reported. Single control bytes act at once, and
0x09 as a line's first byte marks it urgent. Messages are tagged lines (``>IN:``, ``>ER:``,
``>MC:``, ``>Hy:``...; :func:`repetrel_host.protocol.replies.classify` reads them).

This module frames and splits; the host's dialect and the fake controller build on it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import IntEnum


class Control(IntEnum):
    """Single bytes that act at once, between lines (and, for ACK, from the controller)."""

    END_WAIT = 0x01  # end any wait (M0, a heat-up); echoed back
    PAUSE_AT_MOVE_END = 0x02
    PAUSE_AT_LAYER_END = 0x03
    STATUS = 0x05  # a status report
    ACK = 0x06  # controller -> host: one line received
    PING = 0x07  # the reply starts ">Hy:"
    ABORT = 0x08
    URGENT = 0x09  # as a line's first byte: the line goes ahead of the queue
    WATCHDOG = 0x0E  # the host is alive


# The M-codes whose processing the controller reports with a ``>MC:`` notice: those the
# notes name (M0, M6, M30, M104, M109, M140, M190: "many M-codes ..."), and M1, M106, M107
# and M772, which the fake reports too. Only these are awaited by the host, and the fake
# notices exactly these. The host never relies on the set being complete or exact: a notice
# confirms through the oldest awaited line it may be about, whatever came before it.
NOTICED = frozenset(
    {"M0", "M1", "M6", "M30", "M104", "M106", "M107", "M109", "M140", "M190", "M772"}
)
_CONTROL_BYTES = frozenset(int(byte) for byte in Control) - {Control.URGENT}
_NUMBER = re.compile(rb"N(\d+)\s*")
_NOTICE_FIELD = re.compile(r"([A-Za-z])\s*(-?\d+(?:\.\d*)?)")


def additive_checksum(data: bytes) -> int:
    """The sum of the bytes before ``*``. (Its width in the firmware is not in the notes:
    the whole sum is sent, which a line of 96 ASCII bytes keeps under 12,200.)"""
    return sum(data)


def frame(command: str, number: int | None = None, checksum: bool = False) -> bytes:
    """One line for the wire: ``[N<number> ]<command>[*<sum>]\\n``."""
    body = (f"N{number} {command}" if number is not None else command).encode("ascii")
    if checksum:
        body += b"*" + str(additive_checksum(body)).encode("ascii")
    return body + b"\n"


def mark_urgent(line: bytes) -> bytes:
    """A framed line marked urgent: the controller runs it ahead of what it holds."""
    return bytes([Control.URGENT]) + line


class HostReceiver:
    """Splits what the controller sends into ACK credits and text lines, in their order.

    An ACK byte may come between lines or inside one (the controller sends it as soon as
    it has taken a line, whatever it is writing): it is counted and taken out of the text.
    :attr:`acks_before` says, for each line :meth:`feed` returns, how many of the ACKs not
    yet taken came before that line's end (the controller wrote them first).
    """

    def __init__(self) -> None:
        self._partial = bytearray()  # as it came, control bytes and all
        self._partial_acks = 0  # ACKs in it, counted already
        self._acked = False  # an ACK came in blank lines since the last line
        self.acks = 0  # ACK bytes not yet taken with :meth:`take_acks`
        self.acks_before: list[int] = []
        self.acked_ahead: list[bool] = []
        self.acks_inside: list[list[int]] = []
        self.end_wait_echoes = 0

    def feed(self, data: bytes) -> list[str]:
        """The complete lines in ``data`` (and what came before it), without control bytes.
        :attr:`acked_ahead` says, for each, whether an ACK came between the line before
        and its text; :attr:`acks_inside`, where in its text ACKs came."""
        *complete, rest = (self._partial + data).split(b"\n")
        lines: list[str] = []
        self.acks_before = before = []
        self.acked_ahead = ahead = []
        self.acks_inside = inside = []
        acks = self.acks - self._partial_acks  # those in the partial line are counted again
        acked = self._acked
        for raw in complete:
            count = raw.count(Control.ACK)
            acks += count
            line = _text(raw).decode("ascii", errors="replace").strip()
            if line:
                lines.append(line)
                before.append(acks)
                lead = len(raw) - len(raw.lstrip(_BLANK))
                ahead.append(acked or Control.ACK in raw[:lead])
                inside.append(_ack_places(raw[lead:]) if count else [])
                acked = False
            else:
                acked = acked or count > 0
        self._acked = acked
        self._partial = bytearray(rest)
        self._partial_acks = rest.count(Control.ACK)
        self.acks = acks + self._partial_acks
        self.end_wait_echoes += data.count(Control.END_WAIT)
        return lines

    def take_acks(self) -> int:
        acks, self.acks = self.acks, 0
        return acks


_BLANK = b"\x06\x01 \t\r"  # what may come before a line's text


def _ack_places(raw: bytes | bytearray) -> list[int]:
    """Where in the text of ``raw`` (its ACK and end-wait bytes taken out) ACKs came."""
    places: list[int] = []
    at = 0
    for piece in raw.split(b"\x06")[:-1]:
        at += len(piece.replace(b"\x01", b""))
        places.append(at)
    return places


def _text(raw: bytes | bytearray) -> bytes:
    """A received line without the ACK and end-wait bytes that came inside it."""
    return bytes(raw).replace(b"\x06", b"").replace(b"\x01", b"")


@dataclass(frozen=True, slots=True)
class HyrelNotice:
    """``>MC:M109: T11: S200:``: the controller processed an M-code (so every line before
    it ran). ``fields`` holds its letters and values: ``{"T": "11", "S": "200"}``."""

    code: str
    fields: dict[str, str]


def parse_notice(text: str) -> HyrelNotice | None:
    """The text after ``>MC:`` as a :class:`HyrelNotice`; None when it names no M-code, or a
    part of it is no field (a byte garbled: what it says cannot be told)."""
    parts = [part.strip() for part in text.split(":")]
    code = parts[0].upper() if parts else ""
    if not re.fullmatch(r"M\d+", code):
        return None
    fields: dict[str, str] = {}
    for part in filter(None, parts[1:]):
        match = _NOTICE_FIELD.fullmatch(part)
        if match is None:
            return None
        fields[match.group(1).upper()] = match.group(2)
    return HyrelNotice(f"M{int(code[1:])}", fields)


@dataclass(frozen=True, slots=True)
class ReceivedLine:
    """A line the controller took: its command, the ``N`` it set, and whether it was urgent
    or failed its checksum (which the controller only reports)."""

    command: str
    number: int | None
    urgent: bool
    checksum_ok: bool = True


@dataclass(frozen=True, slots=True)
class ReceivedControl:
    """A control byte, acted on at once."""

    control: Control


class ControllerReceiver:
    """The controller's side: bytes from the host, as control bytes and lines, in order."""

    def __init__(self) -> None:
        self._partial = bytearray()

    def feed(self, data: bytes) -> list[ReceivedLine | ReceivedControl]:
        received: list[ReceivedLine | ReceivedControl] = []
        for byte in data:
            if byte in _CONTROL_BYTES:
                received.append(ReceivedControl(Control(byte)))
            elif byte == 0x0A:  # \n
                line = read_line(bytes(self._partial))
                self._partial.clear()
                if line is not None:
                    received.append(line)
            else:
                self._partial.append(byte)
        return received


def read_line(raw: bytes) -> ReceivedLine | None:
    """One received line (without its ``\\n``); None for an empty line or a comment."""
    urgent_line = raw.startswith(b"\x09")
    line = raw[1:] if urgent_line else raw
    line = line.split(b";", 1)[0].strip()
    checksum_ok = True
    star = line.rfind(b"*")
    if star >= 0:
        body, given = line[:star], line[star + 1 :].strip()
        checksum_ok = given.isdigit() and int(given) == additive_checksum(body)
        line = body.strip()
    number = None
    match = _NUMBER.match(line)
    if match is not None:
        number = int(match.group(1))
        line = line[match.end() :]
    if not line and number is None:
        return None
    command = line.decode("ascii", errors="replace").strip()
    return ReceivedLine(command, number, urgent_line, checksum_ok)
