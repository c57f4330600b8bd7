"""The greeting of each connection: a fresh pump on the wire, whose dialect greets the
controller (M110 and a probe on the RepRap link, a ping on Hyrel's); its answer awaited;
then who the controller is (M115: :mod:`.identify`) and whether it reports its temperatures
itself (M155: :mod:`.temperature_watch`). A line that says who it is is taken whenever it
comes: a slow controller's answer still decides the profile, and so its safe stop.

When the greeting goes (at the opening, after a reset or a failure) is :mod:`.reconnect`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Protocol

from repetrel_host.errors import HostError
from repetrel_host.gcode.heaters import HeaterLog
from repetrel_host.protocol.dialects import create_dialect
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.reports import Firmware
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.events import Notice, PrinterEvent, State
from repetrel_host.session.identify import FIRMWARE_TIMEOUT, Identity, hotend_count
from repetrel_host.session.pump import Listener, Pump
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.temperature_watch import TemperatureWatch
from repetrel_host.session.wire import Wire


class GreetedSession(Protocol):
    """What the greeting needs of its session."""

    @property
    def settings(self) -> SessionSettings: ...

    @property
    def state(self) -> State: ...

    # How the controller answered the greeting (the session's ``probe``).
    probe: ProbeKind | None

    def publish(self, event: PrinterEvent) -> None:
        """To the session's subscribers."""


class Greeter:
    """Greets each connection's controller and keeps who it said it is (see the module)."""

    def __init__(
        self,
        session: GreetedSession,
        wire: Wire,
        commands: CommandQueue,
        listener: Listener,
        heaters: HeaterLog,
        temperature_watch: TemperatureWatch,
    ) -> None:
        self._session = session
        self._wire = wire
        self._commands = commands
        self._listener = listener
        self._heaters = heaters
        self._temperature_watch = temperature_watch
        self.identity = Identity()  # who the controller said it is (its firmware)
        self._ready: asyncio.Future[ProbeKind] | None = None  # the greeting under way

    @property
    def firmware(self) -> Firmware | None:
        """What the controller's M115 said it is (or its greeting), None when unknown."""
        return self.identity.firmware

    def expect(self) -> None:
        """A greeting begins: its answer is awaited from now on."""
        self._ready = self._wire.loop.create_future()

    def start_pump(self) -> None:
        """A fresh pump (and dialect) on the wire: its greeting goes out."""
        settings = self._session.settings
        dialect = create_dialect(
            settings.protocol,
            settings.flow,
            reply_timeout=settings.reply_timeout,
            checksum=settings.checksum,
        )
        self._wire.start(Pump(dialect, self._listener, self._heaters))

    async def greet(self) -> None:
        """Until the controller answered the greeting and said who it is."""
        ready = self._ready
        assert ready is not None
        self._session.probe = await ready
        await self._identify()

    def greeted(self, probe: ProbeKind, identity: str) -> None:
        """The controller answered the greeting (``identity``: what it said of itself)."""
        self.identity.greeting = identity
        ready = self._ready
        if ready is not None and not ready.done():
            ready.set_result(probe)

    def fail(self, error: HostError) -> None:
        """The greeting under way, if any, fails with ``error``."""
        ready = self._ready
        if ready is not None and not ready.done():
            ready.set_exception(error)
            ready.exception()  # retrieved: nobody may be awaiting it

    async def _identify(self) -> None:
        watch = self._temperature_watch
        watch.new_connection()
        await self.identity.ask(
            lambda command: self._commands.send(command, own=True).future, self._wire.loop
        )
        self._use_firmware()
        asked = watch.ask_autoreport()
        if asked is not None:
            with contextlib.suppress(TimeoutError):  # polled until it took (if ever)
                await asyncio.wait_for(asyncio.shield(asked), FIRMWARE_TIMEOUT)

    def heard(self, text: str) -> None:
        """A line that says which firmware this is (M115's ``FIRMWARE_NAME:`` and ``Cap:``
        lines), whichever command it came with or after: a slow controller's answer still
        decides, once it comes."""
        known = self.firmware
        found = self.identity.heard(text)
        if found is None:
            return
        session = self._session
        late = session.state is not State.CONNECTING and (known is None or known.name != found.name)
        self._use_firmware()
        # Its M155, if it has one, also when it said who it is only once a job was under
        # way: after this dispatch (not inside it), on this connection only.
        self._wire.loop.call_soon(self._temperature_watch.late_autoreport, self._wire.pump)
        if late:
            session.publish(Notice(f"the controller said who it is: {found.name}"))

    def _use_firmware(self) -> None:
        """What the pump takes from the firmware: its hotends, whether M108 ends a wait."""
        pump, firmware = self._wire.pump, self.firmware
        if pump is not None:
            pump.hotends = hotend_count(firmware)
            pump.breaks_waits = (
                firmware is not None
                and firmware.can("EMERGENCY_PARSER")
                and not pump.dialect.acks_say_received  # Hyrel's link aborts instead
            )
