"""One opened link as asyncio sees it, and the timings of opening it again.

The link (``repetrel_host.links``) opens with a :class:`LinkConnection`; it hands what
happens (opened, data, lost) to the session, which ignores a stale one (after an unplug).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

# After an unplug, the port is tried again after this long, doubling up to the maximum.
RECONNECT_FIRST = 0.25
RECONNECT_MAX = 5.0
# After a failure, the line must be this quiet (or this long, at most) before a new
# greeting: answers to the old lines still on their way must not be taken for its own.
QUIET = 0.3
QUIET_MAX = 5.0
LINK_LOST = "the serial link was lost (printer unplugged, or its port closed)"
# A closed session waits this long at most for its port to be free (what the transport
# still holds is written first: a controller that takes nothing holds it up).
PORT_FREE_WAIT = 5.0


class LinkConnection(asyncio.Protocol):
    """The asyncio side of one opened link: tells the session it opened, each piece of
    data received, and its loss, naming itself (a stale one is ignored)."""

    def __init__(
        self,
        opened: Callable[[LinkConnection], None],
        received: Callable[[LinkConnection, bytes], None],
        lost: Callable[[LinkConnection, Exception | None], None],
    ) -> None:
        self._opened = opened
        self._received = received
        self._lost = lost
        self.transport: asyncio.Transport | None = None
        # Set once the port's file is closed: a serial transport closes it in the
        # background, after what it still holds is written.
        self.closed = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self._opened(self)

    def data_received(self, data: bytes) -> None:
        self._received(self, data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed.set()
        self._lost(self, exc)
