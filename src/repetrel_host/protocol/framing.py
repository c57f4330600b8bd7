"""Line framing of the RepRap protocol: ``N<n> <command>*<cs>\\n``.

The checksum is the XOR of every byte before ``*`` (reprap-gcode-protocol.txt,
"Checking"), written in decimal.
"""

from __future__ import annotations

import re

from repetrel_host.errors import JobError

# A line a slicer or another host already framed: "N12 G1 X5*87". Its number and
# checksum are the old host's, so we strip both and renumber.
_CONTROL = re.compile(r"[\x00-\x1f]")
_EXISTING_FRAME = re.compile(r"^N-?\d+\s*(.*?)\s*(?:\*\d*)?$", re.IGNORECASE)


def checksum(data: bytes) -> int:
    """XOR of all bytes of ``data`` (the part of a line before ``*``)."""
    cs = 0
    for byte in data:
        cs ^= byte
    return cs


def frame(number: int, command: str) -> bytes:
    """Frame one command for the wire: ``N<number> <command>*<cs>\\n``."""
    body = f"N{number} {command}".encode("ascii")
    return body + b"*" + str(checksum(body)).encode("ascii") + b"\n"


def reset_command(number: int) -> str:
    """The M110 command that sets the controller's line number to ``number``.

    Marlin reads the second N of ``N<k> M110 N<k>``, Repetier the first: giving
    both the same value makes them agree (docs/protocol.md, "Numbered lines").
    """
    return f"M110 N{number}"


def clean_line(raw: str | bytes, source: str = "line") -> str:
    """Return the command of one source line, or ``""`` when nothing is to be sent.

    Strips a ``;`` comment, surrounding whitespace and an existing ``N..*cs``
    frame, turns tabs into spaces, and refuses what cannot be framed safely:
    bytes that are not ASCII, and a ``*`` inside the command (the controller
    would read the rest of the line as a checksum). ``source`` names the line
    in error messages ("job.gcode:12").
    """
    if isinstance(raw, bytes):
        command_bytes = raw.split(b";", 1)[0]
        try:
            text = command_bytes.decode("ascii")
        except UnicodeDecodeError:
            raise JobError(f"{source}: the command is not ASCII text") from None
    else:
        text = raw.split(";", 1)[0]
        if not text.isascii():
            raise JobError(f"{source}: the command is not ASCII text")
    text = text.replace("\t", " ").strip()
    if not text:
        return ""
    if text[0] in "Nn":
        match = _EXISTING_FRAME.match(text)
        if match is not None:
            text = match.group(1)
    if "*" in text:
        raise JobError(f"{source}: '*' inside a command would be read as a checksum")
    if _CONTROL.search(text):
        raise JobError(f"{source}: the command holds control characters")
    return text
