"""The controller side of the line protocol: check a received line, answer errors.

Marlin's rules and reply strings (docs/protocol.md, "Marlin's replies"): a numbered line
must be the last number plus one (except M110, which sets it), and must carry
a matching checksum; otherwise the controller answers ``Error:...``,
``Resend: <last + 1>`` and ``ok``, and executes nothing.

``counted_resend`` answers as OctoPrint's virtual printer does instead: the
checksum is checked first, every line with a valid one is counted (resent and
out-of-sequence lines too), and a bad checksum draws ``Resend:`` for that count
plus one, which also becomes the controller's own idea of the last line.
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
    in 256 would let it through. ``counted_resend``: see the module's docstring.
    """

    def __init__(self, drop_duplicates: bool = False, counted_resend: bool = False) -> None:
        self.last_line = 0
        self.drop_duplicates = drop_duplicates
        self.duplicates_dropped = 0
        self.counted_resend = counted_resend
        self.received = 0  # lines with a valid checksum (counted_resend)

    def handle_line(self, raw: bytes, drop: bool = False) -> LineOutcome:
        """Check one received line (without its ``\\n``).

        ``drop``: a line that passes is refused anyway with only ``Error: No Line
        Number with checksum, Last Line: <n>``: no resend request, no ok (as OctoPrint's
        virtual printer does at its line 110).
        """
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
        if self.counted_resend:
            return self._counted(line, star, number, is_m110, command, drop)
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
        if drop and not is_m110:
            return self._drop()
        self.last_line = number
        return Accepted(command, number)

    def _counted(
        self, line: bytes, star: int, number: int, is_m110: bool, command: str, drop: bool
    ) -> LineOutcome:
        if not _checksum_fits(line, star):
            self.last_line = self.received
            return Rejected(
                "checksum mismatch",
                f"Error: Checksum mismatch\nResend:{self.received + 1}\nok\n".encode("ascii"),
            )
        self.received += 1
        if is_m110:
            self.last_line = self.received = number
            return Accepted(command, number)
        expected = self.last_line + 1
        if number != expected:
            reply = f"Error: expected line {expected} got {number}\nResend:{expected}\nok\n"
            return Rejected("line number", reply.encode("ascii"))
        if drop:
            return self._drop()
        self.last_line = number
        return Accepted(command, number)

    def _drop(self) -> Rejected:
        reply = f"Error: No Line Number with checksum, Last Line: {self.last_line}\n"
        return Rejected("dropped", reply.encode("ascii"))

    def _reject(self, reason: str) -> Rejected:
        last = self.last_line
        reply = f"Error:{reason}, Last Line: {last}\nResend: {last + 1}\nok\n".encode("ascii")
        return Rejected(reason, reply)


def _checksum_fits(line: bytes, star: int) -> bool:
    if star < 0 or line.count(b"*") > 1:
        return False
    try:
        return checksum(line[:star]) == int(line[star + 1 :])
    except ValueError:
        return False


def _text(data: bytes) -> str:
    return data.decode("ascii", errors="replace")
