"""Events handed out to subscribers: the session's (states, temperatures, messages) and
each job's (progress, resends, its end), every subscriber at its own pace."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterable
from typing import Generic, TypeVar

# The session's log, as before its parts had modules of their own.
log = logging.getLogger("repetrel_host.session.printer")

E = TypeVar("E")
_END = object()


class EventFanout(Generic[E]):
    """Hands every event to every subscriber, each at its own pace."""

    def __init__(self, backlog: int = 0) -> None:
        self._queues: list[asyncio.Queue[object]] = []
        self._backlog: deque[E] | None = deque(maxlen=backlog) if backlog else None
        self._closed = False
        # Called at once with each event, on the session's path (connect()'s on_event).
        self.callbacks: list[Callable[[E], None]] = []

    def publish(self, event: E) -> None:
        """To every subscriber and callback."""
        if self._backlog is not None:
            self._backlog.append(event)
        for queue in self._queues:
            queue.put_nowait(event)
        for callback in self.callbacks:
            try:
                callback(event)
            except Exception:  # a listener's bug must not break the session
                log.exception("an on_event callback failed on %r", event)

    def close(self) -> None:
        """Every subscription ends (after what it has yet to yield)."""
        self._closed = True
        for queue in self._queues:
            queue.put_nowait(_END)

    def stream(self, first: Iterable[E] = ()) -> AsyncIterator[E]:
        """A subscription from now on (not from the first ``anext``), after ``first``."""
        queue: asyncio.Queue[object] = asyncio.Queue()
        for event in (*first, *(self._backlog or ())):
            queue.put_nowait(event)
        if self._closed:
            queue.put_nowait(_END)
        self._queues.append(queue)
        return self._drain(queue)

    async def _drain(self, queue: asyncio.Queue[object]) -> AsyncIterator[E]:
        try:
            while (event := await queue.get()) is not _END:
                yield event  # type: ignore[misc]
        finally:
            self._queues.remove(queue)
