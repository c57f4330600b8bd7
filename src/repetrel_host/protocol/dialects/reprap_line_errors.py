"""What a RepRap controller's error line says about the resend request after it.

Pure rules, read off the replies alone: the line a Marlin line error names as the last it
accepted, and whether it refused a line for its number or for its checksum. The dialect
(:mod:`~repetrel_host.protocol.dialects.reprap`) weighs them against what it sent.
"""

from __future__ import annotations

import re

from repetrel_host.protocol import replies

_LAST_LINE = re.compile(r"last\s*line:?\s*(-?\d+)", re.IGNORECASE)


def stated_last_line(reply: replies.Reply | None) -> int | None:
    """The "Last Line: L" of a Marlin line error just before a resend request."""
    if isinstance(reply, replies.Error) and reply.line_error:
        match = _LAST_LINE.search(reply.text)
        if match is not None:
            return int(match.group(1))
    return None


def is_number_error(reply: replies.Reply | None) -> bool:
    """A line refused for its number ("Line Number is not Last Line Number+1")."""
    return (
        isinstance(reply, replies.Error)
        and reply.line_error
        and "checksum" not in reply.text.lower()
    )


def is_checksum_error(reply: replies.Reply | None) -> bool:
    """A line refused for its checksum ("checksum mismatch")."""
    return (
        isinstance(reply, replies.Error) and reply.line_error and "checksum" in reply.text.lower()
    )
