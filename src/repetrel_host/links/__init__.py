"""From a port string to a link: the one place that maps a name to a transport.

As python-can's interface registry makes "real or simulated" a configuration
value, a port here is one of:

- ``fake``: the built-in fake controller in a subprocess on a fresh pty, started
  with the first connection and stopped with the session;
- ``sim``: the simulated controller in this process (no pty, no subprocess), for
  fast tests;
- anything else: a serial device (``/dev/ttyUSB0``) or a pyserial URL
  (``socket://host:port``, ``rfc2217://host:port``).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from repetrel_host.errors import LinkError
from repetrel_host.links.ports import AUTO_PORT

if TYPE_CHECKING:
    from repetrel_host.fakes.settings import ControllerSettings

FAKE_PORT = "fake"
SIM_PORT = "sim"

ProtocolFactory = Callable[[], asyncio.Protocol]


class Link(Protocol):
    """Where a session's bytes go; opened again after an unplug."""

    port: str  # as the user gave it
    device: str  # what is opened: a path, a URL, or "sim"

    async def open(self, factory: ProtocolFactory) -> tuple[asyncio.Transport, asyncio.Protocol]:
        """Open the port (again) and connect a new protocol to it."""

    def close(self) -> None:
        """Release what the link started (the fake's process)."""


class SerialLink:
    """A serial device or a pyserial URL."""

    def __init__(self, port: str, baudrate: int) -> None:
        self.port = self.device = port
        self.baudrate = baudrate

    async def open(self, factory: ProtocolFactory) -> tuple[asyncio.Transport, asyncio.Protocol]:
        from repetrel_host.links.serial import open_serial

        folder = not_a_port(self.device)
        if folder is not None:  # pyserial's words: "[Errno 21] ...: [Errno 21] Is a directory"
            raise LinkError(folder)
        return await open_serial(self.device, self.baudrate, factory)

    def close(self) -> None:
        pass


class FakeLink:
    """The built-in fake controller on a pty, its link running at the chosen baud rate."""

    def __init__(
        self,
        baudrate: int,
        log_path: Path | None = None,
        extra_args: Sequence[str] = (),
        protocol: str = "reprap",
    ) -> None:
        from repetrel_host.fakes.fake_controller import BuiltInFake

        self.port = FAKE_PORT
        self.baudrate = baudrate
        # 10 bits on the wire per byte, and a millisecond each way, as a USB adapter.
        args = ["--bandwidth", str(baudrate / 10), "--latency", "0.001", *extra_args]
        args += ["--protocol", protocol]  # the fake speaks what the session speaks
        # Its control channel on stdin also ends it should this process die.
        self.fake = BuiltInFake(log_path, args, control=True)
        self.device = ""

    @property
    def log_path(self) -> Path | None:
        """The fake's list of executed commands (None: it keeps none, as without fake_log)."""
        return self.fake.log_path

    async def open(self, factory: ProtocolFactory) -> tuple[asyncio.Transport, asyncio.Protocol]:
        from repetrel_host.links.serial import open_serial

        if not self.device:
            loop = asyncio.get_running_loop()
            self.device = await loop.run_in_executor(None, self.fake.start)
        return await open_serial(self.device, self.baudrate, factory)

    def close(self) -> None:
        self.fake.stop()


class SimLink:
    """The simulated controller, in this process."""

    def __init__(
        self, settings: ControllerSettings | None = None, protocol: str = "reprap"
    ) -> None:
        from repetrel_host.links.sim import SimController

        self.port = self.device = SIM_PORT
        self.controller = SimController(settings, protocol)

    async def open(self, factory: ProtocolFactory) -> tuple[asyncio.Transport, asyncio.Protocol]:
        return await self.controller.open(factory)

    def close(self) -> None:
        pass


def make_link(
    port: str,
    baudrate: int,
    *,
    fake_log: Path | None = None,
    fake_args: Sequence[str] = (),
    sim: ControllerSettings | None = None,
    protocol: str = "reprap",
) -> Link:
    """The link for ``port`` (see the module's docstring); the fake and the simulator
    speak ``protocol``."""
    if port == FAKE_PORT:
        return FakeLink(baudrate, fake_log, fake_args, protocol)
    if port == SIM_PORT:
        return SimLink(sim, protocol)
    return SerialLink(port, baudrate)


def not_a_port(port: str) -> str | None:
    """Why ``port`` can never open, in one sentence: it names a folder (``/dev/serial/by-id``
    rather than a device in it). None for any other port: a device not there yet may be
    plugged in later, and opening says what else is wrong."""
    if port in (FAKE_PORT, SIM_PORT, AUTO_PORT) or "://" in port or not os.path.isdir(port):
        return None
    return f"cannot open {port}: it is a folder, not a serial port"
