"""What the controller is: its M115 answer (``FIRMWARE_NAME:``, ``Cap:`` lines), asked for
as it is greeted, and taken whenever it comes (a slow controller's answer still decides the
profile, and so its safe stop).

The session's greeting (:mod:`.greeting`) keeps one :class:`Identity` and hands it every
line that may say who the controller is.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from repetrel_host.protocol.reports import Firmware
from repetrel_host.session.commands import Reply

# M115 is asked again when its answer names no firmware (garbled), and waited for this
# long in all: a slow controller's answer decides the profile (and so its safe stop), not
# a short timeout. An answer that comes later still does.
FIRMWARE_TIMEOUT = 2.0  # for the M155 that follows it
FIRMWARE_PATIENCE = 12.0
FIRMWARE_ATTEMPTS = 3


def hotend_count(firmware: Firmware | None) -> int:
    """The hotends the firmware says it drives (``EXTRUDER_COUNT``), at least one."""
    count = firmware.fields.get("EXTRUDER_COUNT", "1") if firmware else "1"
    return int(count) if count.isdigit() and int(count) > 0 else 1


class Identity:
    """Who the controller said it is, on this connection: its firmware, from M115's answer
    (or, without one, from what it said as it was greeted)."""

    def __init__(self) -> None:
        self.firmware: Firmware | None = None
        self.greeting = ""  # what the controller said of itself as it was greeted
        self._lines: list[str] = []  # its M115 lines, whatever command they came with
        self._heard = asyncio.Event()

    def heard(self, text: str) -> Firmware | None:
        """A line that says which firmware this is (M115's ``FIRMWARE_NAME:`` and ``Cap:``
        lines), whichever command it came with or after: the firmware, when it is new or
        says more than the one known (None otherwise)."""
        self._lines.append(text)
        found = Firmware.parse(self._lines)
        known = self.firmware
        if found is None or (
            known is not None
            and (known.fields, known.capabilities) == (found.fields, found.capabilities)
        ):
            return None
        self.firmware = found
        self._heard.set()
        return found

    async def ask(
        self, send: Callable[[str], asyncio.Future[Reply]], loop: asyncio.AbstractEventLoop
    ) -> None:
        """Ask M115 (through ``send``) until an answer names the firmware, up to
        FIRMWARE_ATTEMPTS times within FIRMWARE_PATIENCE seconds; else the greeting's."""
        self.firmware = None
        self._lines = []
        self._heard.clear()
        # Without an answer to M115, the greeting's own (Hyrel's ping: ">Hy: ...").
        greeting = Firmware.parse([f"FIRMWARE_NAME:{self.greeting}"] if self.greeting else [])
        deadline = loop.time() + FIRMWARE_PATIENCE
        for _ in range(FIRMWARE_ATTEMPTS):
            pending = send("M115")
            with contextlib.suppress(TimeoutError):
                reply = await asyncio.wait_for(
                    asyncio.shield(pending), max(0.0, deadline - loop.time())
                )
                self.firmware = Firmware.parse([*reply.lines, reply.ok_line]) or self.firmware
                if self.firmware is not None:
                    break
                # Confirmed, its answer perhaps still to come (a probe found the line taken
                # before it ran), or garbled: a while for it, then ask again.
                left = min(FIRMWARE_TIMEOUT, deadline - loop.time())
                await asyncio.wait_for(self._heard.wait(), max(0.0, left))
            if self.firmware is not None or loop.time() >= deadline:
                break
        if self.firmware is None:
            # Not yet: an answer that comes later still decides (see heard).
            self.firmware = greeting  # or none: it does not say who it is
