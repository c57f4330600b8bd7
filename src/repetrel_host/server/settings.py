"""The print server's settings: the TOML file's and the command line's, checked into one
:class:`ServerSettings` (a sentence and exit 2 for what is wrong), and what the server
makes of them: its API key, its MQTT broker, the farm it joins, the address it listens on.
"""

from __future__ import annotations

import os
import re
import secrets
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    IPvAnyNetwork,
    ValidationError,
)

from repetrel_host.config import CameraCommand, read_toml
from repetrel_host.errors import ConfigError
from repetrel_host.links import not_a_port
from repetrel_host.server.mqtt.bridge import MqttSettings
from repetrel_host.server.mqtt.homeassistant import DEFAULT_PREFIX as DEFAULT_DISCOVERY_PREFIX

if TYPE_CHECKING:
    from repetrel_host.server.farm.node import FarmSettings

DEFAULT_BIND = "127.0.0.1:8765"
API_KEY_FILE = "api-key"
_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_BRANCHES = ("str", "PrinterEntry")  # how pydantic names the sides of a printer's union


def _server_name(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?", name):
        raise ValueError(f"'{name}' is not a host name (no scheme, port or '*')")
    return name.lower()


def _cors_domain(domain: str) -> str:
    """An origin (``http://HOST[:PORT]``, ``*`` for any characters), as Moonraker takes its
    ``cors_domains``: no ``*`` in the top-level domain, no trailing slash."""
    if not re.fullmatch(r"https?://[^/?#\s]+", domain):
        raise ValueError(f"'{domain}' is not an origin: give http(s)://HOST[:PORT], no path")
    if re.search(r"^.+\.[^:]*\*", domain):
        raise ValueError(f"'{domain}': a '*' in the top-level domain would match any site")
    return domain


ServerName = Annotated[str, AfterValidator(_server_name)]
CorsDomain = Annotated[str, AfterValidator(_cors_domain)]


class PrinterEntry(BaseModel):
    """A printer in the TOML file, when it needs more than its port."""

    model_config = ConfigDict(extra="forbid")

    port: str
    machine: str | None = None
    loadout: str | None = None
    flow: Literal["buffered", "unbuffered"] | None = None
    rx_buffer: int | None = Field(default=None, ge=2)
    max_lines: int | None = Field(default=None, ge=1)
    baud: int | None = Field(default=None, gt=0)
    protocol: Literal["reprap", "hyrel"] | None = None  # None: the machine's, else reprap
    report: bool = False  # every job asks for the controller's M773 report (M772 S1)
    camera: CameraCommand | None = None  # M791/M790 snapshots ({path}: the image to write)
    layer_snapshots: bool = True  # with a camera, a snapshot at every M790 (new layer)
    snapshots_kept: int = Field(default=500, ge=1)
    tags: list[str] = []  # in a farm: what jobs may ask of it (tag=abs)
    # A port of its own for Moonraker's clients that take only a host and port.
    moonraker_port: int | None = Field(default=None, ge=1, le=65535)


class Preset(BaseModel):
    """A material's temperatures (°C): ``[presets.PLA] head = 210, bed = 60``."""

    model_config = ConfigDict(extra="forbid")

    head: float = Field(ge=0, le=500)
    bed: float | None = Field(default=None, ge=0, le=200)
    chamber: float | None = Field(default=None, ge=0, le=100)


# The page's presets when the configuration names none (common PLA, PETG and ABS settings).
DEFAULT_PRESETS = {
    "PLA": Preset(head=210, bed=60),
    "PETG": Preset(head=240, bed=80),
    "ABS": Preset(head=250, bed=100),
}


class ServerSettings(BaseModel):
    """What the server runs with: the command line's options over the TOML file's."""

    model_config = ConfigDict(extra="forbid")

    data_dir: Path
    bind: str = DEFAULT_BIND
    printers: dict[str, str | PrinterEntry] = Field(min_length=1)
    api_key: str | None = None
    max_upload_mb: int = Field(default=1024, gt=0)
    automatic_transition: bool = False  # start the next job by itself after one ends
    # A farm's: a person's start of a file waits for the queue's release too (by default
    # a start says the bed is clear, and releases the hold).
    start_waits_for_release: bool = False
    public_read: bool = False  # reads without a key (OctoPrint asks for one on every request)
    # How long a stop (SIGTERM) waits for a printing machine's safe stop before it leaves
    # it owed (and exits 75, for systemd to start the server again to send it).
    stop_timeout: float = Field(default=30.0, gt=0, le=3600)
    # Connections held at once (HTTP and websockets; connections.py keeps 256 more file
    # descriptors for the rest: 1,024 in all), and the seconds a connection has to send a
    # request's head: past either, connections that sent no request are closed.
    max_connections: int = Field(default=768, ge=16, le=100_000)
    header_timeout: float = Field(default=10.0, gt=0, le=300)
    # Moonraker's face lets these networks in without a key (its trusted_clients).
    moonraker_trusted_clients: list[IPvAnyNetwork] = []
    # X-Forwarded-For and -Proto are believed only from these (a web server in front).
    trusted_proxies: list[IPvAnyNetwork] = []
    # Names the server answers to besides localhost, the machine's and node_url's (Host).
    server_names: list[ServerName] = []
    # Other origins whose pages may open the websockets (Moonraker's cors_domains).
    cors_domains: list[CorsDomain] = []
    mqtt: str | None = None  # HOST[:PORT] of a broker
    mqtt_prefix: str = "hyrel"
    mqtt_commands: bool = False
    mqtt_username: str | None = None
    mqtt_password: str | None = None
    mqtt_discovery: bool = True  # Home Assistant's discovery configs, each printer a device
    mqtt_discovery_prefix: str = Field(default=DEFAULT_DISCOVERY_PREFIX, pattern=r"^[^#+]+$")
    presets: dict[str, Preset] = DEFAULT_PRESETS  # the page's material presets
    farm: str | None = None  # postgresql://USER@HOST/DB: a farm's shared queue
    node_name: str | None = None  # this server in the farm (default: the host's name)
    node_url: str | None = None  # where the farm's page links to this server
    farm_lease: float = Field(default=15.0, ge=1, le=600)  # seconds without a heartbeat


def fail(message: str) -> None:
    """Say ``message`` on stderr as hyrel-server's, and exit 2 (something given is wrong)."""
    typer.echo(f"hyrel-server: {message}", err=True)
    raise typer.Exit(2)


def load_settings(
    config: Path | None,
    data_dir: Path | None,
    bind: str | None,
    printer: list[str],
    api_key: str | None,
    max_upload_mb: int | None,
    mqtt: tuple[str | None, str | None, bool, str | None, bool],
    automatic_transition: bool,
    public_read: bool = False,
    farm: tuple[str | None, str | None, str | None] = (None, None, None),
    stop_timeout: float | None = None,
    ways_in: tuple[list[str], list[str], list[str]] = ([], [], []),
    start_waits_for_release: bool = False,
) -> ServerSettings:
    """The settings of the TOML file ``config``, with the options given over them
    (``ways_in``: the trusted proxies, server names and CORS domains given)."""
    values: dict[str, object] = {}
    if config is not None:
        try:
            values = read_toml(config)
        except ConfigError as exc:
            fail(str(exc))
    table = values.get("printers") or {}
    if not isinstance(table, dict):
        fail(f'{config}: printers: a table of name = "port" (or [printers.NAME] tables)')
        raise  # not reached
    printers = dict(table)
    for entry in printer:
        name, sep, port = entry.partition("=")
        if not sep or not name or not port:
            fail(f"--printer {entry}: give NAME=PORT (e.g. left=/dev/ttyUSB0, or demo=fake)")
        printers[name] = port
    given = {
        "data_dir": data_dir,
        "bind": bind,
        "api_key": api_key,
        "max_upload_mb": max_upload_mb,
        "printers": printers,
        "mqtt": mqtt[0],
        "mqtt_prefix": mqtt[1],
        "mqtt_commands": mqtt[2] or None,
        "mqtt_discovery_prefix": mqtt[3],
        "mqtt_discovery": False if mqtt[4] else None,
        "automatic_transition": automatic_transition or None,
        "start_waits_for_release": start_waits_for_release or None,
        "public_read": public_read or None,
        "stop_timeout": stop_timeout,
        "farm": farm[0],
        "node_name": farm[1],
        "node_url": farm[2],
        "trusted_proxies": ways_in[0] or None,
        "server_names": ways_in[1] or None,
        "cors_domains": ways_in[2] or None,
    }
    values.update({key: value for key, value in given.items() if value is not None})
    if not printers:
        fail("no printer: give --printer NAME=PORT (PORT as hyrel-send --port takes it)")
    if "data_dir" not in values:
        fail("give --data-dir DIR (the queue, the uploads and the history live there)")
    try:
        settings = ServerSettings.model_validate(values)
    except ValidationError as exc:
        where = f"{config}: " if config is not None else ""
        problems = "; ".join(
            f"{'.'.join(str(p) for p in error['loc'] if p not in _BRANCHES) or 'settings'}: "
            f"{error['msg']}"
            for error in exc.errors()
            # A printer is a port or a table: a table's errors are its own, not "not a port".
            if not (error["type"] == "string_type" and isinstance(error["input"], dict))
        )
        fail(f"{where}{problems}")
        raise  # not reached
    for name, chosen in settings.printers.items():
        if not _NAME.match(name):
            fail(f"printer name '{name}': use letters, digits, '-' and '_'")
        # A folder never becomes a port (a device not there yet may be plugged in later).
        folder = not_a_port(chosen if isinstance(chosen, str) else chosen.port)
        if folder is not None:
            fail(f"printer {name}: {folder}")
    if settings.farm is not None:
        _check_farm_url(settings.farm)
    _check_moonraker_ports(settings)
    return settings


def _own_ports(settings: ServerSettings) -> list[tuple[str, int]]:
    """(printer, port) of each printer with a port of its own for Moonraker's clients."""
    return [
        (name, entry.moonraker_port)
        for name, entry in settings.printers.items()
        if isinstance(entry, PrinterEntry) and entry.moonraker_port is not None
    ]


def moonraker_ports(settings: ServerSettings) -> dict[int, str]:
    """The printers that have a port of their own for Moonraker's clients: port: name."""
    return {port: name for name, port in _own_ports(settings)}


def _check_moonraker_ports(settings: ServerSettings) -> None:
    """Each moonraker_port is a printer's own: not the server's, not another's."""
    seen: dict[int, str] = {}
    _, _, bound = settings.bind.rpartition(":")
    for name, port in _own_ports(settings):
        if str(port) == bound:
            fail(f"printer {name}: moonraker_port {port} is the server's own port (bind)")
        if port in seen:
            fail(f"printer {name}: moonraker_port {port} is printer {seen[port]}'s own too")
        seen[port] = name


def _check_farm_url(url: str) -> None:
    """A PostgreSQL URL without a password (it would show in ``ps`` and in logs)."""
    try:
        from psycopg.conninfo import conninfo_to_dict
    except ImportError:
        fail("--farm needs PostgreSQL's client: pip install -e '.[farm]' in repetrel-host's clone")
        raise  # not reached
    try:
        info = conninfo_to_dict(url)
    except Exception as exc:  # psycopg's ProgrammingError: the URL's own words
        fail(f"--farm {url}: not a PostgreSQL URL ({str(exc).strip()})")
        raise  # not reached
    port = str(info.get("port", ""))
    if port and not all(part.isdigit() for part in port.split(",")):
        fail(f"--farm {url}: the port '{port}' is not a number")
    if "password" in info:
        fail(
            "--farm: give the database's password in PGPASSWORD or ~/.pgpass, not in the URL "
            "(a URL shows in ps and in logs)"
        )


def farm_to_join(settings: ServerSettings, host: str, port: int) -> FarmSettings | None:
    """The farm this server joins; the database's schema checked first (a newer one than
    this version knows is refused in one sentence; an unreachable database is not: the
    node keeps trying, and its printers print their own queues meanwhile)."""
    if settings.farm is None:
        return None
    import asyncio

    from repetrel_host.server.farm.db import FarmDB
    from repetrel_host.server.farm.node import FarmSettings, shown_url

    farm = FarmSettings(
        settings.farm,
        settings.node_name or default_node_name(),
        (settings.node_url or served_url(host, port)).rstrip("/"),
        settings.farm_lease,
    )

    async def migrate() -> None:
        db = FarmDB(farm.url)
        await asyncio.wait_for(db.open(), 15)
        await db.close()

    try:
        asyncio.run(migrate())
    except ConfigError as exc:
        fail(str(exc))
    except Exception as exc:
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(
            f"hyrel-server: the farm's database at {shown_url(farm.url)} does not answer "
            f"({why}): starting anyway, joining when it does",
            file=sys.stderr,
            flush=True,
        )
    return farm


def default_node_name() -> str:
    """This machine's name (its host name's first part)."""
    return socket.gethostname().split(".")[0] or "node"


def served_url(host: str, port: int) -> str:
    """Where others reach a server listening on ``host``:``port``: the machine's name when
    it listens on every address."""
    shown = host if host not in ("0.0.0.0", "::", "") else default_node_name()
    return f"http://[{shown}]:{port}" if ":" in shown else f"http://{shown}:{port}"


def load_api_key(settings: ServerSettings) -> str:
    """The key given, else the one kept in the data folder, else a new one (kept, 0600)."""
    if settings.api_key:
        return settings.api_key
    path = settings.data_dir / API_KEY_FILE
    if path.exists():
        return path.read_text().strip()
    key = secrets.token_urlsafe(24)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as handle:
        handle.write(key + "\n")
    print(f"hyrel-server: a new API key (kept in {path}): {key}", file=sys.stderr, flush=True)
    return key


def mqtt_settings(settings: ServerSettings) -> MqttSettings | None:
    """The broker the server publishes to, and how; None without one."""
    if settings.mqtt is None:
        return None
    host, port = parse_address(settings.mqtt, "--mqtt", 1883)
    return MqttSettings(
        host,
        port,
        settings.mqtt_prefix,
        settings.mqtt_commands,
        settings.mqtt_username,
        settings.mqtt_password,
        settings.mqtt_discovery_prefix if settings.mqtt_discovery else None,
    )


def parse_address(
    text: str, option: str, default_port: int | None = None, example: str = ""
) -> tuple[str, int]:
    """HOST:PORT (or HOST alone, given a default port); one sentence if it is neither."""
    host, sep, port = text.rpartition(":")
    if not sep and default_port is not None:
        return text, default_port
    if not host or not port.isdigit():
        fail(f"{option} {text}: give HOST:PORT" + (f" (e.g. {example})" if example else ""))
    return host.strip("[]"), int(port)
