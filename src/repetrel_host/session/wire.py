"""The bytes between a printer's pump and its link: what goes out (to the port, to the running
job's wire log in the history, to the taps and the tail; each line, as it first goes, to the
line taps), what comes in (to the pump), and the pump's timer. A
:class:`~repetrel_host.session.printer.Printer` holds one; its parts decide when the
connection and the pump change (a greeting, a reconnect, a failure: :mod:`.reconnect`), and
the wire carries bytes between them meanwhile."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Callable
from typing import BinaryIO

from repetrel_host.session.commands import PendingCommand
from repetrel_host.session.connection import PORT_FREE_WAIT, LinkConnection
from repetrel_host.session.pump import Pump

log = logging.getLogger("repetrel_host.session.printer")  # the printer's, as before


class Wire:
    """One printer's connection of the moment, its pump of the moment, and the bytes between."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.connection: LinkConnection | None = None
        self.pump: Pump | None = None  # none between a failure and the next greeting
        self.log: BinaryIO | None = None  # the running job's stream in the history
        self.taps: list[Callable[[bool, bytes], None]] = []
        self._line_taps: list[Callable[[str, bool], None]] = []
        # The wire's latest pieces, (sent, data), while a log reads them now and then (the
        # push socket's terminal): one append a write or read, nothing more, and nothing at
        # all while it is None. Bounded: a reader that falls behind loses the oldest.
        self.tail: deque[tuple[bool, bytes]] | None = None
        self.last_data_at = 0.0  # when the controller last said anything
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None

    def start(self, pump: Pump) -> None:
        """Make ``pump`` the connection's: its greeting goes out, its timer is armed."""
        self.pump = pump
        if self._line_taps:
            pump.dialect.on_first_send = self._first_send
        self.write(pump.start(self.loop.time()))
        self._arm_timer(pump.deadline)

    def stop(self) -> Pump | None:
        """Take the pump off the wire (its timer with it) and return it."""
        pump, self.pump = self.pump, None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = self._timer_at = None
        return pump

    def tap_lines(self, callback: Callable[[str, bool], None]) -> Callable[[], None]:
        """Call ``callback(command, own)`` for each line as it first goes (see
        :meth:`Printer.tap_lines <repetrel_host.session.printer.Printer.tap_lines>`);
        returns what removes the tap."""
        self._line_taps.append(callback)
        if self.pump is not None:
            self.pump.dialect.on_first_send = self._first_send
        return lambda: self._line_taps.remove(callback)

    def _first_send(self, command: str, tag: object, own: bool, _number: int | None) -> None:
        own = own or (isinstance(tag, PendingCommand) and tag.own)
        for tap in self._line_taps:
            tap(command, own)

    def drop_connection(self) -> None:
        """Close the connection of the moment (the link itself stays the printer's)."""
        connection, self.connection = self.connection, None
        if connection is not None and connection.transport is not None:
            connection.transport.close()

    async def close_connection(self) -> None:
        """Close the connection of the moment and return once its port is free: whoever
        opens it next (a connect, another program) must not find it busy."""
        connection = self.connection
        self.drop_connection()
        if connection is None or connection.transport is None:
            return
        try:
            await asyncio.wait_for(connection.closed.wait(), PORT_FREE_WAIT)
        except TimeoutError:
            log.warning(
                "the port is not closed yet: the controller has not taken what was sent to it"
            )

    def close_log(self) -> None:
        if self.log is not None:
            self.log.close()
            self.log = None

    def received(self, connection: LinkConnection, data: bytes) -> None:
        """What ``connection`` read: to the taps, the tail and the pump (an old
        connection's late bytes are dropped)."""
        if connection is not self.connection:
            return
        log.debug("received %r", data)
        self._show(False, data)
        self.last_data_at = now = self.loop.time()
        pump = self.pump
        if pump is not None:  # none between a failure and the next greeting: let it drain
            pump.receive(data, now)
            self.drive()

    def write(self, data: bytes) -> None:
        connection = self.connection
        if not data or connection is None or connection.transport is None:
            return
        log.debug("sending %r", data)
        self._show(True, data)
        wire_log = self.log
        if wire_log is not None:  # first: the history is never behind the wire
            written = wire_log.write(data)  # one write(2) a call (unbuffered)
            while written < len(data):  # a short one (a signal): the rest, or ENOSPC raised
                written += wire_log.write(data[written:]) or len(data) - written
        connection.transport.write(data)

    def _show(self, sent: bool, data: bytes) -> None:
        """To the taps and the tail, as it goes (``sent``: written, else read)."""
        for tap in self.taps:
            tap(sent, data)
        tail = self.tail
        if tail is not None:
            tail.append((sent, data))

    def drive(self) -> None:
        """Let the pump write what it can now (lines, an urgent byte), and re-arm its timer."""
        pump = self.pump
        if pump is None:
            return
        self.write(pump.poke(self.loop.time()))
        if self.pump is pump:  # the write may have ended the connection, and the pump
            self._arm_timer(pump.deadline)

    def _arm_timer(self, deadline: float | None) -> None:
        # A timer already due no later stays: firing early is harmless (the pump checks
        # its own deadline and is poked again), and most lines only push it back.
        armed = self._timer_at
        if armed is not None and (deadline is None or armed <= deadline):
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_at = deadline
        if deadline is not None:
            self._timer = self.loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = self._timer_at = None
        pump = self.pump
        if pump is not None:
            pump.timeout(self.loop.time())
            self.drive()
