"""The push socket's messages as they are written: each serialized once for all the
clients that get it (:class:`Frame`), what a client subscribed to (OctoPrint's
``subscribe``), and the ``connected`` message a client gets first."""

from __future__ import annotations

import hashlib
import json
import platform
import re
import time
from dataclasses import dataclass
from typing import Any

from repetrel_host.server.access import PERMISSIONS
from repetrel_host.server.octoprint.version import OCTOPRINT_VERSION
from repetrel_host.server.print_server import PrintServer


def dumps(value: Any) -> str:
    """``value`` as compact JSON, as every message goes out."""
    return json.dumps(value, separators=(",", ":"))


class Frame:
    """One message, serialized once for every client that gets it."""

    __slots__ = ("created", "text")

    def __init__(self, text: str) -> None:
        self.text = text
        self.created = time.monotonic()

    @classmethod
    def of(cls, kind: str, payload: Any) -> Frame:
        return cls(dumps({kind: payload}))


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


def connected_text(server: PrintServer) -> str:
    """OctoPrint's ``connected`` message (1.11's fields; ``apikey`` as older versions
    had it, null: a socket that has not logged in is given no key)."""
    printers = ",".join(f"{s.name}={s.port}" for s in server.services.values())
    return dumps(
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
