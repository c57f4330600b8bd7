"""The controller side of the line protocol: check a received line, answer errors.

Marlin's rules and reply strings (PROTOCOL-NOTES.md section 2): a numbered line
must be the last number plus one (except M110, which sets it), and must carry
a matching checksum; otherwise the controller answers ``Error:...``,
``Resend: <last + 1>`` and ``ok``, and executes nothing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from repetrel_host.protocol.framing import checksum

_NUMBER = re.compile(rb"N(-?\d+)")


@dataclass(frozen=True, slots=True)
class Accepted:
    """A line to execute: its command without number and checksum."""

    command: str
    number: int | None


@dataclass(frozen=True, slots=True)
class Rejected:
    """A line refused for its framing; ``reply`` is what the controller sends back."""

    reason: str
    reply: bytes


@dataclass(frozen=True, slots=True)
class Ignored:
    """An empty line or a comment."""


LineOutcome = Accepted | Rejected | Ignored


class ControllerProtocol:
    """Checks received lines the way Marlin does; ``last_line`` is the last accepted number.

    ``drop_duplicates``: ignore, without a reply, a line numbered ``last_line`` or one
    less (a resent duplicate), as newer Marlin does. Unlike Marlin, a line with two
    ``*`` is refused: it is two lines run together by a lost newline, and one checksum
    in 256 would let it through.
    """

    def __init__(self, drop_duplicates: bool = False) -> None:
        self.last_line = 0
        self.drop_duplicates = drop_duplicates
        self.duplicates_dropped = 0

    def handle_line(self, raw: bytes) -> LineOutcome:
        """Check one received line (without its ``\\n``)."""
        line = raw.split(b";", 1)[0].strip()
        if not line:
            return Ignored()
        star = line.rfind(b"*")
        if not line.startswith(b"N"):
            if star >= 0:
                return self._reject("No Line Number with checksum")
            return Accepted(_text(line), None)
        match = _NUMBER.match(line)
        if match is None:
            return self._reject("Line Number is not Last Line Number+1")
        body = line[match.end() : star if star >= 0 else len(line)].strip()
        command = _text(body)
        is_m110 = body.upper().startswith(b"M110")
        number = int(match.group(1))
        if is_m110:
            # Marlin reads the N that follows M110, if there is one.
            second = _NUMBER.search(body, 4)
            if second is not None:
                number = int(second.group(1))
        elif number != self.last_line + 1:
            if self.drop_duplicates and number in (self.last_line, self.last_line - 1):
                self.duplicates_dropped += 1
                return Ignored()
            return self._reject("Line Number is not Last Line Number+1")
        if star < 0:
            return self._reject("No Checksum with line number")
        if line.count(b"*") > 1:
            return self._reject("checksum mismatch")
        try:
            expected = int(line[star + 1 :])
        except ValueError:
            return self._reject("checksum mismatch")
        if checksum(line[:star]) != expected:
            return self._reject("checksum mismatch")
        self.last_line = number
        return Accepted(command, number)

    def _reject(self, reason: str) -> Rejected:
        last = self.last_line
        reply = f"Error:{reason}, Last Line: {last}\nResend: {last + 1}\nok\n".encode("ascii")
        return Rejected(reason, reply)


def _text(data: bytes) -> str:
    return data.decode("ascii", errors="replace")
