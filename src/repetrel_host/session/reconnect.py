"""The link's connections over a session's life: opened and greeted (:mod:`.greeting`),
with the safe stop still owed first (:mod:`.owed`); a vanished port reopened with backoff;
after a reset or a failure of the dialect, the controller greeted again on the same port
once the line is quiet; the connection ended when the session closes. A connection's end
fails what waits on it: the job names its last line, the greeting and the commands fail.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Coroutine
from typing import Any, Protocol

from repetrel_host.errors import HostError, LinkError
from repetrel_host.links import Link
from repetrel_host.protocol.events import DialectFailed, FailureKind
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.connection import (
    LINK_LOST,
    QUIET,
    QUIET_MAX,
    RECONNECT_FIRST,
    RECONNECT_MAX,
    LinkConnection,
)
from repetrel_host.session.events import Notice, PrinterEvent, State
from repetrel_host.session.greeting import Greeter
from repetrel_host.session.owed import OwedStopSender
from repetrel_host.session.pump import failure_error
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.temperature_watch import TemperatureWatch
from repetrel_host.session.wire import Wire

# The session's log, as before its parts had modules of their own.
log = logging.getLogger("repetrel_host.session.printer")


class ReconnectingSession(Protocol):
    """What opening and reopening the link needs of its session."""

    @property
    def settings(self) -> SessionSettings: ...

    @property
    def port(self) -> str: ...

    @property
    def state(self) -> State: ...

    def set_state(self, state: State, reason: str) -> None:
        """The session's state is now ``state``."""

    def spawn(self, coroutine: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        """Run ``coroutine`` as one of the session's tasks."""
        ...

    def publish(self, event: PrinterEvent) -> None:
        """To the session's subscribers."""


class Reconnector:
    """Opens the session's link, and greets or opens it again (see the module)."""

    def __init__(
        self,
        session: ReconnectingSession,
        link: Link,
        wire: Wire,
        greeter: Greeter,
        owing: OwedStopSender,
        commands: CommandQueue,
        temperature_watch: TemperatureWatch,
    ) -> None:
        self._session = session
        self._link = link
        self._wire = wire
        self._greeter = greeter
        self._owing = owing
        self._commands = commands
        self._temperature_watch = temperature_watch
        self.closing = False  # the session closes: its link is never taken up again
        self._reconnecting: asyncio.Task[None] | None = None

    @property
    def reconnects(self) -> bool:
        """A lost or failed link is taken up again: the session was opened to, and it is
        not closing."""
        return self._session.settings.reconnect and not self.closing

    async def open(self) -> None:
        """Open the link and greet the controller: READY, or a HostError."""
        session = self._session
        session.set_state(State.CONNECTING, f"opening {session.port}")
        self._greeter.expect()
        await self._link.open(lambda: LinkConnection(self._opened, self._wire.received, self._lost))
        await self._greet()

    async def _greet(self) -> None:
        try:
            await self._greeter.greet()
        except BaseException as exc:
            # Nothing of this connection may outlive it: its pump, its commands (the
            # next connection's replies must not be taken for theirs).
            error = exc if isinstance(exc, HostError) else LinkError("the greeting stopped")
            self.end(error)
            self._wire.drop_connection()
            raise
        await self._owing.send()
        self._session.set_state(State.READY, "greeted")
        self._temperature_watch.start_polling(self._session.spawn)

    def _opened(self, connection: LinkConnection) -> None:
        if self.closing:
            if connection.transport is not None:
                connection.transport.close()
            return
        self._wire.connection = connection
        if self._owing.release():
            self._session.spawn(self._start_pump_when_quiet())
        else:
            self._greeter.start_pump()

    async def _until_quiet(self) -> None:
        """Until the controller has said nothing for QUIET s (at most QUIET_MAX): late
        answers to what went before must not be taken for the greeting's."""
        loop = self._wire.loop
        quiet_since = loop.time()
        while loop.time() - quiet_since < QUIET_MAX:
            wait = self._wire.last_data_at + QUIET - loop.time()
            if wait <= 0:
                break
            await asyncio.sleep(wait)

    async def _start_pump_when_quiet(self) -> None:
        self._wire.last_data_at = self._wire.loop.time()
        await self._until_quiet()
        if self._wire.connection is not None and not self.closing and self._wire.pump is None:
            self._greeter.start_pump()

    async def _regreet(self, reason: str) -> None:
        """Greet again on the same port (after a reset, or a failure)."""
        if self._wire.connection is None or self.closing:
            return
        self._session.set_state(State.CONNECTING, reason)
        # Late answers to what went before must not be taken for the new greeting's.
        await self._until_quiet()
        if self._wire.connection is None or self.closing:
            return
        if self._owing.release():
            self._wire.last_data_at = self._wire.loop.time()
            await self._until_quiet()
            if self._wire.connection is None or self.closing:
                return
        self._greeter.expect()
        self._greeter.start_pump()
        try:
            await self._greet()
        except HostError as exc:
            self._session.set_state(State.DISCONNECTED, str(exc))
            if self.reconnects and self._reconnecting is None:
                self._reconnecting = self._session.spawn(self._reconnect())

    async def _reconnect(self) -> None:
        delay = RECONNECT_FIRST
        while not self.closing:
            await asyncio.sleep(delay)
            try:
                await self.open()
            except Exception as exc:  # whatever the port did, try again later
                log.debug("reconnect: %r", exc)
                self._session.set_state(State.DISCONNECTED, str(exc))
                delay = min(delay * 2, RECONNECT_MAX)
                continue
            break
        self._reconnecting = None

    def _lost(self, connection: LinkConnection, exc: Exception | None) -> None:
        if connection is not self._wire.connection:
            return
        log.debug("connection lost: %s", exc)
        self._wire.connection = None
        self.end(LinkError(LINK_LOST))
        if self.closing:
            return
        self._session.set_state(State.DISCONNECTED, LINK_LOST)
        if self._session.settings.reconnect and self._reconnecting is None:
            self._reconnecting = self._session.spawn(self._reconnect())

    def failed(self, failure: DialectFailed) -> None:
        """The dialect stopped: the greeting fails, or the connection ends (and is greeted
        again, where the session reconnects)."""
        error = failure_error(failure)
        if failure.kind is FailureKind.NO_ANSWER:
            error = LinkError(self._no_answer(failure.reason))
        session = self._session
        if session.state is State.CONNECTING:
            # The greeting (or its M115) failed: whoever greets says why.
            self._fail_waiters(error)
            return
        if failure.kind is FailureKind.RESET:
            session.publish(Notice("the controller reset; greeting it again"))
        self.end(error)
        if self.reconnects:
            session.spawn(self._regreet(failure.reason))
        else:
            # Once what the pump has yet to write (an abort) went: it writes after this.
            self._wire.loop.call_soon(self._wire.drop_connection)
            session.set_state(State.DISCONNECTED, failure.reason)

    def _no_answer(self, reason: str) -> str:
        """The greeting went unanswered: one sentence with the port, the baud rate, and
        what most likely stands in the way."""
        settings = self._session.settings
        causes = "the wrong port, the wrong baud rate, or the board still booting"
        if settings.protocol == "hyrel":
            causes = (
                "the wrong port, the wrong baud rate, the board still booting, or a "
                "controller that does not speak Hyrel's own link"
            )
        return f"{self._session.port} at {settings.baud} baud: {reason}; likely {causes}"

    def end(self, error: HostError) -> None:
        """The pump is gone: the job fails naming its last line, commands fail."""
        pump = self._wire.stop()
        if pump is not None and pump.run is not None:
            pump.abort(self._wire.loop.time(), pump.run.naming_where(error))
        self._fail_waiters(error)

    def _fail_waiters(self, error: HostError) -> None:
        """The greeting under way and every command awaiting its reply fail with ``error``."""
        self._greeter.fail(error)
        self._commands.fail(self._commands.waiting, error)
