"""MQTT for farms: the server's events published under ``<prefix>/<printer>/...``.

- ``state`` (retained): ``{"state": "ready", "held": false}``
- ``job`` (retained): the printer's current or last job (with its M773 ``report``, if any)
- ``progress`` (retained): lines, the file line, bytes of the running job, its
  ``completion`` (%), ``time_left`` (seconds: the plan's remainder at the run's pace, the
  one figure every face gives) and ``ends``
- ``temperatures`` (retained): ``{"readings": {"T": [actual, target], "B": [...]}}``
- ``snapshot`` (retained): the camera's newest image, ``{"file": ..., "url": "/v1/..."}``
- ``message``: the controller's messages
- ``<prefix>/server/online`` (retained): ``true``, and ``false`` as the will (the broker says
  it when the server vanishes).

Retained, so a dashboard that starts later sees how things stand. Home Assistant's
discovery configs (:mod:`repetrel_host.server.mqtt.homeassistant`) go to its discovery prefix
unless turned off, so that each printer appears there as a device. Commands are taken on
``<prefix>/<printer>/command`` only when allowed (MQTT has no per-topic secret unless the
broker enforces one): ``pause``, ``resume``, ``cancel``, ``release``, or one G-code line,
answered on ``<prefix>/<printer>/reply``. The broker may come and go: the bridge connects
again with backoff and never stops the server.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from dataclasses import dataclass
from typing import Any, Protocol

import aiomqtt

from repetrel_host.server.events import (
    EventHub,
    JobChanged,
    PrinterMessage,
    PrinterState,
    PrintProgress,
    ServerEvent,
    SnapshotTaken,
    TemperatureReadings,
)
from repetrel_host.server.mqtt.homeassistant import DEFAULT_PREFIX, Discovery
from repetrel_host.server.printers.service import PrinterService, Refused
from repetrel_host.server.store import Store

log = logging.getLogger("repetrel_host.server")

RECONNECT_FIRST = 1.0
RECONNECT_MAX = 30.0
ACTIONS = ("pause", "resume", "cancel", "release")
# The events published, each under its printer's topic, and whether that is retained.
_TOPICS: dict[type[ServerEvent], tuple[str, bool]] = {
    PrinterState: ("state", True),
    JobChanged: ("job", True),
    PrintProgress: ("progress", True),
    TemperatureReadings: ("temperatures", True),
    SnapshotTaken: ("snapshot", True),
    PrinterMessage: ("message", False),
}


@dataclass(frozen=True)
class MqttSettings:
    host: str
    port: int = 1883
    prefix: str = "hyrel"
    commands: bool = False
    username: str | None = None
    password: str | None = None
    discovery_prefix: str | None = DEFAULT_PREFIX  # Home Assistant's; None: no discovery


class Served(Protocol):
    """What the bridge reads of the print server (the app's
    :class:`~repetrel_host.server.print_server.PrintServer`, whose lifespan starts the bridge)."""

    events: EventHub
    services: dict[str, PrinterService]
    store: Store

    def printer_uuid(self, name: str) -> str: ...


class MqttBridge:
    """Publishes the server's events to a broker; takes commands when allowed."""

    def __init__(self, server: Served, settings: MqttSettings) -> None:
        self.server = server
        self.settings = settings
        self.prefix = settings.prefix.rstrip("/")
        self.discovery: Discovery | None = None
        if settings.discovery_prefix is not None:
            discovery_prefix = settings.discovery_prefix.rstrip("/")
            self.discovery = Discovery(self.prefix, discovery_prefix, settings.commands)
        self._heaters: dict[str, set[str]] = {}  # each printer's heaters announced

    async def run(self) -> None:
        delay = RECONNECT_FIRST
        settings = self.settings
        online = f"{self.prefix}/server/online"
        while True:
            try:
                async with aiomqtt.Client(
                    settings.host,
                    settings.port,
                    username=settings.username,
                    password=settings.password,
                    will=aiomqtt.Will(online, b"false", qos=1, retain=True),
                ) as client:
                    log.info("mqtt: connected to %s:%d", settings.host, settings.port)
                    delay = RECONNECT_FIRST
                    await self._session(client, online)
            except aiomqtt.MqttError as exc:
                log.warning("mqtt: %s (trying again in %.0f s)", exc, delay)
                await asyncio.sleep(delay)
                delay = min(delay * 2, RECONNECT_MAX)

    async def _session(self, client: aiomqtt.Client, online: str) -> None:
        try:
            await self._forward(client, online)
        finally:  # the server stopping: say so (the will says it for a crash)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.publish(online, b"false", qos=1, retain=True), 2)

    async def _forward(self, client: aiomqtt.Client, online: str) -> None:
        # Listening before the snapshot: none lost.
        async with self.server.events.listen(kinds=tuple(_TOPICS)) as events:
            await client.publish(online, b"true", qos=1, retain=True)
            self._heaters.clear()  # announced again: the broker may have lost them
            for service in self.server.services.values():
                await self._announce(client, service.name)
                await self._publish(client, PrinterState(service.name, service.state, service.held))
                last = self.server.store.last_started(service.name)
                if last is not None:
                    await self._publish(client, JobChanged(service.name, last))
            if self.settings.commands:
                await client.subscribe(f"{self.prefix}/+/command", qos=1)
            async with asyncio.TaskGroup() as group:
                group.create_task(self._commands(client))
                async for event in events:
                    await self._publish(client, event)

    async def _announce(self, client: aiomqtt.Client, name: str) -> None:
        """Home Assistant's discovery configs of printer ``name`` (retained), with every
        heater it reported so far (its hotend and bed at least)."""
        if self.discovery is None:
            return
        service = self.server.services[name]
        known = service.printer.temperatures if service.printer is not None else {}
        heaters = {"T", "B", *known}
        uuid = self.server.printer_uuid(name)
        for topic, payload in self.discovery.printer(name, uuid, sorted(heaters)):
            await client.publish(topic, json.dumps(payload).encode(), 1, True)
        self._heaters[name] = heaters

    async def _announce_heaters(self, client: aiomqtt.Client, event: TemperatureReadings) -> None:
        """A heater reported for the first time (a chamber, a second hotend): its sensors."""
        name = event.printer
        announced = self._heaters.get(name)
        if self.discovery is None or announced is None:
            return
        new = sorted(set(event.readings) - announced)
        if not new:
            return
        uuid = self.server.printer_uuid(name)
        for topic, payload in self.discovery.heaters(name, uuid, new):
            await client.publish(topic, json.dumps(payload).encode(), 1, True)
        announced.update(new)

    async def _publish(self, client: aiomqtt.Client, event: ServerEvent) -> None:
        published = _TOPICS.get(type(event))
        if published is None:
            return
        topic, retain = published
        if isinstance(event, TemperatureReadings):
            await self._announce_heaters(client, event)
        if isinstance(event, PrinterMessage):
            text = event.text  # a message is the controller's line itself
        else:
            fields = {k: v for k, v in event.as_json().items() if k not in ("type", "printer")}
            text = json.dumps(fields)
        await client.publish(f"{self.prefix}/{event.printer}/{topic}", text.encode(), 1, retain)

    async def _commands(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            parts = str(message.topic).split("/")
            name = parts[-2] if len(parts) >= 2 else ""
            service = self.server.services.get(name)
            if service is None or not isinstance(message.payload, bytes | bytearray):
                continue
            text = bytes(message.payload).decode("utf-8", errors="replace").strip()
            answer = await self._command(name, text)
            await client.publish(f"{self.prefix}/{name}/reply", json.dumps(answer).encode(), 1)

    async def _command(self, name: str, text: str) -> dict[str, Any]:
        service = self.server.services[name]
        log.info("mqtt: printer %s: %s", name, text)
        try:
            if text.lower() in ACTIONS:
                await service.control(text.lower())
                return {"command": text, "ok": True}
            reply = await service.command(text)
        except Refused as exc:
            return {"command": text, "ok": False, "error": str(exc)}
        return {"command": text, "ok": True, "lines": reply.lines, "reply": reply.ok_line}
