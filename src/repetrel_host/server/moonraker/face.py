"""What Moonraker's face keeps beside the server: its websockets (told of the server's
events), each printer's objects and G-code store, the one-shot tokens."""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from repetrel_host.server.events import PrinterMessage, ServerEvent
from repetrel_host.server.moonraker.database_store import Database
from repetrel_host.server.moonraker.host import Usage, own_memory, system_memory
from repetrel_host.server.moonraker.objects import Objects
from repetrel_host.server.print_server import PrintServer

log = logging.getLogger("repetrel_host.server.moonraker")

GCODE_STORE = 1000  # Moonraker's gcode_store_size
DATABASE = "moonraker-database.sqlite"  # in the data folder
ONESHOT_SECONDS = 5.0


class Subscriber(Protocol):
    """A websocket as the face sees it: its printer, and how it is told things."""

    id: int
    printer: str
    client: dict[str, Any]
    user: str | None
    refused: bool  # its identify named a wrong key

    def heard(self, event: ServerEvent) -> None: ...

    def send_later(self, method: str, params: list[Any] | None = None) -> None: ...

    def subscribe(self, wanted: dict[str, list[str] | None]) -> dict[str, Any]: ...

    async def close(self) -> None: ...


class MoonrakerFace:
    """What the face keeps beside the server: its websockets, each printer's G-code store
    (commands and responses, as a console shows them), the one-shot tokens."""

    def __init__(self, server: PrintServer) -> None:
        self.server = server
        self.connections: dict[int, Subscriber] = {}
        self.gcode_store: dict[str, deque[dict[str, Any]]] = {
            name: deque(maxlen=GCODE_STORE) for name in server.services
        }
        self.objects = {name: Objects(service) for name, service in server.services.items()}
        self.tokens: dict[str, tuple[str | None, float]] = {}
        self.listeners: list[Callable[[ServerEvent], None]] = []
        self.started = time.time()
        # Its namespaces (server.database.*); a data folder of an earlier version kept them
        # in the job store, moved from there once.
        self.database = Database(server.data_dir / DATABASE, legacy=server.store.path)
        self.usage = Usage()
        self._stats: tuple[float, dict[str, Any]] = (0.0, {})  # the last, and when
        self._task: asyncio.Task[None] | None = None

    # --- the server's events ----------------------------------------------------------

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._listen(), name="moonraker")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        for connection in list(self.connections.values()):
            await connection.close()
        await asyncio.to_thread(self.database.close)

    async def _listen(self) -> None:
        async with self.server.events.listen() as events:
            async for event in events:
                try:
                    self._heard(event)
                except Exception:  # a bug must not silence every later event
                    log.exception("the Moonraker face could not pass on %s", event.type)

    def _heard(self, event: ServerEvent) -> None:
        if isinstance(event, PrinterMessage):
            self.gcode_response(event.printer, event.text)
        for listener in self.listeners:
            listener(event)
        for connection in list(self.connections.values()):
            if event.printer in (None, connection.printer):
                connection.heard(event)

    def gcode_command(self, printer: str, line: str) -> None:
        """A console's command, kept in the printer's G-code store."""
        self.gcode_store[printer].append({"message": line, "time": time.time(), "type": "command"})

    def gcode_response(self, printer: str, text: str) -> None:
        """A response line: kept, and told to the printer's websockets."""
        self.gcode_store[printer].append({"message": text, "time": time.time(), "type": "response"})
        self.notify(printer, "notify_gcode_response", [text])

    def notify(self, printer: str | None, method: str, params: list[Any] | None = None) -> None:
        """A notification to every websocket of ``printer`` (None: all of them)."""
        for connection in list(self.connections.values()):
            if printer in (None, connection.printer):
                connection.send_later(method, params)

    # --- one-shot tokens (a browser cannot set a header on its websocket) -------------

    def oneshot(self, user: str | None) -> str:
        """A token good for one request within 5 s, on behalf of ``user``."""
        now = time.monotonic()
        self.tokens = {t: kept for t, kept in self.tokens.items() if kept[1] > now}
        token = os.urandom(16).hex().upper()
        self.tokens[token] = (user, now + ONESHOT_SECONDS)
        return token

    def redeem(self, token: str) -> tuple[bool, str | None]:
        """(whether ``token`` is a live one-shot token, its user); used up either way."""
        kept = self.tokens.pop(token, None)
        if kept is None or kept[1] < time.monotonic():
            return False, None
        return True, kept[0]

    # --- statistics -----------------------------------------------------------------

    def proc_stats(self) -> dict[str, Any]:
        """Moonraker's process statistics (``notify_proc_stat_update``, ``machine.proc_stats``'s
        latest sample): made once a second, whoever asks."""
        made, stats = self._stats
        now = time.monotonic()
        if now - made < 0.9:
            return {**stats, "websocket_connections": len(self.connections)}
        usage = os.times()
        busy = (usage.user + usage.system) / max(time.time() - self.started, 1)
        cpus, network = self.usage.sample()
        stats = {
            "moonraker_stats": {
                "time": time.time(),
                "cpu_usage": round(100 * busy, 2),
                "memory": own_memory(),
                "mem_units": "kB",
            },
            "cpu_temp": None,
            "network": network,
            "system_cpu_usage": cpus,
            "system_memory": system_memory(),
            "websocket_connections": len(self.connections),
        }
        self._stats = (now, stats)
        return stats
