"""The asyncio pump between a serial link and :class:`HostProtocol`.

It holds no protocol logic: it feeds job lines into the core, writes what the
core wants written (and copies it to the print history), hands received bytes
to the core, maps the core's deadline onto a timer, runs host actions (M0,
M792...) once everything before them is acknowledged, and reports events to an
observer.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import BinaryIO

from repetrel_host.errors import ControllerError, HostError, JobError, LinkError, ProtocolError
from repetrel_host.job import HostAction, JobItem, JobLine
from repetrel_host.link import open_link
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Dialect as HostProtocol
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    Failed,
    FailureKind,
    LineAcknowledged,
    Notice,
    ResendRequested,
)

log = logging.getLogger(__name__)

# After a cancel, how long the safe-stop lines (and those already sent) may take to be
# acknowledged: a heater's M109 ahead of them can hold the queue.
CANCEL_DRAIN_TIMEOUT = 30.0
SAFE_STOP_SOURCE = "safe stop"


class Outcome(Enum):
    COMPLETED = "completed"
    CANCELLED = "cancelled"


class Observer:
    """Receives what happens during a stream; override what you need."""

    def on_ready(self) -> None: ...

    def on_acknowledged(self, line: JobLine) -> None: ...

    def on_resend(self, line: JobLine) -> None: ...

    def on_message(self, text: str, reply: replies.Reply) -> None: ...

    def on_notice(self, text: str) -> None: ...

    async def perform(self, action: HostAction) -> bool:
        """Carry out a host action; return False to stop the job (with the safe stop)."""
        return True


@dataclass(frozen=True, slots=True)
class Summary:
    outcome: Outcome
    lines: int  # job lines acknowledged
    seconds: float
    resends: int
    retransmissions: int


class Sender(asyncio.Protocol):
    """Streams job ``items`` through ``core`` over one asyncio transport."""

    def __init__(
        self,
        core: HostProtocol,
        items: Iterable[JobItem],
        observer: Observer | None = None,
        *,
        safe_stop: Sequence[str] = (),
        wire_log: BinaryIO | None = None,
    ) -> None:
        self.core = core
        self.observer = observer or Observer()
        self.safe_stop = list(safe_stop)
        self._wire_log = wire_log
        self._items: Iterator[JobItem] = iter(items)
        self._items_exhausted = False
        self._error: HostError | None = None  # reported once the safe stop is acknowledged
        self._stopping = False  # no more job lines: cancelled, refused or failed
        self._cancelled = False
        self._barrier: HostAction | None = None  # waiting for every earlier line's ok
        self._action_task: asyncio.Task[bool] | None = None
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
        """Stop the job: send the safe-stop sequence ahead of anything not yet sent.

        A second call stops at once, without waiting for acknowledgements.
        """
        if self._done.done():
            return
        if self._cancelled:
            self._finish(Outcome.CANCELLED)
            return
        self._cancelled = True
        self._stop_feeding()
        self._loop.call_later(CANCEL_DRAIN_TIMEOUT, self._finish, Outcome.CANCELLED)
        self._pump()

    # --- pump ---------------------------------------------------------------

    def _pump(self) -> None:
        if self._done.done():
            return
        core = self.core
        self._feed()
        data = core.data_to_send(self._loop.time())
        if data and self._transport is not None:
            log.debug("sending %r", data)
            self._transport.write(data)
            if self._wire_log is not None:
                self._wire_log.write(data)
        # Read the next lines now, while the controller works, not once its ok is here.
        self._feed()
        self._dispatch_events()
        if self._done.done() or not core.is_done:
            self._arm_timer(core.next_deadline())
            return
        if self._barrier is not None and self._action_task is None:
            self._action_task = self._loop.create_task(self.observer.perform(self._barrier))
            self._action_task.add_done_callback(self._action_done)
        elif self._stopping:
            self._finish(self._error or Outcome.CANCELLED)
        elif self._items_exhausted and self._error is not None:
            self._stop_feeding()
            self._pump()
            return
        elif self._items_exhausted:
            self._finish(Outcome.COMPLETED)
        self._arm_timer(core.next_deadline())

    def _feed(self) -> None:
        """Queue job lines while the core wants them, up to a host action."""
        core = self.core
        while core.wants_lines and not self._stopping and self._barrier is None:
            try:
                item = next(self._items)
            except StopIteration:
                self._items_exhausted = True
                break
            except JobError as exc:
                # A line that cannot go: the lines before it still do, then the safe stop.
                self._error = exc
                self._items_exhausted = True
                break
            if isinstance(item, HostAction):
                self._barrier = item
            else:
                core.send(item.command, item)
        if self._barrier is not None or self._items_exhausted or self._stopping:
            core.request_sync()  # nothing more for now: have the controller confirm it all

    def _action_done(self, task: asyncio.Task[bool]) -> None:
        self._action_task = None
        self._barrier = None
        if task.cancelled():
            return
        error = task.exception()
        if isinstance(error, HostError):
            self._error = error
            self._stop_feeding()
        elif error is not None:  # a bug: surface it rather than hang
            self._done.set_exception(error)
            return
        elif not task.result():
            self._cancelled = True
            self._stop_feeding()
        self._pump()

    def _stop_feeding(self) -> None:
        """No more job lines: drop what is queued, cancel a host action, queue the safe stop."""
        if self._stopping:
            return
        self._stopping = True
        self._barrier = None
        if self._action_task is not None:
            self._action_task.cancel()
            self._action_task = None
        self.core.cancel_pending()
        for command in self.safe_stop:
            self.core.send(command, JobLine(0, 0, command, 0, SAFE_STOP_SOURCE))

    def _dispatch_events(self) -> None:
        observer = self.observer
        while (event := self.core.next_event()) is not None:
            if isinstance(event, LineAcknowledged):
                line = event.tag
                if isinstance(line, JobLine):
                    if line.index > self._acknowledged:
                        self._acknowledged = line.index
                    observer.on_acknowledged(line)
            elif isinstance(event, ResendRequested):
                if isinstance(event.tag, JobLine):
                    observer.on_resend(event.tag)
            elif isinstance(event, ControllerMessage):
                observer.on_message(event.text, event.reply)
            elif isinstance(event, ControllerReady):
                observer.on_ready()
            elif isinstance(event, Notice):
                observer.on_notice(event.text)
            elif isinstance(event, Failed):
                self._finish(_failure_error(event))
                return

    def _arm_timer(self, deadline: float | None) -> None:
        # A timer already due no later stays: firing early is harmless (the core checks
        # its own deadline and the pump re-arms), and most lines only push it back.
        armed = self._timer_at
        if armed is not None and (deadline is None or armed <= deadline):
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

    def _finish(self, result: Outcome | HostError) -> None:
        if self._done.done():
            return
        if self._timer is not None:
            self._timer.cancel()
        if self._action_task is not None:
            self._action_task.cancel()
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
    where = f" (at {event.tag.position})" if isinstance(event.tag, JobLine) else ""
    reason = event.reason + where
    if event.kind in (FailureKind.CONTROLLER, FailureKind.RESET):
        return ControllerError(reason)
    if event.kind is FailureKind.TIMEOUT:
        return LinkError(reason)
    return ProtocolError(reason)


async def stream(
    port: str,
    baudrate: int,
    core: HostProtocol,
    items: Iterable[JobItem],
    observer: Observer | None = None,
    on_open: Callable[[Sender], None] | None = None,
    *,
    safe_stop: Sequence[str] = (),
    wire_log: BinaryIO | None = None,
) -> Summary:
    """Open ``port``, stream ``items``, close the port; the one call most users need.

    ``on_open`` receives the :class:`Sender` once the port is open (to cancel it).
    """

    def factory() -> Sender:
        return Sender(core, items, observer, safe_stop=safe_stop, wire_log=wire_log)

    transport, protocol = await open_link(port, baudrate, factory)
    assert isinstance(protocol, Sender)
    if on_open is not None:
        on_open(protocol)
    try:
        return await protocol.wait()
    finally:
        transport.close()
