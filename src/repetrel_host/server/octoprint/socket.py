"""OctoPrint's push socket (``/sockjs``), for farm managers (FDM Monster, OctoFarm) and
phone apps (OctoApp, Printoid, OctoPod), as OctoPrint 1.11 serves it
(``octoprint/server/util/sockjs.py``, its vendored SockJS server, ``docs/api/push.rst``).

``/sockjs`` speaks SockJS (``/sockjs/info``; the websocket, xhr-streaming and xhr-polling
transports at ``/sockjs/SERVER/SESSION/...``); ``/sockjs/websocket`` is the raw
websocket, one JSON object a message. ``/printers/NAME/sockjs...`` is printer NAME's, and
the root the default printer's, as the REST face. A client gets ``connected`` at once, and
nothing more until it sends ``auth`` with a session from OctoPrint's login (unless the
server opens reads); then ``history``, ``current`` (at every change of state, else every
0.5 s times its ``throttle``), ``event`` and ``plugin`` messages, as ``subscribe`` chose.

No SockJS server library fits Starlette (those on PyPI serve aiohttp, Tornado, Sanic or
Django), and SockJS's framing is small: it is written here.

A socket never slows a printer. A printer's messages are built once a tick (or at a change
of state) and serialized once for all its clients; each client has a bounded outbox that
its own task writes out, and a client that falls behind (a stuck reader) is dropped, never
waited for. The wire's log is read from the session's tail once a tick, not line by line.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import platform
import random
import re
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from itertools import islice
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from starlette.routing import WebSocketRoute
from starlette.types import Receive, Scope, Send

import repetrel_host as rh
from repetrel_host.server.access import PERMISSIONS
from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.rest import OCTOPRINT_VERSION
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import ENDED

log = logging.getLogger("repetrel_host.server")

TICK = 0.5  # OctoPrint's base rate of ``current`` messages (times a client's throttle)
HEARTBEAT = 25.0  # SockJS: an "h" frame after this long without one
DISCONNECT_DELAY = 5.0  # SockJS: an xhr session no request waits on this long is closed
RESPONSE_LIMIT = 128 * 1024  # SockJS: an xhr-streaming response ends after this many bytes
# A client is dropped when its oldest message waiting is this old, or this many wait: it
# does not read (or cannot keep up); it may connect again (and gets the history).
STUCK_AFTER = 5.0
OUTBOX_MOST = 500
LOG_LINES = 300  # OctoPrint's terminal: the log lines a history (and a tick) carries
MESSAGES_KEPT = 300
TICKS_KEPT = 40  # ticks whose logs a throttled client still gets (20 s)
WIRE_PIECES = 1024  # the session's wire tail between two ticks
JOB_KEPT = 2.0  # s a current's job part is reused while the job shown stays the same
LINGER = 30.0  # a printer's feed (and its wire tail) outlives its last client (apps reconnect)
UNAUTHED_BACKLOG = 100  # OctoPrint's: messages held for a client until its auth
INCOMING_MOST = 64 * 1024  # bytes of one client's message
_LINKED = ("ready", "printing", "paused")
_SESSION_ID = re.compile(r"[^/.]+")
_PREFIXES = (b"\nRecv: ", b"\nSend: ")  # OctoPrint's terminal, by "sent"
_PREFIX = len("Send: ")
_STATE_IDS = {
    model.HELD_TEXT: "OPERATIONAL",
    "Offline after error": "CLOSED_WITH_ERROR",
}


def _dumps(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"))


class Frame:
    """One message, serialized once for every client that gets it."""

    __slots__ = ("created", "text")

    def __init__(self, text: str) -> None:
        self.text = text
        self.created = time.monotonic()

    @classmethod
    def of(cls, kind: str, payload: Any) -> Frame:
        return cls(_dumps({kind: payload}))


@dataclass
class Subscriptions:
    """What a client asked for with ``subscribe`` (OctoPrint 1.8+); by default everything."""

    state: bool = True
    logs: bool | re.Pattern[str] = True
    messages: bool | re.Pattern[str] = True
    plugins: list[str] | None = None  # None: all
    events: list[str] | None = None

    @property
    def state_wanted(self) -> tuple[object, ...]:
        return self.state, self.logs, self.messages

    @classmethod
    def parse(cls, value: Any) -> Subscriptions:
        """OctoPrint's ``subscribe`` payload; ValueError when it is not one."""
        if not isinstance(value, dict):
            raise ValueError("subscribe takes an object")
        state = value.get("state", False)
        if isinstance(state, bool):
            logs: bool | re.Pattern[str] = state
            messages: bool | re.Pattern[str] = False
        elif isinstance(state, dict):
            logs, messages = (
                _filter(state.get("logs", False)),
                _filter(state.get("messages", False)),
            )
            state = True
        else:
            raise ValueError("state must be a boolean or an object")
        return cls(
            state, logs, messages, _names(value.get("plugins", [])), _names(value.get("events", []))
        )


def _filter(value: Any) -> bool | re.Pattern[str]:
    if isinstance(value, bool):
        return value
    if isinstance(value, str):
        try:
            return re.compile(value)
        except re.error:
            raise ValueError("value must be a valid regex") from None
    raise ValueError("value must be a string or boolean")


def _names(value: Any) -> list[str] | None:
    if isinstance(value, bool):
        return None if value else []
    if isinstance(value, list):
        return [str(name) for name in value]
    raise ValueError("value must be a list or boolean")


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
        if self.may_read:
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
                message = json.loads(message)
            except ValueError:
                log.info("push socket client %s: not JSON, ignored", self.address)
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
    return _dumps(values)[1:-1]


def terminal_lines(pieces: deque[tuple[bool, bytes]], partial: list[bytes]) -> list[str]:
    """The wire's ``pieces`` (sent or not, data) as OctoPrint's terminal shows them ("Send:
    ...", "Recv: ..."), their last :data:`LOG_LINES` lines; ``partial`` holds the lines not
    complete yet (received, sent), from the last call and for the next. Only the newest
    pieces are read, a piece at a time with C's string operations: a line at a time in
    Python would cost more than the rest of a tick."""
    # The newest pieces that hold the lines shown (a piece holds a line, or hundreds).
    before: list[bytes | None] = [partial[False], partial[True]]
    kept = found = 0
    for _, data in reversed(pieces):
        kept += 1
        found += data.count(b"\n")
        if found > LOG_LINES:
            break
    if kept < len(pieces):
        # Where older pieces are left out, a line begun in them is too (None: unknown).
        unknown = {False, True}
        for sent, data in islice(reversed(pieces), kept, None):
            if sent in unknown:
                unknown.discard(sent)
                before[sent] = b"" if data[-1] == 10 else None
                if not unknown:
                    break
        pieces = deque(islice(pieces, len(pieces) - kept, None))
    chunks: list[bytes] = []
    add = chunks.append
    for sent, data in pieces:
        begun = before[sent]
        if begun:
            data = begun + data
            before[sent] = b""
        elif begun is None:
            cut = data.find(b"\n")
            if cut < 0:
                continue
            data, before[sent] = data[cut + 1 :], b""
            if not data:
                continue
        if data[-1] != 10:  # a line not complete yet (mostly a piece ends with one)
            data, newline, before[sent] = data.rpartition(b"\n")
            if not newline:
                continue
        # "\nSend: " before each line (and after the last: an empty line, left out)
        prefix = _PREFIXES[sent]
        add(prefix + data.replace(b"\n", prefix))
    partial[:] = [before[False] or b"", before[True] or b""]
    text = b"".join(chunks).replace(b"\r", b"").decode("utf-8", "replace")
    lines = text.split("\n")[-LOG_LINES * 2 :]
    return [line for line in lines if len(line) > _PREFIX][-LOG_LINES:]


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
        base_json = _dumps(base)
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
        head = f'{{"current":{base_json[:-1]},"serverTime":{_dumps(server_time)},'
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

    def on_event(self, event: dict[str, Any]) -> None:
        """One of the server's events, as OctoPrint's messages."""
        kind = event.get("type")
        if kind == "temperatures":
            self.temps.append(model.temperature_sample(time.time(), event["readings"]))
        elif kind == "message":
            self.messages.append(str(event["text"]))
        elif kind == "printer":
            self._linked(event["state"] in _LINKED)
            self._changed()
        elif kind == "job":
            self._job(event["job"])
            self._changed()
        elif kind == "z":
            self.event("ZChange", {"new": event["new"], "old": event["old"]})
        elif kind == "snapshot":
            self.event("CaptureDone", {"file": event["file"]})
        elif kind == "file":
            self._file(event)
        elif kind == "appkey":
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

    def _job(self, job: dict[str, Any]) -> None:
        job_id, state = int(job["id"]), str(job["state"])
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

    def _file(self, event: dict[str, Any]) -> None:
        what = "Added" if event["what"] == "added" else "Removed"
        payload = {"storage": "local", "path": event["path"], "name": event["name"]}
        if event["folder"]:
            self.event(f"Folder{what}", payload)
        else:
            kind = ["machinecode", "gcode"]
            self.event(f"File{what}", {**payload, "type": kind, "operation": event["operation"]})
        self.event("UpdatedFiles", {"type": "printables"})

    def _appkey(self, event: dict[str, Any]) -> None:
        """The appkeys plugin's messages: a request to decide, a decision made."""
        if event.get("what") == "request":
            data = {
                "type": "request_access",
                "app_name": event.get("app_id"),
                "user_token": event.get("user_token"),
                "user_id": event.get("user_id"),
                "remote_address": event.get("remote_address"),
            }
            self.plugin("appkeys", data)
        elif event.get("user_token"):
            self.plugin("appkeys", {"type": "end_request", "user_token": event["user_token"]})

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
    """The push socket of one server: a feed per printer with clients, the SockJS
    sessions of the xhr transports, and the server's events routed to the feeds."""

    def __init__(self, server: PrintServer) -> None:
        self.server = server
        self.feeds: dict[str, Feed] = {}
        self.sessions: dict[tuple[str, str], XhrSession] = {}
        self._events: asyncio.Task[None] | None = None
        self._connected = ""

    @property
    def connected(self) -> Frame:
        """OctoPrint's ``connected`` message (1.11's fields; ``apikey`` as older versions
        had it, null: a socket that has not logged in is given no key)."""
        if not self._connected:
            printers = ",".join(f"{s.name}={s.port}" for s in self.server.services.values())
            self._connected = _dumps(
                {
                    "connected": {
                        "apikey": None,
                        "version": OCTOPRINT_VERSION,
                        "display_version": OCTOPRINT_VERSION,
                        "branch": None,
                        "python_version": platform.python_version(),
                        "plugin_hash": _md5("appkeys"),
                        "config_hash": _md5(printers),
                        "debug": False,
                        "safe_mode": None,
                        "online": True,
                        "permissions": [_permission(key) for key in PERMISSIONS],
                    }
                }
            )
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
        async with self.server.events.subscribe() as queue:
            while True:
                event = await queue.get()
                printer = event.get("printer")
                feeds = list(self.feeds.values())
                for feed in feeds:
                    if printer is None or printer == feed.name:
                        try:
                            feed.on_event(event)
                        except Exception:  # a bug here must not end every feed
                            log.exception("printer %s: push socket event %s", feed.name, event)

    async def stop(self) -> None:
        for session in list(self.sessions.values()):
            session.end()
        for feed in list(self.feeds.values()):
            self.retire(feed)
        if self._events is not None:
            self._events.cancel()
            await asyncio.gather(self._events, return_exceptions=True)


def _md5(text: str) -> str:
    return hashlib.md5(text.encode(), usedforsecurity=False).hexdigest()


def _permission(key: str) -> dict[str, Any]:
    """A permission as OctoPrint's ``connected`` lists it."""
    entry: dict[str, Any] = {
        "key": key,
        "name": key.replace("_", " ").title(),
        "dangerous": key in ("ADMIN", "SYSTEM", "SETTINGS"),
        "default_groups": ["admins"] if key in ("ADMIN", "SYSTEM", "SETTINGS") else ["users"],
        "description": "",
        "needs": {"role": [key.lower()]},
    }
    if key.startswith("PLUGIN_APPKEYS_"):
        entry["plugin"] = "appkeys"
    return entry


# --- SockJS ------------------------------------------------------------------------------


def _sockjs_messages(text: str) -> Iterable[Any]:
    """The messages of one SockJS frame from a client: a JSON list of strings, or one
    string; octorest's ``send`` writes a bare object, taken as one message."""
    try:
        data = json.loads(text)
    except ValueError:
        return ()
    return data if isinstance(data, list) else (data,)


def _array(frames: list[Frame]) -> str:
    """A SockJS message frame. OctoPrint's holds the messages themselves, JSON objects
    (its session wrapper skips SockJS's quoting them as strings): clients expect that."""
    return "a[" + ",".join(frame.text for frame in frames) + "]"


def _close_frame(code: int, reason: str) -> str:
    return f"c[{code},{json.dumps(reason)}]"


GO_AWAY = _close_frame(3000, "Go away!")
ANOTHER = _close_frame(2010, "Another connection still open")


def _cors(request: Request, methods: str | None = None) -> dict[str, str]:
    """SockJS's CORS headers: the origin that asked, with credentials (as sockjs-tornado)."""
    headers = {
        "Access-Control-Allow-Origin": request.headers.get("origin", "*"),
        "Access-Control-Allow-Credentials": "true",
    }
    asked = request.headers.get("access-control-request-headers")
    if asked:
        headers["Access-Control-Allow-Headers"] = asked
    if methods is not None:
        headers["Access-Control-Allow-Methods"] = methods
        headers["Allow"] = methods
        headers["Cache-Control"] = "max-age=31536000, public"
        headers["Access-Control-Max-Age"] = "31536000"
    return headers


NO_CACHE = {"Cache-Control": "no-store, no-cache, must-revalidate, max-age=0"}


class XhrSession:
    """A SockJS session of the xhr transports: its client outlives each request, and is
    closed once no request waited on it for :data:`DISCONNECT_DELAY` seconds."""

    def __init__(self, push: Push, key: tuple[str, str], client: Client) -> None:
        self.push = push
        self.key = key
        self.client = client
        self.attached = False
        self.opened = False  # its "o" frame went
        self._expiry: asyncio.TimerHandle | None = None
        self._detached()

    def attach(self) -> None:
        self.attached = True
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def detach(self) -> None:
        self.attached = False
        self._detached()

    def _detached(self) -> None:
        loop = asyncio.get_running_loop()
        self._expiry = loop.call_later(DISCONNECT_DELAY, self.end)

    def end(self) -> None:
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        self.client.close("the SockJS session ended")
        if self.push.sessions.get(self.key) is self:
            del self.push.sessions[self.key]


class XhrResponse(Response):
    """An xhr-streaming (``streaming``) or xhr-polling response of a SockJS session."""

    media_type = "application/javascript; charset=UTF-8"

    def __init__(self, session: XhrSession, streaming: bool, headers: dict[str, str]) -> None:
        super().__init__(headers=headers)
        self.session = session
        self.streaming = streaming

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        session, client = self.session, self.session.client
        headers = [(k, v) for k, v in self.raw_headers if k != b"content-length"]
        await send({"type": "http.response.start", "status": 200, "headers": headers})

        async def body(text: str, more: bool = True) -> None:
            await send({"type": "http.response.body", "body": text.encode(), "more_body": more})

        if self.streaming:
            await body("h" * 2048 + "\n")
        if client.closed:
            await body(GO_AWAY + "\n", False)
            return
        if session.attached:
            await body(ANOTHER + "\n", False)
            return
        session.attach()
        writer = asyncio.ensure_future(self._write(body))
        client.writer = writer
        gone = asyncio.ensure_future(_disconnected(receive))
        try:
            await asyncio.wait({writer, gone}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            writer.cancel()
            gone.cancel()
            client.writer = None
            if (gone.done() and not gone.cancelled()) or client.closed:
                session.end()  # the client went (or was dropped): as sockjs-tornado
            else:
                session.detach()
        if writer.done() and not writer.cancelled() and writer.exception() is None:
            await body("", False)

    async def _write(self, body: Callable[[str, bool], Any]) -> None:
        session, client = self.session, self.session.client
        if not session.opened:
            session.opened = True
            await body("o\n", True)
            if not self.streaming:
                return
        sent = 0
        while sent < RESPONSE_LIMIT:
            frames = await client.take(HEARTBEAT)
            if client.closed:
                await body(GO_AWAY + "\n", True)
                return
            chunk = (_array(frames) if frames else "h") + "\n"
            await body(chunk, True)
            if not self.streaming:
                return
            sent += len(chunk)


async def _disconnected(receive: Receive) -> None:
    while (await receive())["type"] != "http.disconnect":
        pass


class SocketEndpoint:
    """A websocket: SockJS framed (``o``, ``h``, ``a[...]``, ``c[...]``) or raw (one JSON
    object a message). A plain ASGI app: each message goes out in one ASGI send."""

    def __init__(self, push: Push, sockjs: bool) -> None:
        self.push = push
        self.sockjs = sockjs

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (await receive())["type"] != "websocket.connect":
            return
        try:
            feed = self.push.feed(scope.get("path_params", {}).get("printer"))
        except HTTPException:
            await send({"type": "websocket.close", "code": 1008})  # no such printer
            return
        await send({"type": "websocket.accept"})
        sockjs = self.sockjs
        address = scope["client"][0] if scope.get("client") else ""
        client = Client(feed, f"{address} ({'SockJS' if sockjs else 'raw'} websocket)")

        async def text(message: str) -> None:
            await send({"type": "websocket.send", "text": message})

        async def write() -> None:
            if sockjs:
                await text("o")
            while True:
                frames = await client.take(HEARTBEAT if sockjs else None)
                if client.closed:
                    if sockjs:
                        await text(GO_AWAY)
                    await send({"type": "websocket.close", "code": 3000, "reason": "Go away!"})
                    return
                if sockjs:
                    await text(_array(frames) if frames else "h")
                else:
                    for frame in frames:
                        await text(frame.text)

        async def read() -> None:
            while True:
                message = await receive()
                if message["type"] == "websocket.disconnect":
                    client.close(f"the client went (code {message.get('code')})")
                    return
                data = message.get("text")
                if data is None:
                    data = (message.get("bytes") or b"").decode("utf-8", "replace")
                if not data or len(data) > INCOMING_MOST:
                    continue  # SockJS: an empty message is ignored
                for each in _sockjs_messages(data) if sockjs else (data,):
                    client.receive(each)

        writer = asyncio.ensure_future(write())
        reader = asyncio.ensure_future(read())
        client.writer = writer
        feed.add(client)
        try:
            await asyncio.wait({writer, reader}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            client.close("the connection ended")
            for task in (writer, reader):
                task.cancel()
            await asyncio.gather(writer, reader, return_exceptions=True)


def router(push: Push) -> APIRouter:
    """The push socket's routes: include at the root and under ``/printers/{printer}``."""
    router = APIRouter(include_in_schema=False)

    @router.get("/sockjs")
    @router.get("/sockjs/")
    async def greeting() -> PlainTextResponse:
        return PlainTextResponse("Welcome to SockJS!\n")

    @router.get("/sockjs/info")
    async def info(request: Request) -> JSONResponse:
        push.server.service(request.path_params.get("printer"))  # 404: no such printer
        return JSONResponse(
            {
                "websocket": True,
                "cookie_needed": False,
                "origins": ["*:*"],
                "entropy": random.randint(0, 2**31 - 1),
            },
            headers={**_cors(request), **NO_CACHE},
        )

    @router.options("/sockjs/info")
    async def info_options(request: Request) -> Response:
        return Response(status_code=204, headers=_cors(request, "OPTIONS, GET"))

    router.routes.append(WebSocketRoute("/sockjs/websocket", SocketEndpoint(push, False)))
    sockjs = SocketEndpoint(push, True)
    router.routes.append(WebSocketRoute("/sockjs/{server_id}/{session_id}/websocket", sockjs))

    def session_of(request: Request, session_id: str, create: bool) -> XhrSession | None:
        if _SESSION_ID.fullmatch(session_id) is None:
            raise HTTPException(404, "not a SockJS session id")
        feed = push.feed(request.path_params.get("printer"))
        key = (feed.name, session_id)
        session = push.sessions.get(key)
        if session is None and create:
            address = request.client.host if request.client is not None else ""
            client = Client(feed, f"{address} (SockJS xhr)")
            session = push.sessions[key] = XhrSession(push, key, client)
            feed.add(client)
        return session

    async def xhr(request: Request, session_id: str, streaming: bool) -> XhrResponse:
        session = session_of(request, session_id, create=True)
        assert session is not None
        return XhrResponse(session, streaming, {**_cors(request), **NO_CACHE})

    @router.post("/sockjs/{server_id}/{session_id}/xhr_streaming")
    async def xhr_streaming(request: Request, server_id: str, session_id: str) -> XhrResponse:
        return await xhr(request, session_id, streaming=True)

    @router.post("/sockjs/{server_id}/{session_id}/xhr")
    async def xhr_polling(request: Request, server_id: str, session_id: str) -> XhrResponse:
        return await xhr(request, session_id, streaming=False)

    @router.post("/sockjs/{server_id}/{session_id}/xhr_send")
    async def xhr_send(request: Request, server_id: str, session_id: str) -> Response:
        session = session_of(request, session_id, create=False)
        headers = {**_cors(request), **NO_CACHE}
        if session is None or session.client.closed:
            return PlainTextResponse("no such SockJS session", 404, headers=headers)
        body = await request.body()
        if not body:
            return PlainTextResponse("Payload expected.", 400, headers=headers)
        if len(body) > INCOMING_MOST:
            return PlainTextResponse("the message is too long", 413, headers=headers)
        try:
            messages = json.loads(body)
        except ValueError:
            return PlainTextResponse("Broken JSON encoding.", 400, headers=headers)
        for message in messages if isinstance(messages, list) else (messages,):
            session.client.receive(message)
        return Response(status_code=204, headers={**headers, "Content-Type": "text/plain"})

    for transport in ("xhr", "xhr_streaming", "xhr_send"):

        @router.options(f"/sockjs/{{server_id}}/{{session_id}}/{transport}")
        async def xhr_options(request: Request, server_id: str, session_id: str) -> Response:
            return Response(status_code=204, headers=_cors(request, "OPTIONS, POST"))

    return router
