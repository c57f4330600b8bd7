"""A command on its way to the controller: the check of what a caller may send, the
command waiting for its reply, and the reply (its lines, then its ok).

The session's command queue (:mod:`.command_queue`) sends them; the pump's listener
(``repetrel_host.session.listener``) hands each its lines and its ok.
"""

from __future__ import annotations

import asyncio
import re
from dataclasses import dataclass

from repetrel_host.errors import UsageError
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol.framing import clean_line
from repetrel_host.session.job import MAX_COMMAND_LENGTH

_FRAMED = re.compile(r"^\s*N-?\d|\*", re.IGNORECASE)


@dataclass(frozen=True, slots=True)
class Reply:
    """The controller's answer to one command: its lines, then its ok."""

    command: str
    lines: list[str]  # the controller's lines for it, before its ok
    ok_line: str  # the ok line itself ("ok T:200.0 /200.0 B:60.0 /60.0"); "" when none came

    @property
    def ok(self) -> bool:
        """The controller acknowledged the command. False for M112 and M108, which go out
        at once (the firmware's emergency parser reads them) and get no ok."""
        return bool(self.ok_line)


class PendingCommand:
    """A command on its way: the lines that come for it, and the reply it awaits."""

    __slots__ = ("command", "future", "lines", "own")

    def __init__(self, command: str, future: asyncio.Future[Reply], own: bool = False) -> None:
        self.command = command
        self.lines: list[str] = []
        self.future = future
        self.own = own  # the session's own (the greeting's M115, a poll), not the caller's


def clean_command(line: str) -> str:
    """The command a caller asked to send, cleaned; a UsageError for what the host owns
    (line numbers, checksums, M110) or what no controller takes (empty, too long)."""
    if _FRAMED.search(line.split(";", 1)[0]):
        raise UsageError(
            "line numbers and checksums are the host's: send the command alone, "
            "without N<number> and *<checksum>"
        )
    command = clean_line(line, "command")
    if not command:
        raise UsageError("the command is empty")
    if len(command) > MAX_COMMAND_LENGTH:  # Marlin drops the rest: its checksum fails
        raise UsageError(
            f"the command is {len(command)} characters long; "
            f"controllers take at most {MAX_COMMAND_LENGTH}"
        )
    if command_word(command) == "M110":
        raise UsageError("M110 sets line numbers, which the host owns; it cannot be sent")
    return command
