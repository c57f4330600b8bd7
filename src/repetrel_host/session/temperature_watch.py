"""How a session keeps the controller's temperatures coming: the firmware's own reports
(``M155``, asked once a connection where it says it can) or, failing that, a poll every
``poll_interval`` seconds (Hyrel's status request where the link has one, else ``M105``);
and a first report at once, where none came yet to read a target set back in. What a report
says is read by the listener (:mod:`.listener`); this only makes them come."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable, Coroutine
from typing import Any, Protocol

from repetrel_host.errors import HostError
from repetrel_host.protocol.reports import Firmware, parse_temperatures
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.commands import Reply
from repetrel_host.session.events import Message, State
from repetrel_host.session.pump import Pump
from repetrel_host.session.settings import SessionSettings

FIRST_REPORT_WAIT = 2.0  # s: for the answer to Hyrel's status request (it comes at once)


class WatchedSession(Protocol):
    """What the watch needs of its session (the printer's inner side)."""

    @property
    def settings(self) -> SessionSettings: ...

    @property
    def state(self) -> State: ...

    @property
    def firmware(self) -> Firmware | None: ...

    @property
    def temperatures(self) -> dict[str, tuple[float, float | None]]:
        """The latest readings, by sensor."""
        ...

    @property
    def pump(self) -> Pump | None: ...

    def drive_pump(self) -> None:
        """Let the pump write what it can now."""

    def broadcast(self, event: Message) -> None:
        """To the session's subscribers and the running job's."""


class TemperatureWatch:
    """M155 where the firmware reports temperatures itself, else a poll (see the module)."""

    def __init__(self, session: WatchedSession, commands: CommandQueue) -> None:
        self._session = session
        self._commands = commands
        self.autoreport = False  # the controller reports temperatures itself (M155 took)
        self._asked: asyncio.Future[Reply] | None = None  # this connection's M155
        self._polling: asyncio.Task[None] | None = None

    def new_connection(self) -> None:
        """A greeting began: the firmware's reports are this connection's to ask for."""
        self.autoreport = False
        self._asked = None

    def ask_autoreport(self) -> asyncio.Future[Reply] | None:
        """M155 once a connection, where the firmware reports temperatures itself (and the
        session polls at all): the polls stop once the controller took it, whenever that
        is (mid-job too: it goes among the job's lines as a poll does, none of them)."""
        session = self._session
        interval = session.settings.poll_interval
        firmware = session.firmware
        if (
            self._asked is not None
            or not interval
            or firmware is None
            or not firmware.can("AUTOREPORT_TEMP")
            or session.pump is None
        ):
            return self._asked
        pending = self._commands.send(f"M155 S{max(1, math.ceil(interval))}", own=True)
        pending.future.add_done_callback(self._autoreporting)
        self._asked = pending.future
        return pending.future

    def late_autoreport(self, pump: Pump | None) -> None:
        """The controller said who it is only once the greeting was over: its M155 now, on
        ``pump``'s connection only."""
        if pump is not None and pump is self._session.pump:
            self.ask_autoreport()

    def _autoreporting(self, future: asyncio.Future[Reply]) -> None:
        if future.cancelled() or future.exception() is not None:
            return  # refused, or the connection ended: polled instead
        if future is not self._asked:
            return  # an earlier connection's
        self.autoreport = True
        if self._session.state is not State.CONNECTING:
            # What came while it waited is the job's (messages), not the M155's.
            for line in future.result().lines:
                if not parse_temperatures(line):
                    self._session.broadcast(Message(line))

    async def first_report(self, timeout: float | None) -> None:
        """Nothing reported yet to set a target in: a report now (Hyrel's status request,
        else M105), so that the target reads back as its command returns, as it does once
        there are readings."""
        session = self._session
        pump = session.pump
        wait = min(timeout or FIRST_REPORT_WAIT, FIRST_REPORT_WAIT)
        if pump is None or not pump.dialect.request_status():
            await self._commands.ask("M105", wait, own=True)
            return
        session.drive_pump()
        async with asyncio.timeout(wait):
            while not session.temperatures:
                await asyncio.sleep(0.02)

    def start_polling(
        self, spawn: Callable[[Coroutine[Any, Any, None]], asyncio.Task[None]]
    ) -> None:
        """Poll from now on, where the session polls at all (once a session)."""
        interval = self._session.settings.poll_interval
        if interval and self._polling is None:
            self._polling = spawn(self._poll(interval))

    async def _poll(self, interval: float) -> None:
        """Temperatures every ``interval`` seconds, unless the controller reports them
        itself (M155): while idle, and while a job prints or is paused when the session was
        opened with ``poll_while_printing``. Where the link has a status request that the
        controller answers at once, whatever it holds (Hyrel's 0x05), that; else M105,
        while no command waits: among a job's lines it is numbered as they are, but none of
        them (the job's count and recovery point never include it; a resend sends it again as
        itself; a stop drops it unsent)."""
        session = self._session
        while True:
            await asyncio.sleep(interval)
            pump = session.pump
            if self.autoreport or pump is None or not self._polls_now():
                continue
            if pump.dialect.request_status():
                session.drive_pump()
                continue
            if pump.controller_holds:
                continue
            with contextlib.suppress(HostError, TimeoutError):
                reply = await self._commands.poll("M105", interval * 2)
                if reply is None:
                    continue
                # What came while it waited is the job's (messages), not the poll's.
                for line in reply.lines:
                    if not parse_temperatures(line):
                        session.broadcast(Message(line))

    def _polls_now(self) -> bool:
        session = self._session
        state = session.state
        if state is State.READY:
            return True
        job = state is State.PRINTING or state is State.PAUSED
        return job and session.settings.poll_while_printing
