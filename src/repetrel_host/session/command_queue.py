"""The session's commands on their way to the controller, oldest first: each sent through
the pump, awaited until its reply, failed when its connection ends; and the lock that lets
one caller's command (or a job's start) go at a time.

What a command and its reply are is :mod:`.commands`'; the pump's listener
(:mod:`.listener`) hands each its lines and its ok.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from collections.abc import Iterable

from repetrel_host.errors import HostError, LinkError
from repetrel_host.gcode.commands import command_word
from repetrel_host.session.commands import PendingCommand, Reply
from repetrel_host.session.wire import Wire


class CommandQueue:
    """The commands sent or queued that wait for their reply, and the lock of the session's
    commands (see the module)."""

    def __init__(self, wire: Wire, port: str) -> None:
        self._wire = wire
        self._port = port
        self.waiting: deque[PendingCommand] = deque()
        self.lock = asyncio.Lock()

    @property
    def busy(self) -> bool:
        """A caller's command holds the lock or waits for its reply."""
        return self.lock.locked() or bool(self.waiting)

    def send(self, command: str, own: bool = False) -> PendingCommand:
        """``command`` to the pump (``own``: the session's, not a caller's); what awaits
        its reply. A LinkError while unlinked."""
        pump = self._wire.pump
        if pump is None:
            raise LinkError(f"{self._port} is not connected")
        pending = PendingCommand(command, self._wire.loop.create_future(), own)
        self.waiting.append(pending)
        pump.command(command, pending)
        self._wire.drive()
        return pending

    async def ask(self, command: str, timeout: float | None, own: bool = False) -> Reply:
        """Send ``command`` and wait for its reply, at most ``timeout`` seconds."""
        pending = self.send(command, own)
        # Shielded: a timeout leaves it pending, so that its late lines are still its own.
        return await asyncio.wait_for(asyncio.shield(pending.future), timeout)

    async def poll(self, command: str, timeout: float) -> Reply | None:
        """``command`` as the session's own, unless a caller's command is sent or waits to
        be: then None (the poll stands aside)."""
        if self.busy:
            return None  # a caller's command goes first: no poll this time
        async with self.lock:
            return await self.ask(command, timeout, own=True)

    def urgent(self, command: str) -> None:
        """``command``'s word at once, unnumbered (M112, M108), as emergency parsers read it."""
        pump = self._wire.pump
        if pump is None:
            raise LinkError(f"{self._port} is not connected")
        pump.dialect.send_urgent(command_word(command))
        self._wire.drive()

    def fail(self, commands: Iterable[PendingCommand], error: HostError) -> None:
        """Those commands fail with ``error`` and wait no more."""
        for pending in list(commands):
            if not pending.future.done():
                pending.future.set_exception(error)
                pending.future.exception()  # retrieved: nobody may be awaiting it
            with contextlib.suppress(ValueError):
                self.waiting.remove(pending)
