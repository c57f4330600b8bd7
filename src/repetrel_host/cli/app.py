"""``hyrel-send``: the typer app, its options, ``main()`` and the exit code each failure
maps to.

Presentation only: the plan is ``planning``'s, the streaming the session's. This module
parses the options and hands the run to what does it: :mod:`.send` streams a job at the
terminal, :mod:`.remote` sends it to a print server (``--server``, ``--farm``),
:mod:`.offline` answers what needs no printer (``--check``, ``--dry-run``,
``--list-ports``, ``--history-list``), :mod:`.console` is ``--console``.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from repetrel_host import __version__
from repetrel_host.cli import offline
from repetrel_host.cli.console import CONSOLE_HELP, ConsoleOptions, run_console
from repetrel_host.cli.exit_codes import (
    EXIT_BAD_INPUT,
    EXIT_CONTROLLER_ERROR,
    EXIT_LINK_FAILURE,
    EXIT_NOT_SAFE,
    EXIT_OK,
)
from repetrel_host.cli.out import Out
from repetrel_host.cli.remote import FarmRequest, ServerRequest, run_with_farm, run_with_server
from repetrel_host.cli.send import SendOptions, announce_recovery, send_job
from repetrel_host.cli.stop_signals import exit_code_of_stop, interrupt_on_stop_signals
from repetrel_host.config import load_user_config
from repetrel_host.errors import (
    ConfigError,
    ControllerError,
    HostError,
    JobError,
    LinkError,
    ProtocolError,
    SafeStopError,
    UsageError,
)
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.flow import FlowMode
from repetrel_host.session import history as print_history
from repetrel_host.session.machine_state import HomeAxes
from repetrel_host.session.planning import (
    PORT_ENV,
    JobRequest,
    LinkRequest,
    layer_line,
    plan_job,
    recovery_plan,
)
from repetrel_host.session.settings import RECONNECT_WAIT


class Protocol(StrEnum):
    REPRAP = "reprap"
    HYREL = "hyrel"


app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"hyrel-send (repetrel-host) {__version__}")
        raise typer.Exit(EXIT_OK)


@app.command()
def send(
    job: Annotated[
        Path | None,
        typer.Argument(help="G-code file to stream.", readable=False, metavar="JOB"),
    ] = None,
    port: Annotated[
        str | None,
        typer.Option(
            metavar="PORT",
            help="Serial port or pyserial URL; 'auto' for the only port that looks like a "
            "Hyrel or Marlin board (see --list-ports); 'fake' for the built-in fake "
            f"controller. Default: ${PORT_ENV}, then [printer] port in the configuration, "
            "else the fake.",
        ),
    ] = None,
    baud: Annotated[
        int | None, typer.Option(help="Baud rate (default 115200).", min=1, metavar="N")
    ] = None,
    protocol: Annotated[
        Protocol | None,
        typer.Option(
            help="reprap: numbered lines, ok and Resend; hyrel: Hyrel's own link (ACK "
            "bytes, control bytes, the host watchdog). Default: the machine profile's, else "
            "reprap."
        ),
    ] = None,
    flow: Annotated[
        FlowMode | None,
        typer.Option(help="buffered (default): several lines in flight; unbuffered: one."),
    ] = None,
    rx_buffer: Annotated[
        int | None,
        typer.Option(
            help="Controller receive buffer in bytes (default 128; with --protocol hyrel, "
            "the headroom within which it takes lines: 2048).",
            min=2,
            metavar="BYTES",
        ),
    ] = None,
    max_lines: Annotated[
        int | None,
        typer.Option(
            help="Most lines in flight at once (default 8; 256 with --protocol hyrel).",
            min=1,
            metavar="N",
        ),
    ] = None,
    reply_timeout: Annotated[
        float,
        typer.Option(
            help="Seconds of silence after which the controller is taken as gone.",
            min=0.1,
            metavar="SECONDS",
        ),
    ] = DEFAULT_REPLY_TIMEOUT,
    reconnect_wait: Annotated[
        float,
        typer.Option(
            help="After the link failed mid-job (unplugged, reset, silent), how long to keep "
            "reopening the port to send the safe stop before giving up.",
            min=0,
            metavar="SECONDS",
        ),
    ] = RECONNECT_WAIT,
    loadout: Annotated[
        Path | None,
        typer.Option(
            help="Loadout TOML (or the name of a shipped one): which head is where.",
            metavar="FILE|NAME",
        ),
    ] = None,
    machine: Annotated[
        str | None,
        typer.Option(
            metavar="NAME",
            help="Machine profile, when there is no loadout (default: from the firmware's "
            "answer to M115, or, without a printer, from the slicer that wrote the job).",
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            help="Configuration file (default ~/.config/repetrel-host/config.toml).",
            metavar="FILE",
        ),
    ] = None,
    no_header: Annotated[
        bool, typer.Option("--no-header", help="Do not send the heads' settings first.")
    ] = False,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Print the commands that would be sent; send none.")
    ] = False,
    framed: Annotated[
        bool, typer.Option("--framed", help="With --dry-run: with line numbers and checksums.")
    ] = False,
    check: Annotated[
        bool, typer.Option("--check", help="Only check the job; send nothing.")
    ] = False,
    force: Annotated[bool, typer.Option("--force", help="Send despite errors found.")] = False,
    report: Annotated[
        bool,
        typer.Option(
            "--report",
            help="Send M772 S1 first: a Hyrel controller sends its job report (M773) at "
            "M30, kept beside the print history and shown at the end.",
        ),
    ] = False,
    from_line: Annotated[
        int | None,
        typer.Option(
            help="Resume a failed print at this source line (the first command on it or "
            "after it): what the lines before it set up (temperatures, fans, modes, the "
            "tool, the last position, E and feed rate) is restored first. A failed job's "
            "summary gives the exact command.",
            metavar="N",
        ),
    ] = None,
    from_layer: Annotated[
        int | None,
        typer.Option(
            help="Resume at the start of this layer (from 1, as the slicer marks them).",
            metavar="L",
        ),
    ] = None,
    recovery_home: Annotated[
        HomeAxes,
        typer.Option(
            "--resume-home",
            help="With --from-line/--from-layer: xy (default) homes X and Y before going "
            "back to the resume point (the safe stop turned their motors off); none: the "
            "controller still knows where they are. Z is never homed: the part is on the bed.",
        ),
    ] = HomeAxes.XY,
    history: Annotated[
        Path | None,
        typer.Option(
            help="Folder for the print history (default ~/.local/share/repetrel-host/history).",
            metavar="DIR",
        ),
    ] = None,
    no_history: Annotated[
        bool, typer.Option("--no-history", help="Do not keep the transmitted stream.")
    ] = False,
    fake_log: Annotated[
        Path | None,
        typer.Option(
            help="Where the built-in fake writes the commands it executed (default: none kept).",
            metavar="FILE",
        ),
    ] = None,
    list_ports: Annotated[
        bool,
        typer.Option(
            "--list-ports",
            help="List the serial ports (USB description, VID:PID), marking the ones that "
            "look like a Hyrel or Marlin board, and exit.",
        ),
    ] = False,
    history_list: Annotated[
        bool,
        typer.Option(
            "--history-list",
            help=f"Show the newest {print_history.LIST_LENGTH} prints in the history folder "
            "(--history DIR), how each ended, and exit.",
        ),
    ] = False,
    server: Annotated[
        str | None,
        typer.Option(
            metavar="URL",
            help="Send JOB to a print server (hyrel-server) and follow it, instead of a port.",
        ),
    ] = None,
    printer: Annotated[
        str | None,
        typer.Option(metavar="NAME", help="With --server: which printer (default: its first)."),
    ] = None,
    api_key: Annotated[
        str | None,
        typer.Option(metavar="KEY", help="With --server: its API key (default: $HYREL_API_KEY)."),
    ] = None,
    list_jobs: Annotated[
        bool, typer.Option("--list", help="With --server: list the printer's jobs.")
    ] = False,
    cancel: Annotated[
        int | None,
        typer.Option(metavar="ID", help="With --server: cancel a job (the safe stop first)."),
    ] = None,
    release: Annotated[
        bool,
        typer.Option(
            "--release",
            help="With --server: the bed is clear, let the printer's held queue go on.",
        ),
    ] = False,
    farm: Annotated[
        bool,
        typer.Option(
            "--farm",
            help="With --server: the farm's queue (hyrel-server --farm), not one printer's: "
            "JOB goes to whichever printer can print it; --list and --cancel act on it.",
        ),
    ] = False,
    require: Annotated[
        list[str] | None,
        typer.Option(
            metavar="KEY=VALUE",
            help="With --farm: what the printer must have (material=PLA, T1.head=MK1-250, "
            "tag=abs, machine=..., printer=...); repeat.",
        ),
    ] = None,
    priority: Annotated[int, typer.Option(help="With --farm: higher goes first (default 0).")] = 0,
    copies: Annotated[
        int, typer.Option(help="With --farm: print this many (default 1).", min=1)
    ] = 1,
    recover: Annotated[
        int | None,
        typer.Option(
            "--resume",
            metavar="ID",
            help="With --farm: go on with farm job ID on the printer that printed it, from "
            "its first line not acknowledged (or --from-line, --from-layer).",
        ),
    ] = None,
    console_mode: Annotated[bool, typer.Option("--console", help=CONSOLE_HELP)] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version", help="Show the version and exit.", callback=_version, is_eager=True
        ),
    ] = False,
) -> None:
    """Stream JOB to a Hyrel (or Marlin-style) controller and show progress.

    Without a port it streams to the built-in fake controller, which runs every command
    at once on a link as fast as --baud (115200: 11.5 KB/s each way) with 1 ms latency.
    For a slower or noisier one (hyrel-fake-controller --help lists its settings):

    \b
      hyrel-fake-controller --move-time 0.01 --faults "drop_ok=0.01" --link /tmp/printer &
      hyrel-send JOB --port /tmp/printer
    """
    console, errors = Out(), Out(stderr=True)
    try:
        if list_ports or history_list:
            if job is not None:
                raise UsageError("--list-ports and --history-list take no JOB")
            if list_ports:
                offline.list_serial_ports(console)
            if history_list:
                offline.history_list(console, history, config)
            raise typer.Exit(EXIT_OK)
        if console_mode:
            given: dict[str, object] = {
                **{"JOB": job, "--dry-run": dry_run, "--check": check, "--framed": framed},
                **{"--force": force, "--report": report, "--server": server},
                **{"--from-line": from_line is not None, "--from-layer": from_layer is not None},
            }
            terminal = ConsoleOptions(
                port,
                LinkRequest(baud, flow, rx_buffer, max_lines, _value(protocol)),
                machine,
                loadout,
                reply_timeout,
                history,
                no_history,
                fake_log,
                not no_header,
            )
            raise typer.Exit(run_console(terminal, load_user_config(config), given))
        if from_line is not None and from_layer is not None:
            raise UsageError("--from-line and --from-layer both say where to resume: give one")
        if server is not None and farm:
            if printer or release:
                raise UsageError("--printer and --release name one printer: not with --farm")
            if recover is None and (from_line is not None or from_layer is not None):
                raise UsageError("with --farm, --from-line and --from-layer go with --resume ID")
            request = ServerRequest(printer, api_key, job, list_jobs, cancel, release)
            farm_request = FarmRequest(
                require or [], priority, copies, recover, from_line, from_layer
            )
            raise typer.Exit(run_with_farm(console, server, request, farm_request))
        if server is not None and (from_line is not None or from_layer is not None):
            raise UsageError("--from-line and --from-layer resume on a port, not with --server")
        if require or farm or priority or copies != 1 or recover is not None:
            raise UsageError(
                "--farm, --require, --priority, --copies and --resume go with --server URL"
            )
        if server is not None:
            request = ServerRequest(printer, api_key, job, list_jobs, cancel, release)
            code = run_with_server(console, server, request)
            raise typer.Exit(code)
        if list_jobs or cancel is not None or printer or api_key or release:
            raise UsageError(
                "--list, --cancel, --release, --printer and --api-key go with --server URL"
            )
        if job is None:
            raise UsageError("give the JOB to send (a G-code file)")
        if framed and not dry_run:
            raise UsageError("--framed shows the wire of a dry run: add --dry-run")
        user = load_user_config(config)
        last = offline.port_machine(port, history, user) if check else None
        plan = plan_job(job, JobRequest(loadout, machine, not no_header, last), user)
        if from_layer is not None:
            from_line = layer_line(job, from_layer)
        if from_line is not None:
            plan = recovery_plan(plan, from_line, recovery_home)
            announce_recovery(errors if dry_run or check else console, plan, from_layer)
        if check or dry_run or not plan.checked_as_it_streams:
            findings = offline.check_job(plan, errors)
            if check:
                pace = offline.printer_pace(port, history, user, plan.profile.name or "")
                raise typer.Exit(offline.check_verdict(console, plan, findings, pace))
            if dry_run:  # a preview: shown even when the findings would refuse the job
                offline.dry_run(errors, plan, framed, _value(protocol))
                raise typer.Exit(EXIT_OK)
            plan.refuse(findings, force, "--force")
        options = SendOptions(
            port,
            LinkRequest(baud, flow, rx_buffer, max_lines, _value(protocol)),
            reply_timeout,
            reconnect_wait,
            history,
            no_history,
            fake_log,
            force,
            report,
            tuple(sys.argv[1:]),
        )
        code = asyncio.run(send_job(console, errors, plan, user, options))
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM or SIGHUP before the job's first line
        with contextlib.suppress(OSError):  # a closed terminal (SIGHUP) takes no words
            errors.print("interrupted before streaming began.")
        code = exit_code_of_stop()
    except (JobError, ConfigError, UsageError) as exc:
        errors.print(f"error: {exc}", markup=False)
        code = EXIT_BAD_INPUT
    except SafeStopError as exc:
        errors.print(f"not safe: {exc}", markup=False)
        code = EXIT_NOT_SAFE
    except LinkError as exc:
        errors.print(f"link failure: {exc}", markup=False)
        code = EXIT_LINK_FAILURE
    except (ControllerError, ProtocolError) as exc:
        errors.print(f"controller error: {exc}", markup=False)
        code = EXIT_CONTROLLER_ERROR
    raise typer.Exit(code)


def _value(protocol: Protocol | None) -> str | None:
    return protocol.value if protocol is not None else None


def main() -> None:
    """Console-script entry point."""
    interrupt_on_stop_signals()  # SIGTERM, SIGHUP: as Ctrl-C, never the end on the spot
    try:
        app()
    except KeyboardInterrupt:
        with contextlib.suppress(OSError):  # a closed terminal (SIGHUP) takes no words
            Out(stderr=True).print("interrupted before streaming began.")
        raise SystemExit(exit_code_of_stop()) from None
    except HostError as exc:  # a last guard: one sentence, never a traceback
        Out(stderr=True).print(f"error: {exc}", markup=False)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        Out(stderr=True).print(f"error: {where}{exc.strerror}", markup=False)
        raise SystemExit(EXIT_BAD_INPUT) from None


if __name__ == "__main__":
    main()
