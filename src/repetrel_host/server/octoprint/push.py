"""OctoPrint's push socket (``/sockjs``), for farm managers (FDM Monster, OctoFarm) and
phone apps (OctoApp, Printoid, OctoPod), as OctoPrint 1.11 serves it
(``octoprint/server/util/sockjs.py``, ``docs/api/push.rst``): what is pushed, and when.
Its transports (SockJS's and the raw websocket) are :mod:`.sockjs`'s.

A client gets ``connected`` at once, and nothing more until it sends ``auth`` with a
session from OctoPrint's login (unless the server opens reads); then ``history``,
``current`` (at every change of state, else every 0.5 s times its ``throttle``),
``event`` and ``plugin`` messages, as ``subscribe`` chose.

A socket never slows a printer. A printer's messages are built once a tick (or at a change
of state) and serialized once for all its clients; each client has a bounded outbox that
its own task writes out, and a client that falls behind (a stuck reader) is dropped, never
waited for. The wire's log is read from the session's tail once a tick, not line by line.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import repetrel_host as rh
from repetrel_host.server.events import (
    AppKeyEvent,
    FileChanged,
    JobChanged,
    PrinterMessage,
    PrinterState,
    ServerEvent,
    SnapshotTaken,
    TemperatureReadings,
    ZChanged,
)
from repetrel_host.server.json_input import JsonTooDeep, parse_json
from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.messages import Frame, Subscriptions, connected_text, dumps
from repetrel_host.server.octoprint.terminal import LOG_LINES, terminal_lines
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import ENDED, JobRecord

log = logging.getLogger("repetrel_host.server")

TICK = 0.5  # OctoPrint's base rate of ``current`` messages (times a client's throttle)
# A client is dropped when its oldest message waiting is this old, or this many wait: it
# does not read (or cannot keep up); it may connect again (and gets the history).
STUCK_AFTER = 5.0
OUTBOX_MOST = 500
MESSAGES_KEPT = 300
TICKS_KEPT = 40  # ticks whose logs a throttled client still gets (20 s)
WIRE_PIECES = 1024  # the session's wire tail between two ticks
JOB_KEPT = 2.0  # s a current's job part is reused while the job shown stays the same
LINGER = 30.0  # a printer's feed (and its wire tail) outlives its last client (apps reconnect)
UNAUTHED_BACKLOG = 100  # OctoPrint's: messages held for a client until its auth
INCOMING_MOST = 64 * 1024  # bytes of one client's message
_LINKED = ("ready", "printing", "paused")
_STATE_IDS = {
    model.HELD_TEXT: "OPERATIONAL",
    "Offline after error": "CLOSED_WITH_ERROR",
}


def _kept(lines: list[str], wanted: bool | re.Pattern[str]) -> list[str]:
    if wanted is True:
        return lines
    if wanted is False:
        return []
    return [line for line in lines if wanted.search(line)]


class Client:
    """One socket's connection to a printer's feed: who it is, what it asked for, and the
    messages waiting for it (its transport writes them out)."""

    def __init__(self, feed: Feed, address: str) -> None:
        self.feed = feed
        self.address = address
        self.user: str | None = None
        self.registered = False  # gets the printer's messages (OctoPrint: STATUS)
        self.throttle = 1
        self.last_tick = 0  # the tick of its last current
        self.subscriptions = Subscriptions()
        self.subscribed = False  # sent a subscribe (else it gets everything)
        self.outbox: deque[Frame] = deque()
        self.waiting_since = 0.0  # when its oldest message waiting was queued
        self.backlog: list[Frame] = []  # plugin messages held until its auth
        self.wake = asyncio.Event()
        self.closed = ""  # why, once closed
        self.writer: asyncio.Future[Any] | None = None  # its transport's, cancelled if dropped

    @property
    def may_read(self) -> bool:
        """OctoPrint's STATUS permission: a session's user, or anyone where reads are open."""
        return self.user is not None or self.feed.push.server.access.public_read

    # --- out ------------------------------------------------------------------------

    def offer(self, frame: Frame) -> None:
        """Queue ``frame``; a client that does not keep up is dropped, never waited for."""
        if self.closed:
            return
        outbox = self.outbox
        if not outbox:
            self.waiting_since = frame.created
        elif len(outbox) >= OUTBOX_MOST or frame.created - self.waiting_since > STUCK_AFTER:
            self.drop(f"it did not read its messages for {STUCK_AFTER:g} s")
            return
        outbox.append(frame)
        self.wake.set()

    def offer_event(self, name: str, frame: Frame) -> None:
        events = self.subscriptions.events
        if self.registered and self.may_read and (events is None or name in events):
            self.offer(frame)

    def offer_plugin(self, plugin: str, frame: Frame) -> None:
        plugins = self.subscriptions.plugins
        if plugins is not None and plugin not in plugins:
            return
        # Open reads do not open the appkeys plugin's messages: a user_token decides a request.
        if self.may_read and (self.user is not None or plugin != "appkeys"):
            self.offer(frame)
        elif len(self.backlog) < UNAUTHED_BACKLOG:  # (offered at its auth: queued then)
            self.backlog.append(frame)  # OctoPrint holds it until the client's auth

    async def take(self, timeout: float | None) -> list[Frame]:
        """The messages waiting, once there are some (none after ``timeout`` seconds, or
        once the client was closed)."""
        if not self.outbox and not self.closed:
            self.wake.clear()
            if timeout is None:
                await self.wake.wait()
            else:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(timeout):
                        await self.wake.wait()
        frames = list(self.outbox)
        self.outbox.clear()
        return frames

    def close(self, why: str) -> None:
        if not self.closed:
            log.info(
                "printer %s: push socket client %s closed: %s", self.feed.name, self.address, why
            )
            self.closed = why
            self.outbox.clear()
            self.wake.set()
            self.feed.remove(self)

    def drop(self, why: str) -> None:
        """Close a client that does not keep up: its transport is abandoned mid-write."""
        log.warning(
            "printer %s: push socket client %s dropped: %s", self.feed.name, self.address, why
        )
        self.close(why)
        if self.writer is not None:
            self.writer.cancel()

    # --- in -------------------------------------------------------------------------

    def receive(self, message: Any) -> None:
        """A message from the client: JSON text, or (octorest's, in a SockJS frame) an
        object. What is not understood is ignored, as OctoPrint does."""
        if isinstance(message, str):
            if len(message) > INCOMING_MOST:
                return
            try:
                message = parse_json(message)
            except (ValueError, JsonTooDeep) as exc:
                log.info("push socket client %s: ignored: %s", self.address, exc)
                return
        if not isinstance(message, dict):
            return
        if "auth" in message:
            self._auth(message["auth"])
        elif "throttle" in message:
            try:
                throttle = int(message["throttle"])
            except (TypeError, ValueError):
                return
            if throttle >= 1:
                self.throttle = throttle
        elif "subscribe" in message:
            try:
                subscriptions = Subscriptions.parse(message["subscribe"])
            except ValueError as exc:
                log.info("push socket client %s: subscribe ignored: %s", self.address, exc)
                return
            before = self.subscriptions.state_wanted if self.subscribed else None
            self.subscriptions, self.subscribed = subscriptions, True
            if subscriptions.state and subscriptions.state_wanted != before:
                self.feed.send_history(self)  # as OctoPrint: the state anew

    def _auth(self, value: Any) -> None:
        parts = value.split(":") if isinstance(value, str) else []
        if len(parts) != 2:
            log.info("push socket client %s: an auth that is not user:session", self.address)
            return
        user, session = parts
        access = self.feed.push.server.access
        if user and access.user_for_session(session) == user:
            self.user = user
            log.info("push socket client %s: %s logged in", self.address, user)
            backlog, self.backlog = self.backlog, []
            for frame in backlog:
                self.offer(Frame(frame.text))
        else:
            log.info("push socket client %s: unknown user or session", self.address)
            self.user = None
            self.offer(Frame.of("reauthRequired", {"reason": "stale"}))
        self.feed.register(self)


@dataclass
class Tick:
    """What one tick of a printer's feed added: temperatures, log lines, messages; as JSON
    fragments (a list's items, without brackets) for the clients that want them all."""

    number: int
    temps: str
    logs: list[str]
    logs_json: str
    messages: list[str]
    messages_json: str


def _items(values: list[Any]) -> str:
    return dumps(values)[1:-1]


class Feed:
    """One printer's messages, built once for all its clients."""

    def __init__(self, push: Push, service: PrinterService) -> None:
        self.push = push
        self.service = service
        self.name = service.name
        self.clients: set[Client] = set()
        self.tick_number = 0
        self.ticks: deque[Tick] = deque(maxlen=TICKS_KEPT)
        self.temps: list[dict[str, Any]] = []  # since the last tick
        self.messages: list[str] = []
        self.logs_kept: deque[str] = deque(maxlen=LOG_LINES)
        self.messages_kept: deque[str] = deque(maxlen=MESSAGES_KEPT)
        self.last_base = ""
        self.last_state: dict[str, Any] | None = None
        self.jobs: dict[int, str] = {}  # the job states told (print events)
        self.linked = service.state in _LINKED
        self.tailing: rh.Printer | None = None
        self.partial = [b"", b""]  # a line of the wire not complete yet (received, sent)
        self._loop = asyncio.get_running_loop()
        self._timer: asyncio.TimerHandle | None = None
        self._snapshot_due = False
        self._job_kept: tuple[object, float, dict[str, Any]] | None = None
        self._idle_since: float | None = self._loop.time()
        running = service.running
        record = service.store.job(running.record.id) if running is not None else None
        if record is not None:
            self.jobs[record.id] = record.state.value
        service.watchers.append(self._changed)
        self._timer = self._loop.call_later(TICK, self._on_tick)

    # --- clients ----------------------------------------------------------------

    def add(self, client: Client) -> None:
        self.clients.add(client)
        self._idle_since = None
        client.offer(self.push.connected)
        self.register(client)

    def remove(self, client: Client) -> None:
        self.clients.discard(client)
        if not self.clients:
            self._idle_since = self._loop.time()

    def register(self, client: Client) -> None:
        """A client that may read gets the printer's messages, the history first (OctoPrint
        registers a socket once it has the STATUS permission)."""
        if not client.registered and client.may_read and not client.closed:
            client.registered = True
            self.send_history(client)

    def send_history(self, client: Client) -> None:
        if not client.registered or not client.subscriptions.state or not client.may_read:
            return
        service = self.service
        payload = model.current(service)
        payload["temps"] = [
            model.temperature_sample(when, readings)
            for when, readings in list(service.temperature_history)
        ]
        payload["logs"] = _kept(list(self.logs_kept), client.subscriptions.logs)
        payload["messages"] = _kept(list(self.messages_kept), client.subscriptions.messages)
        client.last_tick = self.tick_number
        client.offer(Frame.of("history", payload))

    # --- the tick -----------------------------------------------------------------

    def _changed(self) -> None:
        """The printer's state or a phase may have changed (told on its path): looked at
        as soon as that path returns, so that even a short phase goes out."""
        if not self._snapshot_due:
            self._snapshot_due = True
            self._loop.call_soon(self._snapshot)

    def _snapshot(self) -> None:
        self._snapshot_due = False
        if self.clients and model.state(self.service) != self.last_state:
            self.tick(forced=True)

    def _on_tick(self) -> None:
        self._timer = self._loop.call_later(TICK, self._on_tick)
        idle = self._idle_since
        if idle is not None and self._loop.time() - idle > LINGER:
            self.push.retire(self)
            return
        if any(client.registered for client in self.clients):
            try:
                self.tick(forced=False)
            except Exception:  # a bug here must not end the printer's feed
                log.exception("printer %s: the push socket's tick failed", self.name)

    def tick(self, forced: bool) -> None:
        """Build the printer's ``current`` once, and offer it to the clients due (all of
        them at a change of state): sent when something changed, as OctoPrint does."""
        service = self.service
        logs = self._read_wire()
        temps, self.temps = self.temps, []
        messages, self.messages = self.messages, []
        base = model.current(service, self._job_now())
        server_time = base.pop("serverTime")
        state = base["state"]
        base_json = dumps(base)
        if base_json == self.last_base and not (logs or temps or messages):
            return
        if state != self.last_state and self.last_state is not None:
            text = state["text"]
            state_id = _STATE_IDS.get(text, text.upper().replace(" ", "_"))
            self.event("PrinterStateChanged", {"state_id": state_id, "state_string": text})
        self.last_base, self.last_state = base_json, state
        self.logs_kept.extend(logs)
        self.messages_kept.extend(messages)
        self.tick_number += 1
        now = Tick(self.tick_number, _items(temps), logs, _items(logs), messages, _items(messages))
        self.ticks.append(now)
        head = f'{{"current":{base_json[:-1]},"serverTime":{dumps(server_time)},'
        made: dict[tuple[object, ...], Frame] = {}
        for client in list(self.clients):
            if not (client.registered and client.subscriptions.state and client.may_read):
                continue
            if not forced and self.tick_number - client.last_tick < client.throttle:
                continue
            subscriptions = client.subscriptions
            logs_wanted, messages_wanted = subscriptions.logs, subscriptions.messages
            shared = isinstance(logs_wanted, bool) and isinstance(messages_wanted, bool)
            key = (client.last_tick, logs_wanted, messages_wanted) if shared else (client,)
            frame = made.get(key)
            if frame is None:
                frame = made[key] = Frame(self._current(head, client))
            client.last_tick = self.tick_number
            client.offer(frame)

    def _job_now(self) -> dict[str, Any]:
        """The job's part of a current, made again when the job (or file) shown changed,
        or after :data:`JOB_KEPT` s (its file's size, the last print's time)."""
        service = self.service
        key = (id(service.running), service.selected, id(service.finished), service.finished_at)
        now = self._loop.time()
        kept = self._job_kept
        if kept is None or kept[0] != key or now - kept[1] > JOB_KEPT:
            kept = self._job_kept = (key, now, model.job(service))
        return kept[2]

    def _current(self, head: str, client: Client) -> str:
        """The ``current`` text for a client: the ticks since its last one (several when it
        throttles), its logs and messages as it subscribed."""
        since = [tick for tick in self.ticks if tick.number > client.last_tick]
        temps = ",".join(tick.temps for tick in since if tick.temps)
        wanted = client.subscriptions
        logs = self._part(since, wanted.logs, lambda tick: tick.logs, lambda tick: tick.logs_json)
        messages = self._part(
            since, wanted.messages, lambda tick: tick.messages, lambda tick: tick.messages_json
        )
        return f'{head}"temps":[{temps}],"logs":[{logs}],"messages":[{messages}]}}}}'

    @staticmethod
    def _part(
        ticks: list[Tick],
        wanted: bool | re.Pattern[str],
        lines: Callable[[Tick], list[str]],
        fragment: Callable[[Tick], str],
    ) -> str:
        if wanted is False:
            return ""
        if wanted is True:
            return ",".join(fragment(tick) for tick in ticks if fragment(tick))
        return _items([line for tick in ticks for line in lines(tick) if wanted.search(line)])

    def _read_wire(self) -> list[str]:
        """The wire since the last tick, as OctoPrint's terminal shows it: the session's
        tail is swapped for an empty one (the session only ever appends to it)."""
        printer = self.service.printer
        if printer is not self.tailing:
            if self.tailing is not None:
                self.tailing.wire_tail = None
            self.tailing = printer
            self.partial = [b"", b""]
            if printer is not None:
                printer.wire_tail = deque(maxlen=WIRE_PIECES)
            return []
        if printer is None or not printer.wire_tail:
            return []
        pieces = printer.wire_tail
        printer.wire_tail = deque(maxlen=WIRE_PIECES)
        return terminal_lines(pieces, self.partial)

    # --- events -------------------------------------------------------------------

    def event(self, name: str, payload: dict[str, Any]) -> None:
        """OctoPrint's event ``name`` to the clients that subscribed to it."""
        if self.clients:
            frame = Frame.of("event", {"type": name, "payload": payload})
            for client in list(self.clients):
                client.offer_event(name, frame)

    def plugin(self, plugin: str, data: dict[str, Any]) -> None:
        frame = Frame.of("plugin", {"plugin": plugin, "data": data})
        for client in list(self.clients):
            client.offer_plugin(plugin, frame)

    def on_event(self, event: ServerEvent) -> None:
        """One of the server's events, as OctoPrint's messages."""
        if isinstance(event, TemperatureReadings):
            self.temps.append(model.temperature_sample(time.time(), event.readings))
        elif isinstance(event, PrinterMessage):
            self.messages.append(event.text)
        elif isinstance(event, PrinterState):
            self._linked(event.state in _LINKED)
            self._changed()
        elif isinstance(event, JobChanged):
            self._job(event.record)
            self._changed()
        elif isinstance(event, ZChanged):
            self.event("ZChange", {"new": event.new, "old": event.old})
        elif isinstance(event, SnapshotTaken):
            self.event("CaptureDone", {"file": event.file})
        elif isinstance(event, FileChanged):
            self._file(event)
        elif isinstance(event, AppKeyEvent):
            self._appkey(event)

    def _linked(self, linked: bool) -> None:
        if linked == self.linked:
            return
        self.linked = linked
        if linked:
            printer = self.service.printer
            baud = printer.settings.baud if printer is not None else None
            self.event("Connected", {"port": self.service.port, "baudrate": baud})
        else:
            self.event("Disconnected", {})

    def _job(self, changed: JobRecord) -> None:
        job_id, state = changed.id, changed.state.value
        before = self.jobs.get(job_id)
        if state == before:
            return
        self.jobs[job_id] = state
        while len(self.jobs) > 50:
            del self.jobs[next(iter(self.jobs))]
        service = self.service
        record = service.store.job(job_id)
        if record is None or record.started is None or not self.clients:
            return  # a queued job, or one refused before it started
        running = service.running if state in ("printing", "paused") else service.finished
        if running is not None and running.record.id != job_id:
            running = None
        if state == "printing":
            payload = model.print_event(service, record)
            self.event("PrintResumed" if before == "paused" else "PrintStarted", payload)
        elif state == "paused":
            self.event("PrintPaused", model.print_event(service, record, running))
        elif state == "completed":
            self.event("PrintDone", model.print_event(service, record))
        elif state in ENDED:
            payload = model.print_event(service, record, running)
            if state == "cancelled":
                self.event("PrintCancelled", payload)
                self.event("PrintFailed", {**payload, "reason": "cancelled"})
            else:
                self.event("PrintFailed", {**payload, "reason": "error", "error": record.error})

    def _file(self, event: FileChanged) -> None:
        payload = {"storage": "local", "path": event.path, "name": event.name}
        if event.what == "analysed":  # its gcodeAnalysis is complete: OctoPrint's words
            self.event("MetadataAnalysisFinished", {**payload, "origin": "local"})
        elif event.what == "moved" and event.source is not None:
            # OctoPrint's move: removed, added and moved (its filemanager's move_file).
            name = event.source.rsplit("/", 1)[-1]
            self._added_or_removed(
                "Removed", event, {"storage": "local", "path": event.source, "name": name}
            )
            self._added_or_removed("Added", event, payload)
            moved = {
                "storage": "local",
                "source_path": event.source,
                "source_name": name,
                "destination_path": event.path,
                "destination_name": event.name,
            }
            self.event("FolderMoved" if event.folder else "FileMoved", moved)
        else:
            what = "Added" if event.what == "added" else "Removed"
            self._added_or_removed(what, event, payload)
        self.event("UpdatedFiles", {"type": "printables"})

    def _added_or_removed(self, what: str, event: FileChanged, payload: dict[str, Any]) -> None:
        if event.folder:
            self.event(f"Folder{what}", payload)
        else:
            kind = ["machinecode", "gcode"]
            self.event(f"File{what}", {**payload, "type": kind, "operation": event.operation})

    def _appkey(self, event: AppKeyEvent) -> None:
        """The appkeys plugin's messages: a request to decide, a decision made."""
        if event.what == "request":
            data = {
                "type": "request_access",
                "app_name": event.app_id,
                "user_token": event.user_token,
                "user_id": event.user_id,
                "remote_address": event.remote_address,
            }
            self.plugin("appkeys", data)
        elif event.user_token:
            self.plugin("appkeys", {"type": "end_request", "user_token": event.user_token})

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        with contextlib.suppress(ValueError):
            self.service.watchers.remove(self._changed)
        if self.tailing is not None:
            self.tailing.wire_tail = None
        for client in list(self.clients):
            client.close("the server stops")


class Push:
    """The push socket of one server: a feed per printer with clients, and the server's
    events routed to the feeds. Its transports end what is theirs when it stops."""

    def __init__(self, server: PrintServer) -> None:
        self.server = server
        self.feeds: dict[str, Feed] = {}
        # What the transports end first when it stops (SockJS's xhr sessions).
        self.on_stop: list[Callable[[], None]] = []
        self._events: asyncio.Task[None] | None = None
        self._connected = ""

    @property
    def connected(self) -> Frame:
        """OctoPrint's ``connected`` message, made once."""
        if not self._connected:
            self._connected = connected_text(self.server)
        return Frame(self._connected)

    def feed(self, printer: str | None) -> Feed:
        """The feed of ``printer`` (None: the default one); 404 when there is none."""
        service = self.server.service(printer)
        feed = self.feeds.get(service.name)
        if feed is None:
            feed = self.feeds[service.name] = Feed(self, service)
        if self._events is None:
            self._events = asyncio.get_running_loop().create_task(self._route(), name="push")
        return feed

    def retire(self, feed: Feed) -> None:
        """A feed without clients for a while goes (and with it the wire's tail)."""
        if self.feeds.get(feed.name) is feed:
            del self.feeds[feed.name]
        feed.close()

    async def _route(self) -> None:
        async with self.server.events.listen() as events:
            async for event in events:
                feeds = list(self.feeds.values())
                for feed in feeds:
                    if event.printer is None or event.printer == feed.name:
                        try:
                            feed.on_event(event)
                        except Exception:  # a bug here must not end every feed
                            log.exception(
                                "printer %s: push socket event %s", feed.name, event.as_json()
                            )

    async def stop(self) -> None:
        for end in self.on_stop:
            end()
        for feed in list(self.feeds.values()):
            self.retire(feed)
        if self._events is not None:
            self._events.cancel()
            await asyncio.gather(self._events, return_exceptions=True)
