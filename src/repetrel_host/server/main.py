"""``hyrel-server``: the print server's command line.

``hyrel-server --data-dir DIR --printer NAME=PORT [--printer ...] [--bind HOST:PORT]``, or
the same in a TOML file (``--config server.toml``: ``data_dir``, ``bind``, ``api_key``,
``max_upload_mb``, ``mqtt``, ``mqtt_discovery_prefix``..., and a ``[printers]`` table of
``name = "port"``, or of ``[printers.NAME]`` tables: ``port``, ``machine``, ``protocol``,
``report``...). Logs go to stderr, one line each, without times (journald adds them).
SIGTERM, SIGHUP or Ctrl-C stops feeding, runs the safe stop on a printing machine, and exits.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import secrets
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from repetrel_host import __version__
from repetrel_host.config import CameraCommand, read_toml
from repetrel_host.errors import ConfigError
from repetrel_host.server.mqtt.bridge import MqttSettings
from repetrel_host.server.mqtt.homeassistant import DEFAULT_PREFIX as DEFAULT_DISCOVERY_PREFIX
from repetrel_host.server.printers import PrinterConfig

if TYPE_CHECKING:
    from repetrel_host.server.farm.node import FarmSettings

DEFAULT_BIND = "127.0.0.1:8765"
API_KEY_FILE = "api-key"
_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_BRANCHES = ("str", "PrinterSettings")  # how pydantic names the sides of a printer's union

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)


class PrinterSettings(BaseModel):
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
    printers: dict[str, str | PrinterSettings] = Field(min_length=1)
    api_key: str | None = None
    max_upload_mb: int = Field(default=1024, gt=0)
    automatic_transition: bool = False  # start the next job by itself after one ends
    public_read: bool = False  # reads without a key (OctoPrint asks for one on every request)
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


def _fail(message: str) -> None:
    typer.echo(f"hyrel-server: {message}", err=True)
    raise typer.Exit(2)


def _settings(
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
) -> ServerSettings:
    values: dict[str, object] = {}
    if config is not None:
        try:
            values = read_toml(config)
        except ConfigError as exc:
            _fail(str(exc))
    table = values.get("printers") or {}
    if not isinstance(table, dict):
        _fail(f'{config}: printers: a table of name = "port" (or [printers.NAME] tables)')
        raise  # not reached
    printers = dict(table)
    for entry in printer:
        name, sep, port = entry.partition("=")
        if not sep or not name or not port:
            _fail(f"--printer {entry}: give NAME=PORT (e.g. left=/dev/ttyUSB0, or demo=fake)")
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
        "public_read": public_read or None,
        "farm": farm[0],
        "node_name": farm[1],
        "node_url": farm[2],
    }
    values.update({key: value for key, value in given.items() if value is not None})
    if not printers:
        _fail("no printer: give --printer NAME=PORT (PORT as hyrel-send --port takes it)")
    if "data_dir" not in values:
        _fail("give --data-dir DIR (the queue, the uploads and the history live there)")
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
        _fail(f"{where}{problems}")
        raise  # not reached
    for name in settings.printers:
        if not _NAME.match(name):
            _fail(f"printer name '{name}': use letters, digits, '-' and '_'")
    if settings.farm is not None:
        _check_farm_url(settings.farm)
    return settings


def _check_farm_url(url: str) -> None:
    """A PostgreSQL URL without a password (it would show in ``ps`` and in logs)."""
    try:
        from psycopg.conninfo import conninfo_to_dict
    except ImportError:
        _fail("--farm needs PostgreSQL's client: pip install 'repetrel-host[farm]'")
        raise  # not reached
    try:
        info = conninfo_to_dict(url)
    except Exception as exc:  # psycopg's ProgrammingError: the URL's own words
        _fail(f"--farm {url}: not a PostgreSQL URL ({str(exc).strip()})")
        raise  # not reached
    port = str(info.get("port", ""))
    if port and not all(part.isdigit() for part in port.split(",")):
        _fail(f"--farm {url}: the port '{port}' is not a number")
    if "password" in info:
        _fail(
            "--farm: give the database's password in PGPASSWORD or ~/.pgpass, not in the URL "
            "(a URL shows in ps and in logs)"
        )


def _farm(settings: ServerSettings, host: str, port: int) -> FarmSettings | None:
    """The farm this server joins; the database's schema checked first (a newer one than
    this version knows is refused in one sentence; an unreachable database is not: the
    node keeps trying, and its printers print their own queues meanwhile)."""
    if settings.farm is None:
        return None
    import asyncio

    from repetrel_host.server.farm.db import FarmDB
    from repetrel_host.server.farm.node import FarmSettings, default_node_name, shown_url

    shown_host = host if host not in ("0.0.0.0", "::", "") else default_node_name()
    farm = FarmSettings(
        settings.farm,
        settings.node_name or default_node_name(),
        (settings.node_url or f"http://{shown_host}:{port}").rstrip("/"),
        settings.farm_lease,
    )

    async def migrate() -> None:
        db = FarmDB(farm.url)
        await asyncio.wait_for(db.open(), 15)
        await db.close()

    try:
        asyncio.run(migrate())
    except ConfigError as exc:
        _fail(str(exc))
    except Exception as exc:
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(
            f"hyrel-server: the farm's database at {shown_url(farm.url)} does not answer "
            f"({why}): starting anyway, joining when it does",
            file=sys.stderr,
            flush=True,
        )
    return farm


def _api_key(settings: ServerSettings) -> str:
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


def _mqtt(settings: ServerSettings) -> MqttSettings | None:
    if settings.mqtt is None:
        return None
    host, port = _address(settings.mqtt, "--mqtt", 1883)
    return MqttSettings(
        host,
        port,
        settings.mqtt_prefix,
        settings.mqtt_commands,
        settings.mqtt_username,
        settings.mqtt_password,
        settings.mqtt_discovery_prefix if settings.mqtt_discovery else None,
    )


def _address(
    text: str, option: str, default_port: int | None = None, example: str = ""
) -> tuple[str, int]:
    """HOST:PORT (or HOST alone, given a default port); one sentence if it is neither."""
    host, sep, port = text.rpartition(":")
    if not sep and default_port is not None:
        return text, default_port
    if not host or not port.isdigit():
        _fail(f"{option} {text}: give HOST:PORT" + (f" (e.g. {example})" if example else ""))
    return host.strip("[]"), int(port)


@app.command()
def serve(
    data_dir: Annotated[
        Path | None, typer.Option(help="Folder of the queue, uploads, history and API key.")
    ] = None,
    printer: Annotated[
        list[str] | None,
        typer.Option(help="NAME=PORT, PORT as hyrel-send --port takes it (fake too); repeat."),
    ] = None,
    bind: Annotated[
        str | None, typer.Option(help=f"HOST:PORT to listen on (default {DEFAULT_BIND}).")
    ] = None,
    api_key: Annotated[
        str | None, typer.Option(help="The API key (default: kept in the data folder).")
    ] = None,
    max_upload_mb: Annotated[
        int | None, typer.Option(help="Largest upload, in MB (default 1024).", min=1)
    ] = None,
    mqtt: Annotated[
        str | None, typer.Option(metavar="HOST[:PORT]", help="Publish to this MQTT broker.")
    ] = None,
    mqtt_prefix: Annotated[
        str | None, typer.Option(help="Topic prefix (default hyrel): PREFIX/PRINTER/state...")
    ] = None,
    mqtt_commands: Annotated[
        bool,
        typer.Option(
            "--mqtt-commands",
            help="Take commands on PREFIX/PRINTER/command (off: MQTT topics have no secret).",
        ),
    ] = False,
    mqtt_discovery_prefix: Annotated[
        str | None,
        typer.Option(
            help=f"Home Assistant's MQTT discovery prefix (default {DEFAULT_DISCOVERY_PREFIX}): "
            "each printer appears there as a device."
        ),
    ] = None,
    no_mqtt_discovery: Annotated[
        bool,
        typer.Option("--no-mqtt-discovery", help="Publish no Home Assistant discovery configs."),
    ] = False,
    automatic_transition: Annotated[
        bool,
        typer.Option(
            "--automatic-transition",
            help="Start the next queued job by itself when one ends (default: the queue is "
            "held until released, as the part is still on the bed).",
        ),
    ] = False,
    public_read: Annotated[
        bool,
        typer.Option(
            "--public-read",
            help="Answer reads (states, files, snapshots) without a key. Default: every "
            "request needs the key or an app key, as on OctoPrint.",
        ),
    ] = False,
    farm: Annotated[
        str | None,
        typer.Option(
            metavar="postgresql://USER@HOST/DB",
            help="Join a farm: one job queue in PostgreSQL shared by many servers (the "
            "password from PGPASSWORD or ~/.pgpass).",
        ),
    ] = None,
    node_name: Annotated[
        str | None, typer.Option(help="This server's name in the farm (default: the host's).")
    ] = None,
    node_url: Annotated[
        str | None,
        typer.Option(help="Where the farm reaches this server (default: http://BIND)."),
    ] = None,
    config: Annotated[Path | None, typer.Option(help="A TOML file with these settings.")] = None,
    version: Annotated[bool, typer.Option("--version", help="Print the version.")] = False,
) -> None:
    """Serve the printers: a job queue each, an HTTP API (OctoPrint's too)."""
    if version:
        typer.echo(f"hyrel-server (repetrel-host) {__version__}")
        return
    settings = _settings(
        config,
        data_dir,
        bind,
        printer or [],
        api_key,
        max_upload_mb,
        (mqtt, mqtt_prefix, mqtt_commands, mqtt_discovery_prefix, no_mqtt_discovery),
        automatic_transition,
        public_read,
        (farm, node_name, node_url),
    )
    host, port = _address(settings.bind, "--bind", example=DEFAULT_BIND)
    logging.basicConfig(
        stream=sys.stderr, level=logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        lock = (settings.data_dir / "lock").open("w")
        try:  # held until the process ends
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _fail(f"another hyrel-server uses the data folder {settings.data_dir}")
        key = _api_key(settings)
    except OSError as exc:
        _fail(f"cannot use the data folder {settings.data_dir}: {exc.strerror}")
        raise  # not reached
    farm_settings = _farm(settings, host, port)

    import uvicorn

    from repetrel_host.server.app import PrintServer, create_app

    printers = {
        name: PrinterConfig(entry)
        if isinstance(entry, str)
        else PrinterConfig(**{**entry.model_dump(), "tags": tuple(entry.tags)})
        for name, entry in settings.printers.items()
    }
    server = PrintServer(
        settings.data_dir,
        printers,
        key,
        settings.max_upload_mb * 1024 * 1024,
        automatic_transition=settings.automatic_transition,
        public_read=settings.public_read,
        presets={name: p.model_dump() for name, p in settings.presets.items()},
        farm=farm_settings,
    )
    # uvicorn shuts down gracefully on SIGTERM and SIGINT, then raises the signal again
    # with the handlers found before it started: these, so that a stop asked for exits
    # 0 (130 for Ctrl-C) once the printers are safe, not as if killed.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    signal.signal(signal.SIGINT, lambda *_: sys.exit(130))
    # SIGHUP (the terminal or ssh session it was started in, gone) would end it on the
    # spot, heaters on: it stops as SIGTERM does, with the printers' safe stop.
    signal.signal(signal.SIGHUP, lambda *_: signal.raise_signal(signal.SIGTERM))
    uvicorn.run(
        create_app(server, _mqtt(settings)),
        host=host,
        port=port,
        log_level="info",
        access_log=False,
        # Event streams never end by themselves: after this long they are closed, so that
        # a stop reaches the printers' safe stop.
        timeout_graceful_shutdown=3,
        # The push socket's messages go uncompressed: deflating each for each client
        # would cost more CPU than the socket's whole work (the socket's clients are on
        # the farm's network).
        ws_per_message_deflate=False,
        # A websocket client that does not answer a ping within 10 s (it stopped reading:
        # a stuck app) is closed, whatever the kernel's buffers still take for it.
        ws_ping_interval=10.0,
        ws_ping_timeout=10.0,
    )


keys = typer.Typer(
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    help="The app keys granted on the status page (OctoPrint's appkeys).",
)
DataDir = Annotated[Path | None, typer.Option(help="The server's data folder (or give --config).")]
ConfigFile = Annotated[Path | None, typer.Option(help="The server's TOML file.")]


def _data_dir(data_dir: Path | None, config: Path | None) -> Path:
    if data_dir is None and config is not None:
        try:
            found = read_toml(config).get("data_dir")
        except ConfigError as exc:
            _fail(str(exc))
        data_dir = Path(found) if isinstance(found, str) else None
    if data_dir is None:
        _fail("give --data-dir DIR (or --config FILE), the server's data folder")
        raise  # not reached
    return data_dir


@keys.command("list")
def list_keys(data_dir: DataDir = None, config: ConfigFile = None) -> None:
    """The applications that hold a key, one a line: name, user, when granted."""
    from datetime import datetime

    from repetrel_host.server.access import KEYS_FILE, read_keys

    granted = read_keys(_data_dir(data_dir, config) / KEYS_FILE)
    for key in granted:
        typer.echo(f"{key.app}\t{key.user}\t{datetime.fromtimestamp(key.created):%Y-%m-%d %H:%M}")
    if not granted:
        typer.echo("no app keys (an application asks for one; allow it on the status page)")


@keys.command("revoke")
def revoke_key(
    app: Annotated[str, typer.Argument(help="The application's name, as listed.")],
    data_dir: DataDir = None,
    config: ConfigFile = None,
) -> None:
    """Revoke an application's key: the server refuses it from its next request on."""
    from repetrel_host.server.access import KEYS_FILE, revoke

    folder = _data_dir(data_dir, config)
    try:
        found = revoke(folder / KEYS_FILE, app)
    except OSError as exc:
        _fail(f"cannot change the keys in {folder}: {exc.strerror}")
    if not found:
        _fail(f"no key for app '{app}' (hyrel-server keys list shows them)")
    typer.echo(f"revoked the key of {app}")


def main() -> None:
    if sys.argv[1:2] == ["keys"]:  # the server itself takes no command name
        keys(sys.argv[2:], prog_name="hyrel-server keys")
    else:
        app()


if __name__ == "__main__":
    main()
