"""What a session was opened with (``connect``'s choices, resolved), and the defaults the
session and its callers share."""

from __future__ import annotations

from dataclasses import dataclass, field

from repetrel_host.config import UserConfig
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.flow import FlowControl
from repetrel_host.session.planning import JobRequest

# Temperatures are asked for this often while idle (M105), unless the firmware reports them.
POLL_INTERVAL = 5.0
# A job whose link failed before its safe stop was confirmed ends once the safe stop went
# after a reconnect, or after this long without one (connect's reconnect_wait).
RECONNECT_WAIT = 30.0


@dataclass(frozen=True, slots=True)
class SessionSettings:
    """What a session was opened with."""

    port: str
    baud: int
    flow: FlowControl
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT
    reconnect: bool = True
    poll_interval: float | None = POLL_INTERVAL
    protocol: str = "reprap"
    user: UserConfig = field(default_factory=UserConfig)
    request: JobRequest = field(default_factory=JobRequest)
    checksum: bool = False  # Hyrel's link: the additive checksum on every line
    poll_while_printing: bool = False  # M105 between a job's lines, as OctoPrint does
    reconnect_wait: float = RECONNECT_WAIT
