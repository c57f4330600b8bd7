"""The simulated controller in this process: an asyncio transport, no pty, no subprocess.

For fast tests of everything above the link. The simulator runs on the event
loop's clock; its fault switches and ``!!DEBUG:`` lines work as on the pty fake
(``!!DEBUG:link_drop 1`` unplugs this transport, and the link opens again after
the given time).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from repetrel_host.errors import LinkError
from repetrel_host.fakes.hyrel_simulator import RX_BUFFER as HYREL_RX_BUFFER
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.fakes.simulator import ControllerSimulator


class SimController:
    """One simulated controller that outlives its connections, as a board outlives a cable."""

    def __init__(
        self, settings: ControllerSettings | None = None, protocol: str = "reprap"
    ) -> None:
        self.protocol = protocol
        self.settings = settings or (
            ControllerSettings(rx_buffer=HYREL_RX_BUFFER, banner=False)
            if protocol == "hyrel"
            else ControllerSettings()
        )
        self.simulator: ControllerSimulator | None = None
        self.unplugged_until = 0.0

    async def open(
        self, protocol_factory: Callable[[], asyncio.Protocol]
    ) -> tuple[asyncio.Transport, asyncio.Protocol]:
        loop = asyncio.get_running_loop()
        if loop.time() < self.unplugged_until:
            raise LinkError("cannot open sim: no such port (it is unplugged)")
        if self.simulator is None:
            kind = HyrelControllerSimulator if self.protocol == "hyrel" else ControllerSimulator
            self.simulator = kind(self.settings, now=loop.time())
        protocol = protocol_factory()
        return SimTransport(loop, protocol, self), protocol


class SimTransport(asyncio.Transport):
    """Bytes written go to the simulator; its replies come back as they are due."""

    def __init__(
        self, loop: asyncio.AbstractEventLoop, protocol: asyncio.Protocol, controller: SimController
    ) -> None:
        super().__init__()
        assert controller.simulator is not None
        self._loop = loop
        self._protocol = protocol
        self._controller = controller
        self._simulator = controller.simulator
        self._wire = bytearray()  # held back by a link that pushes back
        self._timer: asyncio.TimerHandle | asyncio.Handle | None = None
        self._closing = False
        self._stepping = False
        loop.call_soon(self._connect)

    def _connect(self) -> None:
        if not self._closing:
            self._protocol.connection_made(self)
            self._step()

    # --- asyncio.Transport ----------------------------------------------------

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if self._closing:
            return
        self._wire += data
        if self._stepping:
            return  # the step in progress takes it
        # Not at once: the protocol that writes must not be called back while it writes.
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self._loop.call_soon(self._step)

    def is_closing(self) -> bool:
        return self._closing

    def close(self) -> None:
        self._lose(None)

    def abort(self) -> None:
        self._lose(None)

    def get_write_buffer_size(self) -> int:
        return len(self._wire)

    # --- the simulator ----------------------------------------------------------

    def _step(self) -> None:
        self._timer = None
        simulator = self._simulator
        self._stepping = True
        try:
            while not self._closing:
                now = self._loop.time()
                simulator.receive_from(self._wire, now)
                simulator.advance(now)
                if simulator.link_drop_requested is not None:
                    seconds = simulator.link_drop_requested
                    simulator.link_drop_requested = None
                    simulator.unplug()
                    self._controller.unplugged_until = now + seconds
                    self._lose(LinkError("the simulated cable was pulled"))
                    return
                output = simulator.take_output(now)
                if not output:
                    break
                self._protocol.data_received(output)  # may write the answer: take it now
        finally:
            self._stepping = False
        if self._closing:
            return
        wakeup = simulator.next_wakeup()
        if self._wire:  # held back: try again shortly
            wakeup = now + 0.001 if wakeup is None else min(wakeup, now + 0.001)
        if wakeup is not None:
            self._timer = self._loop.call_at(max(wakeup, now), self._step)

    def _lose(self, exc: Exception | None) -> None:
        if self._closing:
            return
        self._closing = True
        if self._timer is not None:
            self._timer.cancel()
        self._loop.call_soon(self._protocol.connection_lost, exc)
