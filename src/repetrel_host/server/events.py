"""The server's events, to every listener (the event streams' clients, OctoPrint's push
socket, MQTT): printer states, jobs, progress, heights, temperatures, controller messages
and snapshots, files, app keys and the farm's notices. One frozen dataclass per kind, each
with its wire name (``type``) and the JSON dict it is sent as (``as_json``), and the hub
that fans them out."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, ClassVar

from repetrel_host.server.store import JobRecord

BACKLOG = 1000  # events a slow listener may fall behind by; older ones are dropped


@dataclass(frozen=True)
class StateDetail:
    """Since when a printer is in its state (seconds since the epoch), why, if said, and a
    phase asked for and not reached yet ("pausing", "resuming")."""

    since: float
    reason: str | None
    phase: str | None


@dataclass(frozen=True)
class PrinterState:
    """A printer's state, and whether its queue is held; with its ``detail`` as the service
    tells a change (None: the bare state, as MQTT tells it on connecting)."""

    type: ClassVar[str] = "printer"
    printer: str
    state: str
    held: bool
    detail: StateDetail | None = None

    def as_json(self) -> dict[str, Any]:
        json: dict[str, Any] = {
            "type": self.type,
            "printer": self.printer,
            "state": self.state,
            "held": self.held,
        }
        if self.detail is not None:
            json["since"] = self.detail.since
            json["reason"] = self.detail.reason
            json["phase"] = self.detail.phase
        return json


@dataclass(frozen=True)
class JobChanged:
    """A job of the printer was queued, started, paused, ended or cancelled: its record."""

    type: ClassVar[str] = "job"
    printer: str
    record: JobRecord

    def as_json(self) -> dict[str, Any]:
        return {"type": self.type, "printer": self.printer, "job": self.record.as_json()}


@dataclass(frozen=True)
class PrintProgress:
    """Where the printer's job is: its lines and bytes acknowledged, its layer, its
    completion (%) and the seconds it has left, and how they were found; and when the
    printer should be free, its queue counted."""

    type: ClassVar[str] = "progress"
    printer: str
    job: int  # the job's id
    lines: int
    last_line: int  # the file's line last acknowledged
    offset: int  # the file's bytes acknowledged
    size: int
    layer: int
    layers: int
    completion: float | None
    time_left: int | None  # seconds
    time_left_from: str | None  # printers.running.LEFT_FROM: estimate, plan, slicer
    ends: str | None = None  # when it should end: ISO 8601, UTC
    free_at: str | None = None  # when the printer should be free (its queue too): ISO, UTC

    def as_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "printer": self.printer,
            "job": self.job,
            "lines": self.lines,
            "last_line": self.last_line,
            "bytes": self.offset,
            "size": self.size,
            "layer": self.layer,
            "layers": self.layers,
            "completion": self.completion,
            "time_left": self.time_left,
            "time_left_from": self.time_left_from,
            "ends": self.ends,
            "free_at": self.free_at,
        }


@dataclass(frozen=True)
class ZChanged:
    """The job reached a new height, as the slicer marked it (OctoPrint's ZChange)."""

    type: ClassVar[str] = "z"
    printer: str
    new: float
    old: float | None

    def as_json(self) -> dict[str, Any]:
        return {"type": self.type, "printer": self.printer, "new": self.new, "old": self.old}


@dataclass(frozen=True)
class TemperatureReadings:
    """A temperature report of the printer: sensor (``T``, ``B``...): (actual, target)."""

    type: ClassVar[str] = "temperatures"
    printer: str
    time: float  # when it came (seconds since the epoch)
    readings: Mapping[str, tuple[float, float | None]]

    def as_json(self) -> dict[str, Any]:
        readings = {sensor: list(value) for sensor, value in self.readings.items()}
        return {"type": self.type, "printer": self.printer, "time": self.time, "readings": readings}


@dataclass(frozen=True)
class PrinterMessage:
    """A message about the printer: the controller's, or the server's (a host code told
    rather than done, a safe stop held up)."""

    type: ClassVar[str] = "message"
    printer: str
    text: str

    def as_json(self) -> dict[str, Any]:
        return {"type": self.type, "printer": self.printer, "text": self.text}


@dataclass(frozen=True)
class SnapshotTaken:
    """The printer's camera took a snapshot: its file's name, and where the API serves it."""

    type: ClassVar[str] = "snapshot"
    printer: str
    file: str
    url: str

    def as_json(self) -> dict[str, Any]:
        return {"type": self.type, "printer": self.printer, "file": self.file, "url": self.url}


@dataclass(frozen=True)
class FileChanged:
    """An upload (or a folder) was ``added`` or ``removed`` by an ``operation`` (add, copy,
    remove), ``moved`` (by move: from ``source`` to ``path``, one event, as Moonraker tells
    a move), or its analysis was made in the background (``analysed``, by ``analyse``);
    ``path`` and ``source`` are below the uploads. The server's, for every printer."""

    type: ClassVar[str] = "file"
    printer: ClassVar[None] = None
    what: str
    path: str
    name: str
    folder: bool
    operation: str
    source: str | None = None

    def as_json(self) -> dict[str, Any]:
        found = {
            "type": self.type,
            "what": self.what,
            "path": self.path,
            "name": self.name,
            "folder": self.folder,
            "operation": self.operation,
        }
        if self.source is not None:
            found["source"] = self.source
        return found


@dataclass(frozen=True)
class AppKeyEvent:
    """An app-key request (``what``: request) or decision (granted, denied, revoked); a
    request's and its decision's with the request as OctoPrint lists it (its user, token and
    address), a key granted or revoked directly with its app alone. The server's (the
    page shows them)."""

    type: ClassVar[str] = "appkey"
    printer: ClassVar[None] = None
    what: str
    app_id: str
    user_id: str | None = None
    user_token: str | None = None
    remote_address: str | None = None

    def as_json(self) -> dict[str, Any]:
        json: dict[str, Any] = {"type": self.type, "what": self.what, "app_id": self.app_id}
        request = {
            "user_id": self.user_id,
            "user_token": self.user_token,
            "remote_address": self.remote_address,
        }
        json.update((key, value) for key, value in request.items() if value is not None)
        return json


@dataclass(frozen=True)
class FarmEvent:
    """One of the farm's notifications (jobs queued, claimed, reported; nodes, printers),
    as PostgreSQL told it. The farm's, for its own event stream."""

    type: ClassVar[str] = "farm"
    printer: ClassVar[None] = None
    notice: Mapping[str, Any]

    def as_json(self) -> dict[str, Any]:
        return {"type": self.type, **self.notice}


ServerEvent = (
    PrinterState
    | JobChanged
    | PrintProgress
    | ZChanged
    | TemperatureReadings
    | PrinterMessage
    | SnapshotTaken
    | FileChanged
    | AppKeyEvent
    | FarmEvent
)


class Subscription:
    """What one listener hears: the events it asked for, in order (``async for``, or
    ``get()`` to wait with a timeout), at most ``BACKLOG`` behind: a slow listener loses the
    oldest, and never blocks the printers."""

    def __init__(self, printer: str | None, kinds: tuple[type[ServerEvent], ...] | None) -> None:
        self.printer = printer  # None: every printer's
        self.kinds = kinds  # None: every kind
        self._queue: asyncio.Queue[ServerEvent] = asyncio.Queue(BACKLOG)

    def wants(self, event: ServerEvent) -> bool:
        """``event`` is one this listener asked for: of its printer (or the server's, for
        every printer), of its kinds."""
        if self.printer is not None and event.printer not in (None, self.printer):
            return False
        return self.kinds is None or isinstance(event, self.kinds)

    def offer(self, event: ServerEvent) -> None:
        """Queue ``event`` if it is wanted, dropping the oldest when the queue is full."""
        if not self.wants(event):
            return
        if self._queue.full():
            self._queue.get_nowait()
        self._queue.put_nowait(event)

    async def get(self) -> ServerEvent:
        """The next event, once there is one."""
        return await self._queue.get()

    def __aiter__(self) -> Subscription:
        return self

    async def __anext__(self) -> ServerEvent:
        return await self.get()


class EventHub:
    """The server's events, fanned out to every listener as they are published."""

    def __init__(self) -> None:
        self._subscriptions: set[Subscription] = set()
        self._loop: asyncio.AbstractEventLoop | None = None  # the listeners', once one came

    def publish(self, event: ServerEvent) -> None:
        for subscription in self._subscriptions:
            subscription.offer(event)

    def publish_from_thread(self, event: ServerEvent) -> None:
        """:meth:`publish` from another thread (a background analysis): on the listeners'
        event loop; nothing when no one ever listened."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self.publish, event)

    @asynccontextmanager
    async def listen(
        self, printer: str | None = None, kinds: tuple[type[ServerEvent], ...] | None = None
    ) -> AsyncIterator[Subscription]:
        """The events published while in the block: those of ``printer`` (and the server's,
        for every printer) when given, of ``kinds`` when given."""
        subscription = Subscription(printer, kinds)
        self._loop = asyncio.get_running_loop()
        self._subscriptions.add(subscription)
        try:
            yield subscription
        finally:
            self._subscriptions.discard(subscription)
