"""The asyncio pump between a serial link and :class:`HostProtocol`.

It holds no protocol logic: it feeds job lines into the core, writes what the
core wants written, hands received bytes to the core, maps the core's
deadline onto a timer, and reports events to an observer.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from enum import Enum

from repetrel_host.errors import ControllerError, HostError, JobError, LinkError, ProtocolError
from repetrel_host.job import JobLine
from repetrel_host.link import open_link
from repetrel_host.protocol import replies
from repetrel_host.protocol.host import (
    ControllerMessage,
    ControllerReady,
    Failed,
    HostProtocol,
    LineAcknowledged,
    ResendRequested,
)

log = logging.getLogger(__name__)

# After Ctrl-C, how long to wait for the lines already sent to be acknowledged.
CANCEL_DRAIN_TIMEOUT = 5.0


class Outcome(Enum):
    COMPLETED = "completed"
    CANCELLED = "cancelled"


class Observer:
    """Receives what happens during a stream; override what you need."""

    def on_ready(self) -> None: ...

    def on_acknowledged(self, line: JobLine) -> None: ...

    def on_resend(self, line: JobLine) -> None: ...

    def on_message(self, text: str, reply: replies.Reply) -> None: ...


@dataclass(frozen=True, slots=True)
class Summary:
    outcome: Outcome
    lines: int  # job lines acknowledged
    seconds: float
    resends: int
    retransmissions: int


class Sender(asyncio.Protocol):
    """Streams ``lines`` through ``core`` over one asyncio transport."""

    def __init__(
        self, core: HostProtocol, lines: Iterable[JobLine], observer: Observer | None = None
    ) -> None:
        self.core = core
        self.observer = observer or Observer()
        self._lines: Iterator[JobLine] = iter(lines)
        self._lines_exhausted = False
        self._job_error: JobError | None = None
        self._cancelled = False
        self._acknowledged = 0  # job lines acknowledged: the highest index seen
        self._loop = asyncio.get_running_loop()
        self._done: asyncio.Future[Summary] = self._loop.create_future()
        self._transport: asyncio.Transport | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at: float | None = None
        self._started_at = 0.0

    # --- asyncio.Protocol ---------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        self._started_at = self._loop.time()
        self.core.start(self._started_at)
        self._pump()

    def data_received(self, data: bytes) -> None:
        log.debug("received %r", data)
        self.core.receive_data(data, self._loop.time())
        self._pump()

    def connection_lost(self, exc: Exception | None) -> None:
        log.debug("connection lost: %s", exc)
        self._finish(LinkError("the serial link was lost (printer unplugged, or its port closed)"))

    # --- control ------------------------------------------------------------

    async def wait(self) -> Summary:
        """Wait until the job completed, was cancelled, or failed (raises a HostError)."""
        return await self._done

    def cancel(self) -> None:
        """Stop feeding the job; finish once what is already on the wire is answered."""
        if self._cancelled or self._done.done():
            return
        self._cancelled = True
        self.core.cancel_pending()
        self._loop.call_later(CANCEL_DRAIN_TIMEOUT, self._finish_cancel)
        self._pump()

    # --- pump ---------------------------------------------------------------

    def _pump(self) -> None:
        if self._done.done():
            return
        core = self.core
        while core.wants_lines and not self._lines_exhausted and not self._cancelled:
            try:
                line = next(self._lines)
            except StopIteration:
                self._lines_exhausted = True
                break
            except JobError as exc:
                # Send no more, but let what is on the wire be acknowledged first.
                self._job_error = exc
                self._lines_exhausted = True
                break
            core.send(line.command, line)
        now = self._loop.time()
        data = core.data_to_send(now)
        if data and self._transport is not None:
            log.debug("sending %r", data)
            self._transport.write(data)
        self._dispatch_events()
        if self._done.done():
            return
        if core.is_done and (self._lines_exhausted or self._cancelled):
            if self._job_error is not None:
                self._finish(self._job_error)
            else:
                self._finish(Outcome.CANCELLED if self._cancelled else Outcome.COMPLETED)
            return
        self._arm_timer(core.next_deadline())

    def _dispatch_events(self) -> None:
        observer = self.observer
        while (event := self.core.next_event()) is not None:
            if isinstance(event, LineAcknowledged):
                line = event.tag
                # After a resend the controller may acknowledge a line again; count it once.
                if isinstance(line, JobLine) and line.index > self._acknowledged:
                    self._acknowledged = line.index
                    observer.on_acknowledged(line)
            elif isinstance(event, ResendRequested):
                if isinstance(event.tag, JobLine):
                    observer.on_resend(event.tag)
            elif isinstance(event, ControllerMessage):
                observer.on_message(event.text, event.reply)
            elif isinstance(event, ControllerReady):
                observer.on_ready()
            elif isinstance(event, Failed):
                self._finish(_failure_error(event))
                return

    def _arm_timer(self, deadline: float | None) -> None:
        if deadline == self._timer_at:
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._timer_at = deadline
        if deadline is not None:
            self._timer = self._loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        self._timer_at = None
        self.core.handle_timeout(self._loop.time())
        self._pump()

    def _finish_cancel(self) -> None:
        self._finish(Outcome.CANCELLED)

    def _finish(self, result: Outcome | HostError) -> None:
        if self._done.done():
            return
        if self._timer is not None:
            self._timer.cancel()
        if isinstance(result, HostError):
            self._done.set_exception(result)
            return
        stats = self.core.stats
        self._done.set_result(
            Summary(
                outcome=result,
                lines=self._acknowledged,
                seconds=self._loop.time() - self._started_at,
                resends=stats.resend_requests,
                retransmissions=stats.retransmissions,
            )
        )


def _failure_error(event: Failed) -> HostError:
    if event.kind == "controller":
        return ControllerError(event.reason)
    if event.kind == "timeout":
        return LinkError(event.reason)
    return ProtocolError(event.reason)


async def stream(
    port: str,
    baudrate: int,
    core: HostProtocol,
    lines: Iterable[JobLine],
    observer: Observer | None = None,
    on_open: Callable[[Sender], None] | None = None,
) -> Summary:
    """Open ``port``, stream ``lines``, close the port; the one call most users need.

    ``on_open`` receives the :class:`Sender` once the port is open (to cancel it).
    """
    transport, protocol = await open_link(port, baudrate, lambda: Sender(core, lines, observer))
    assert isinstance(protocol, Sender)
    if on_open is not None:
        on_open(protocol)
    try:
        return await protocol.wait()
    finally:
        transport.close()
