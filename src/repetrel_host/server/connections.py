"""Connections that send nothing cannot crowd the server out (slowloris).

uvicorn waits for a request's head as long as a client likes and takes connections until
the process runs out of file descriptors: then it accepts none (a keyed client waits in
the queue), a printer's port cannot be reopened after a link drop (its safe stop waits),
and asyncio logs a traceback for each accept it tries. Here:

- a connection must send a complete request head within ``header_timeout`` seconds of
  connecting (or of its last answer, kept alive): else it is closed;
- the server holds at most ``max_connections`` connections (HTTP and websockets): past
  them, the oldest connection waiting for a request head is closed (one that never sent a
  request before one kept alive after its answer), so a client that asks at once (a keyed
  client, the page) gets in; the file limit keeps
  :data:`RESERVED_FILES` more for the printers' ports, the database, logs and workers;
- a refusal is logged once a minute per kind, with how many there were.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import logging
import resource
import time
from typing import Any, cast

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("repetrel_host.server")

# File descriptors kept for what is not a connection: printers' ports (reopened at each
# reconnect), the database, the data folder's files, logs, the file workers' pipes, MQTT
# and the farm's database. With settings.py's default of 768 connections, these make the
# usual limit of 1,024, so that every descriptor stays below 1,024 (pyserial's select(),
# a URL link's, takes no higher one).
RESERVED_FILES = 256
# asyncio accepts up to the listening socket's backlog of connections at each wake-up,
# before the guard sees any of them: a small one keeps that burst within the reserve
# (uvicorn's 2,048 took every descriptor at once).
BACKLOG = 64
LOG_EVERY = 60.0  # s between two lines of one kind of refusal
CLOSED_A_TURN = 64  # late connections closed in one turn of the event loop
# A connection closed with a request's body still coming (a refusal before the body was
# read: 413, 403) is first only shut for writing, and what still comes is dropped for up
# to this long or this much: closed at once, with bytes unread, the kernel resets it and
# the client may never see the answer.
LINGER = 2.0  # s
LINGER_BYTES = 1024 * 1024


class RefusalLog:
    """One log line per kind of refusal per :data:`LOG_EVERY` seconds: the first at
    once, the rest counted and said in one line when the time is up."""

    def __init__(self, every: float = LOG_EVERY) -> None:
        self.every = every
        self._last: dict[str, float] = {}  # kind: when it was last said
        self._unsaid: dict[str, tuple[str, int]] = {}  # kind: its sentence, how many since

    def note(self, kind: str, sentence: str) -> None:
        """One refusal of ``kind``, said by ``sentence``."""
        now = time.monotonic()
        last = self._last.get(kind)
        if last is None or now - last >= self.every:
            self._say(kind, sentence, 1)
            return
        _, count = self._unsaid.get(kind, (sentence, 0))
        self._unsaid[kind] = (sentence, count + 1)
        if count == 0:  # the first held back: said when the minute is up
            with contextlib.suppress(RuntimeError):  # no loop: said with the next one
                asyncio.get_running_loop().call_later(last + self.every - now, self._flush, kind)

    def _flush(self, kind: str) -> None:
        sentence, count = self._unsaid.pop(kind, ("", 0))
        if count:
            self._say(kind, sentence, count)

    def _say(self, kind: str, sentence: str, count: int) -> None:
        sentence, before = self._unsaid.pop(kind, (sentence, 0))
        count += before
        self._last[kind] = time.monotonic()
        times = f" ({count} times in the last minute)" if count > 1 else ""
        log.warning("%s%s", sentence, times)


refusals = RefusalLog()

# What asyncio and uvicorn log for each connection they could not take or read: one line
# a minute instead (a traceback per accept filled hundreds of MB of log in a minute).
_REPEATED = {
    "socket.accept() out of system resource": (
        "files",
        "out of file descriptors: new connections wait (raise LimitNOFILE, or lower "
        "max_connections)",
    ),
    "Invalid HTTP request received.": ("invalid", "refused invalid HTTP requests"),
}


class QuietRepeats(logging.Filter):
    """asyncio's and uvicorn's line for each refused connection, as :data:`refusals`."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = str(record.msg)
        # uvicorn's two lines for each websocket refused before its upgrade (another site's
        # page, no key, a name not served): one count, said once a minute.
        if message.startswith('%s - "WebSocket %s"') and "[accepted]" not in message:
            refusals.note("websocket", "refused websocket upgrades")
            return False
        if message.startswith("connection rejected ("):
            return False  # the second line of the same refusal
        for start, (kind, sentence) in _REPEATED.items():
            if message.startswith(start):
                refusals.note(kind, sentence)
                return False
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, OSError) and exc.errno in (errno.EMFILE, errno.ENFILE):
            refusals.note("files", _REPEATED["socket.accept() out of system resource"][1])
            return False
        return True


def quiet_repeats() -> None:
    """Put :class:`QuietRepeats` on the loggers that repeat (after uvicorn set its own)."""
    for name in ("asyncio", "uvicorn.error"):
        logging.getLogger(name).addFilter(QuietRepeats())


def connection_limit(wanted: int) -> int:
    """How many connections the server holds: ``wanted``, within the file limit (raised to
    the hard one when ``wanted`` needs more) less :data:`RESERVED_FILES`."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = wanted + RESERVED_FILES
    if soft < needed:
        raised = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (raised, hard))
            soft = raised
    limit = max(16, min(wanted, soft - RESERVED_FILES))
    if limit < wanted:
        log.warning(
            "at most %d connections, not max_connections %d: the file limit is %d, and %d "
            "of them are kept for the printers and the server's files (raise LimitNOFILE)",
            limit,
            wanted,
            soft,
            RESERVED_FILES,
        )
    return limit


class ConnectionGuard:
    """The connections waiting for a request head, oldest first, each with its deadline:
    the new ones, and those kept alive after an answer; the limit of connections held."""

    def __init__(self, limit: int, header_timeout: float) -> None:
        self.limit = limit
        self.header_timeout = header_timeout
        self.new: dict[GuardedH11Protocol, asyncio.TimerHandle] = {}  # no request yet
        self.kept: dict[GuardedH11Protocol, asyncio.TimerHandle] = {}  # between two
        self.closing: set[GuardedH11Protocol] = set()  # closed here, not yet gone
        self.late: collections.deque[GuardedH11Protocol] = collections.deque()  # to close

    def options(self) -> dict[str, Any]:
        """uvicorn's ``Config`` options: its HTTP protocol class, answering to this guard,
        and the listening socket's backlog."""
        protocol = type("GuardedH11Protocol", (GuardedH11Protocol,), {"guard": self})
        return {"http": protocol, "backlog": BACKLOG}

    def arrived(self, connection: GuardedH11Protocol) -> None:
        """A new connection: it waits for its head; past the limit, the oldest waiting
        connections are closed: those that never sent a request first (a slow client's
        kept connection costs it a reconnect), this one if no other waits."""
        self.waits(connection, self.new)
        held = len(connection.connections) - len(self.closing)  # uvicorn's: every one
        for _ in range(held - self.limit):
            waiting = self.new or self.kept
            if not waiting:
                break
            refusals.note(
                "crowded",
                f"at {self.limit} connections: closed the oldest that had sent no request",
            )
            self.close(next(iter(waiting)))

    def answered(self, connection: GuardedH11Protocol) -> None:
        """``connection`` was answered and is kept alive: it waits for its next head."""
        self.waits(connection, self.kept)

    def waits(
        self, connection: GuardedH11Protocol, waiting: dict[GuardedH11Protocol, asyncio.TimerHandle]
    ) -> None:
        self.headed(connection)
        waiting[connection] = connection.loop.call_later(
            self.header_timeout, self._late, connection
        )

    def headed(self, connection: GuardedH11Protocol) -> None:
        """``connection`` sent a whole request head (or went): it waits no more."""
        for waiting in (self.new, self.kept):
            timer = waiting.pop(connection, None)
            if timer is not None:
                timer.cancel()

    def gone(self, connection: GuardedH11Protocol) -> None:
        self.headed(connection)
        self.closing.discard(connection)

    def _late(self, connection: GuardedH11Protocol) -> None:
        refusals.note(
            "late",
            f"closed connections that sent no complete request within {self.header_timeout:g} s",
        )
        # Connections opened in one burst are late in one burst: closing 1,100 of them in
        # one turn of the loop held it 60 ms. A few each turn, the rest in the next ones.
        self.late.append(connection)
        if len(self.late) == 1:
            connection.loop.call_soon(self._close_late)

    def _close_late(self) -> None:
        for _ in range(min(CLOSED_A_TURN, len(self.late))):
            connection = self.late.popleft()
            if connection in self.new or connection in self.kept:  # its head still not sent
                self.close(connection)
        if self.late:
            asyncio.get_running_loop().call_soon(self._close_late)

    def close(self, connection: GuardedH11Protocol) -> None:
        self.headed(connection)
        transport = connection.transport
        if transport.is_closing():
            return
        self.closing.add(connection)
        with contextlib.suppress(h11.LocalProtocolError):
            connection.conn.send(h11.ConnectionClosed())
        transport.close()


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, telling its :class:`ConnectionGuard` when a connection
    comes, sends a request head, waits for the next one, and goes; and closing a
    connection whose request body is still coming with a lingering close."""

    guard: ConnectionGuard
    dropped: int | None = None  # lingering: the bytes dropped since

    def connection_made(self, transport: Any) -> None:
        super().connection_made(cast(asyncio.Transport, LingeringClose(transport, self)))
        self.guard.arrived(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.guard.gone(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self.dropped is None:
            super().data_received(data)
            return
        self.dropped += len(data)  # the rest of a refused body: read for nothing
        if self.dropped > LINGER_BYTES:
            self.transport.close()

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        # A new request began (a new cycle), or the connection became a websocket.
        if self.cycle is not cycle or self.transport.get_protocol() is not self:
            self.guard.headed(self)

    def on_response_complete(self) -> None:
        if not self.transport.is_closing():
            self.guard.answered(self)  # kept alive: the next head has its deadline too
        super().on_response_complete()


class LingeringClose:
    """A connection's transport as its :class:`GuardedH11Protocol` sees it: closed while
    the request's body still comes, it sends what was written and a FIN, drops what comes
    for :data:`LINGER` seconds or :data:`LINGER_BYTES`, and then closes."""

    def __init__(self, transport: Any, protocol: GuardedH11Protocol) -> None:
        self._transport = transport
        self._protocol = protocol

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)

    def is_closing(self) -> bool:
        return self._protocol.dropped is not None or bool(self._transport.is_closing())

    def close(self) -> None:
        transport, protocol = self._transport, self._protocol
        body_coming = (
            transport.get_protocol() is protocol  # not a websocket by now
            and protocol.conn.their_state is h11.SEND_BODY
            and protocol.dropped is None
            and transport.can_write_eof()
            and not transport.is_closing()
        )
        if not body_coming:
            transport.close()
            return
        protocol.dropped = 0
        transport.write_eof()
        transport.resume_reading()
        protocol.loop.call_later(LINGER, transport.close)
