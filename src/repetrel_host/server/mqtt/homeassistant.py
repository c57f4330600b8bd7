"""Home Assistant's MQTT discovery: each printer appears in Home Assistant by itself when
both use the same broker, without a cloud or an integration to install.

Each printer is one Home Assistant device (its identifiers from the printer's stable UUID)
whose entities read the server's own topics (:mod:`repetrel_host.server.mqtt.bridge`): its state,
progress (%), time left, current file, each heater's temperature and target, and, when
MQTT commands are on, pause/resume/cancel buttons that publish to its command topic. Every
entity is available while ``<prefix>/server/online`` says ``true``.

The configs are retained on ``<discovery prefix>/<component>/hyrel_<uuid>/<entity>/config``
(Home Assistant's discovery topic: ``[a-zA-Z0-9_-]`` ids), as its MQTT discovery
documentation describes them (``device``, ``unique_id``, ``state_topic``,
``value_template``, ``availability_topic``, ``command_topic``, ``payload_press``...).
A template that renders ``None`` (no job yet, no estimate) leaves the sensor unknown.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from repetrel_host import __version__
from repetrel_host.session.events import State

DEFAULT_PREFIX = "homeassistant"
BUTTONS = ("pause", "resume", "cancel")
Config = tuple[str, dict[str, Any]]  # (topic, payload)


@dataclass(frozen=True)
class Discovery:
    """Where the configs go (``discovery_prefix``), the server's own topic prefix that
    they read, and whether commands are taken (the buttons)."""

    prefix: str
    discovery_prefix: str = DEFAULT_PREFIX
    commands: bool = False

    def printer(self, name: str, uuid: str, heaters: Iterable[str] = ("T", "B")) -> list[Config]:
        """Every config of printer ``name``: its sensors, its heaters', its buttons."""
        topics = f"{self.prefix}/{name}"
        configs = [
            self._entity(
                name,
                uuid,
                "sensor",
                "state",
                {
                    "name": "State",
                    "state_topic": f"{topics}/state",
                    "value_template": "{{ value_json.state }}",
                    "device_class": "enum",
                    "options": [state.value for state in State],
                    "icon": "mdi:printer-3d",
                },
            ),
            self._entity(
                name,
                uuid,
                "sensor",
                "progress",
                {
                    "name": "Progress",
                    "state_topic": f"{topics}/progress",
                    "value_template": "{{ value_json.completion }}",
                    "unit_of_measurement": "%",
                    "state_class": "measurement",
                    "suggested_display_precision": 1,
                    "icon": "mdi:progress-clock",
                },
            ),
            self._entity(
                name,
                uuid,
                "sensor",
                "time_left",
                {
                    "name": "Time left",
                    "state_topic": f"{topics}/progress",
                    "value_template": "{{ value_json.time_left }}",
                    "device_class": "duration",
                    "unit_of_measurement": "s",
                },
            ),
            self._entity(
                name,
                uuid,
                "sensor",
                "print_end",
                {
                    "name": "Print end",
                    "state_topic": f"{topics}/progress",
                    "value_template": "{{ value_json.ends }}",
                    "device_class": "timestamp",
                },
            ),
            self._entity(
                name,
                uuid,
                "sensor",
                "file",
                {
                    "name": "File",
                    "state_topic": f"{topics}/job",
                    "value_template": "{{ value_json.job.name }}",
                    "icon": "mdi:file-outline",
                },
            ),
            *self.heaters(name, uuid, heaters),
        ]
        if self.commands:
            configs += [
                self._entity(
                    name,
                    uuid,
                    "button",
                    action,
                    {
                        "name": action.capitalize(),
                        "command_topic": f"{topics}/command",
                        "payload_press": action,
                        "icon": f"mdi:{action if action != 'cancel' else 'stop'}",
                    },
                )
                for action in BUTTONS
            ]
        return configs

    def heaters(self, name: str, uuid: str, sensors: Iterable[str]) -> list[Config]:
        """A temperature and a target sensor for each heater the printer reports (``T``,
        ``T1``, ``B``, ``C``: the keys of its ``temperatures`` topic)."""
        configs: list[Config] = []
        for sensor in sensors:
            label = heater_label(sensor)
            slug = label.lower().replace(" ", "_")
            for index, what in enumerate(("temperature", "target")):
                payload = {
                    "name": f"{label} {what}",
                    "state_topic": f"{self.prefix}/{name}/temperatures",
                    "value_template": f"{{{{ value_json.readings['{sensor}'][{index}] }}}}",
                    "device_class": "temperature",
                    "unit_of_measurement": "°C",
                    "state_class": "measurement",
                }
                configs.append(self._entity(name, uuid, "sensor", f"{slug}_{what}", payload))
        return configs

    def _entity(
        self, name: str, uuid: str, component: str, key: str, fields: dict[str, Any]
    ) -> Config:
        node = f"hyrel_{uuid}"
        payload = {
            **fields,
            "unique_id": f"{node}_{key}",
            "availability_topic": f"{self.prefix}/server/online",
            "payload_available": "true",
            "payload_not_available": "false",
            "device": {
                "identifiers": [node],
                "name": name,
                "manufacturer": "repetrel-host",
                "model": "hyrel-server printer",
                "sw_version": __version__,
            },
            "origin": {"name": "hyrel-server", "sw_version": __version__},
        }
        return f"{self.discovery_prefix}/{component}/{node}/{key}/config", payload


def heater_label(sensor: str) -> str:
    """``T`` Hotend, ``T1`` Hotend T1, ``B`` Bed, ``C`` Chamber (another: its own name)."""
    if sensor == "T":
        return "Hotend"
    if sensor.startswith("T"):
        return f"Hotend {sensor}"
    return {"B": "Bed", "C": "Chamber"}.get(sensor, sensor)
