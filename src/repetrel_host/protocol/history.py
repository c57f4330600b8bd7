"""Numbered lines: the numbering cursor, and the lines the controller may still ask for."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(slots=True)
class Line:
    """One numbered line, framed once."""

    number: int
    command: str
    tag: object
    wire: bytes
    unbuffered: bool
    # The host's own lines, never reported as acknowledged: M110 and a probe that runs.
    is_reset: bool = False
    is_probe: bool = False
    transmitted: bool = False
    acknowledged: bool = False
    is_host_line: bool = False  # is_reset or is_probe, read for every acknowledgement
    # A command whose reply someone waits for: probed as late as an unbuffered line, since
    # a probe's answer comes before the oks of lines the controller still holds.
    patient: bool = False


class History:
    """Lines by number, from ``floor`` to ``next_number - 1``.

    ``cursor`` is the next number to transmit: below ``next_number`` while lines
    are being sent again after a resend request.
    """

    __slots__ = ("cursor", "floor", "lines", "margin", "next_number")

    def __init__(self, margin: int) -> None:
        self.margin = margin  # lines kept behind the last acknowledged one
        self.lines: dict[int, Line] = {}
        self.floor = 0  # lowest number still held
        self.next_number = 0  # the number the next new line gets
        self.cursor = 0

    def restart(self, reset: Line) -> None:
        """Numbering starts again at ``reset`` (an M110 line), which goes out first."""
        self.lines = {reset.number: reset}
        self.floor = self.cursor = reset.number
        self.next_number = reset.number + 1

    def append(self, line: Line) -> None:
        self.lines[line.number] = line
        self.next_number += 1

    def get(self, number: int) -> Line | None:
        return self.lines.get(number)

    def prune(self, acknowledged_through: int) -> None:
        """Forget lines far enough behind the last acknowledged one."""
        floor = acknowledged_through - self.margin
        while self.floor < floor:
            self.lines.pop(self.floor, None)
            self.floor += 1

    def held(self) -> str:
        return f"{self.floor}..{self.next_number - 1}"
