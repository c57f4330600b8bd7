"""The RepRap dialect's probes: how one is written, and the one in flight.

A probe asks where the controller stands (see :mod:`~repetrel_host.protocol.dialects.reprap`):
a command probe is a numbered M105 that runs once, a checksum probe (for a controller whose
ok for M105 says nothing) a line that never runs.
"""

from __future__ import annotations

from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.framing import checksum
from repetrel_host.protocol.window import Transmission

# A checksum probe's checksum field. Valid checksums are 0..255; one changed character
# turns "9999" into 0, 9, 99 or a number above 255, so the probe's body is chosen with
# a checksum outside {0, 9, 99} and can never become valid.
_PING_CHECKSUM = b"9999"
_PING_UNSAFE = frozenset({0, 9, 99})
PROBE_COMMAND = "M105"  # harmless everywhere; its ok carries the temperatures


def ping_wire(number: int) -> bytes:
    """``N<number> M105 S<k>*9999``: refused by any controller that checks checksums."""
    for k in range(10):
        body = f"N{number} {PROBE_COMMAND} S{k}".encode("ascii")
        if checksum(body) not in _PING_UNSAFE:
            return body + b"*" + _PING_CHECKSUM + b"\n"
    raise AssertionError("unreachable: ten bodies cannot all have unsafe checksums")


class Probing:
    """The probe in flight, if any, and how many went unanswered."""

    __slots__ = ("current", "kind", "stray", "unanswered")

    def __init__(self, kind: ProbeKind) -> None:
        self.kind = kind
        self.current: Transmission | None = None
        self.unanswered = 0  # timeouts in a row
        # Answers of M105s no longer counted on the wire that may still come (a probe given
        # up for another, an M105 whose place a plain ok took): each an "ok T:..." that
        # confirms no line.
        self.stray = 0

    def answered(self) -> None:
        self.current = None
        self.unanswered = 0

    def superseded(self) -> None:
        """A resend request answers a probe too: its line is now just a stale transmission."""
        if self.current is not None:
            self.answered()
