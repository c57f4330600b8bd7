"""``hyrel-server``: the print server's command line.

``hyrel-server --data-dir DIR --printer NAME=PORT [--printer ...] [--bind HOST:PORT]``, or
the same in a TOML file (``--config server.toml``: ``data_dir``, ``bind``, ``api_key``,
``max_upload_mb``, ``mqtt``, ``mqtt_discovery_prefix``..., and a ``[printers]`` table of
``name = "port"``, or of ``[printers.NAME]`` tables: ``port``, ``machine``, ``protocol``,
``report``...). Logs go to stderr, one line each, without times (journald adds them).
SIGTERM, SIGHUP or Ctrl-C stops feeding, runs the safe stop on a printing machine, and exits.
Beside it, on its data folder: ``hyrel-server keys list|revoke`` (the app keys) and
``hyrel-server link`` (a one-time link to the page).
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import signal
import socket
import sys
import time
from pathlib import Path
from typing import IO, Annotated

import typer

from repetrel_host import __version__
from repetrel_host.config import read_toml
from repetrel_host.errors import ConfigError
from repetrel_host.server.mqtt.homeassistant import DEFAULT_PREFIX as DEFAULT_DISCOVERY_PREFIX
from repetrel_host.server.printers.config import PrinterConfig
from repetrel_host.server.settings import (
    DEFAULT_BIND,
    fail,
    farm_to_join,
    load_api_key,
    load_settings,
    moonraker_ports,
    mqtt_settings,
    parse_address,
    served_url,
)

# A stop that left a printer's safe stop owed (EX_TEMPFAIL: start it again to send it).
EXIT_SAFE_STOP_OWED = 75
app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)


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
    start_waits_for_release: Annotated[
        bool,
        typer.Option(
            "--start-waits-for-release",
            help="A print started from a client waits for the queue's release too, as queued "
            "jobs do (a farm's; default: a person's start says the bed is clear).",
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
    stop_timeout: Annotated[
        float | None,
        typer.Option(
            help="Seconds a stop (SIGTERM) waits for a printing machine's safe stop (default "
            "30); a stop left owed exits 75, and the next start sends it first.",
        ),
    ] = None,
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
    trusted_proxy: Annotated[
        list[str] | None,
        typer.Option(
            metavar="ADDRESS[/BITS]",
            help="A web server in front, whose X-Forwarded-For names the client (default "
            "none: the header is ignored); repeat.",
        ),
    ] = None,
    server_name: Annotated[
        list[str] | None,
        typer.Option(
            help="A host name the server answers to, besides IP addresses, localhost and the "
            "machine's own; repeat.",
        ),
    ] = None,
    cors_domain: Annotated[
        list[str] | None,
        typer.Option(
            metavar="http(s)://HOST[:PORT]",
            help="Another origin whose pages may open the websockets ('*' for any "
            "characters); repeat.",
        ),
    ] = None,
    config: Annotated[Path | None, typer.Option(help="A TOML file with these settings.")] = None,
    version: Annotated[bool, typer.Option("--version", help="Print the version.")] = False,
) -> None:
    """Serve the printers: a job queue each, an HTTP API (OctoPrint's too)."""
    if version:
        typer.echo(f"hyrel-server (repetrel-host) {__version__}")
        return
    settings = load_settings(
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
        stop_timeout,
        (trusted_proxy or [], server_name or [], cors_domain or []),
        start_waits_for_release,
    )
    host, port = parse_address(settings.bind, "--bind", example=DEFAULT_BIND)
    logging.basicConfig(
        stream=sys.stderr, level=logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    # A second server on a running one's data folder says so, not that the port is taken.
    lock = data_lock(settings.data_dir, make=False)
    # Bound before anything is written or started: a port in use is one sentence, and
    # leaves neither a data folder nor a key behind, nor a server half up.
    ports = moonraker_ports(settings)
    sockets = [bound(host, port, "--bind")] + [
        bound(host, own, f"printer {name}'s moonraker_port") for own, name in ports.items()
    ]
    try:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        lock = lock or data_lock(settings.data_dir, make=True)
        key = load_api_key(settings)
    except OSError as exc:
        fail(f"cannot use the data folder {settings.data_dir}: {exc.strerror}")
        raise  # not reached
    farm_settings = farm_to_join(settings, host, port)
    where = logging.getLogger("repetrel_host.server")
    where.info("listening on http://%s:%d", host, port)
    for own, name in ports.items():
        where.info("printer %s: Moonraker's clients on http://%s:%d too", name, host, own)

    import uvicorn

    from repetrel_host.server.app import PrinterPorts, PrintServer, create_app
    from repetrel_host.server.bodies import SMALL_BODY
    from repetrel_host.server.connections import ConnectionGuard, connection_limit, quiet_repeats
    from repetrel_host.server.origins import Origins, machine_names

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
        start_waits_for_release=settings.start_waits_for_release,
        public_read=settings.public_read,
        trusted=settings.moonraker_trusted_clients,
        presets={name: p.model_dump() for name, p in settings.presets.items()},
        farm=farm_settings,
        stop_timeout=settings.stop_timeout,
    )

    # uvicorn shuts down gracefully on SIGTERM and SIGINT, then raises the signal again
    # with the handlers found before it started: these, so that a stop asked for exits
    # 0 (130 for Ctrl-C) once the printers are safe, not as if killed; and 75 when a safe
    # stop was left owed, so that systemd's Restart=on-failure starts the server again,
    # which sends it first.
    def stopped(code: int) -> None:
        if server.left_owing:
            logging.getLogger("repetrel_host.server").error(
                "exiting with %d: the safe stop of printer %s is owed (it goes first at the "
                "next start)",
                EXIT_SAFE_STOP_OWED,
                ", ".join(server.left_owing),
            )
            sys.exit(EXIT_SAFE_STOP_OWED)
        sys.exit(code)

    signal.signal(signal.SIGTERM, lambda *_: stopped(0))
    signal.signal(signal.SIGINT, lambda *_: stopped(130))
    # SIGHUP (the terminal or ssh session it was started in, gone) and SIGQUIT (Ctrl-\)
    # would end it on the spot, heaters on: they stop it as SIGTERM does.
    for signum in (signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, lambda *_: signal.raise_signal(signal.SIGTERM))
    node_url = farm_settings.node_url if farm_settings is not None else None
    origins = Origins(
        {*machine_names(), host, *served_names(node_url), *settings.server_names},
        settings.cors_domains,
    )
    served = create_app(server, mqtt_settings(settings), origins)
    proxies = [str(network) for network in settings.trusted_proxies]
    # Connections that send nothing are closed, and take no more than their share of files.
    guard = ConnectionGuard(connection_limit(settings.max_connections), settings.header_timeout)
    listening = uvicorn.Config(
        PrinterPorts(served, ports) if ports else served,
        host=host,
        port=port,
        log_level="info",
        access_log=False,
        # X-Forwarded-For names the client only when a proxy the settings name sent it
        # (uvicorn's default believes any local process, $FORWARDED_ALLOW_IPS anyone).
        proxy_headers=bool(proxies),
        forwarded_allow_ips=proxies,
        **guard.options(),
        # A websocket's message is bounded as an HTTP body is (bodies.py).
        ws_max_size=SMALL_BODY,
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
    quiet_repeats()  # after uvicorn set up its loggers
    uvicorn.Server(listening).run(sockets=sockets)


def served_names(url: str | None) -> list[str]:
    """The host name in ``url`` (the farm's link to this server), if it has one."""
    from urllib.parse import urlsplit

    name = urlsplit(url).hostname if url else None
    return [name] if name else []


def data_lock(folder: Path, make: bool) -> IO[str] | None:
    """The data folder's lock, held until the process ends; one sentence and exit 2 when
    another hyrel-server holds it. Without ``make``, None where there is no lock yet (no
    server ever ran there) or it cannot be opened (the start says why once it makes it)."""
    try:
        lock = (folder / "lock").open("w" if make else "r")
    except OSError:
        if make:
            raise
        return None
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fail(f"another hyrel-server uses the data folder {folder}")
    return lock


def bound(host: str, port: int, what: str) -> socket.socket:
    """A socket bound to ``host``:``port``, not listening yet: a client is refused until the
    server serves (as before it was bound here), not kept waiting. One sentence and exit 2
    when it cannot be bound."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP named: asyncio turns Nagle's algorithm off (TCP_NODELAY) only on sockets
    # that say they are TCP, and an accepted socket takes its protocol from this one. With
    # 0 here, each answer on a kept connection waited 40 ms for the client's delayed ACK.
    made = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        made.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        made.bind((host, port))
        return made
    except OSError as exc:
        made.close()
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        fail(f"cannot listen on {host}:{port} ({what}): {reason}")
        raise  # not reached


keys = typer.Typer(
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    help="The app keys granted on the status page (OctoPrint's appkeys).",
)
DataDir = Annotated[Path | None, typer.Option(help="The server's data folder (or give --config).")]
ConfigFile = Annotated[Path | None, typer.Option(help="The server's TOML file.")]


def _configured(config: Path | None, name: str) -> str | None:
    """The setting ``name`` of the TOML file ``config``, if it gives one."""
    if config is None:
        return None
    try:
        found = read_toml(config).get(name)
    except ConfigError as exc:
        fail(str(exc))
        raise  # not reached
    return found if isinstance(found, str) else None


def _data_dir(data_dir: Path | None, config: Path | None) -> Path:
    if data_dir is None:
        found = _configured(config, "data_dir")
        data_dir = Path(found) if found is not None else None
    if data_dir is None:
        fail("give --data-dir DIR (or --config FILE), the server's data folder")
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
        fail(f"cannot change the keys in {folder}: {exc.strerror}")
    if not found:
        fail(f"no key for app '{app}' (hyrel-server keys list shows them)")
    typer.echo(f"revoked the key of {app}")


link = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)
_UNITS = {"s": 1, "m": 60, "h": 3600}


@link.command()
def one_time_link(
    data_dir: DataDir = None,
    config: ConfigFile = None,
    valid_for: Annotated[
        str, typer.Option("--for", metavar="TIME", help="How long it stays good: 90s, 10m, 2h.")
    ] = "10m",
    name: Annotated[
        str | None,
        typer.Option(
            help="The name of the app key it gives (default: 'page link', the time and four "
            "hex digits); a key of that name already given is replaced when the link is opened."
        ),
    ] = None,
    url: Annotated[
        str | None,
        typer.Option(
            help="The page's address as the browser reaches it (default: the --config's "
            f"node_url, else its bind, else http://{DEFAULT_BIND})."
        ),
    ] = None,
) -> None:
    """Print a one-time link to the page: the first browser that opens it in time gets an
    app key of its own, kept in the browser as a typed key is; the link is spent then."""
    from repetrel_host.server.access import LINK_LONGEST, make_page_link

    folder = _data_dir(data_dir, config)
    if not (folder / "lock").exists():  # made at a server's first start
        fail(f"no hyrel-server has run on the data folder {folder} (give its --data-dir)")
    amount = re.fullmatch(r"(\d+(?:\.\d+)?)([smh])", valid_for.strip())
    seconds = float(amount[1]) * _UNITS[amount[2]] if amount else 0.0
    if not 0 < seconds <= LINK_LONGEST:
        fail(f"--for {valid_for}: give a time with its unit, at most 24h (90s, 10m, 2h)")
    if name is not None and not 0 < len(name.strip()) <= 200:
        fail("--name: give a name of 1 to 200 characters")
    base = url or _configured(config, "node_url")
    if base is None:
        bind = _configured(config, "bind") or DEFAULT_BIND
        base = served_url(*parse_address(bind, "bind", example=DEFAULT_BIND))
    if not re.match(r"https?://[^/?#\s]+", base):
        fail(f"--url {base}: give the page's address, http(s)://HOST[:PORT]")
    try:
        token, made = make_page_link(folder, name.strip() if name else None, seconds)
    except OSError as exc:
        fail(f"cannot make a link in {folder}: {exc.strerror}")
        raise  # not reached
    typer.echo(f"{base.rstrip('/')}/#token={token}")
    until = time.strftime("%H:%M", time.localtime(made.expires))
    typer.echo(
        f"hyrel-server: opens the page once, until {until}, giving the browser the app key "
        f"'{made.app}' (hyrel-server keys revoke takes it back)",
        err=True,
    )


def main() -> None:
    # The server itself takes no command name: these are its tools beside it.
    if sys.argv[1:2] == ["keys"]:
        keys(sys.argv[2:], prog_name="hyrel-server keys")
    elif sys.argv[1:2] == ["link"]:
        link(sys.argv[2:], prog_name="hyrel-server link")
    else:
        app()


if __name__ == "__main__":
    main()
