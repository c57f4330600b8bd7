"""``hyrel-send``: stream one G-code job from a terminal.

Presentation only: the plan is ``planning``'s, the streaming the session's. This
module parses options, opens a session, draws progress, answers M0 pauses at the
keyboard and turns Ctrl-C into the safe stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shlex
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from repetrel_host import __version__
from repetrel_host.cli.actions import (
    Connecting,
    ConsoleActions,
    read_line,
    stop_delayed_text,
    summary_text,
)
from repetrel_host.cli.console import CONSOLE_HELP, ConsoleOptions, run_console
from repetrel_host.cli.stop_signals import (
    StopSignals,
    exit_code_of_stop,
    interrupt_on_stop_signals,
    stopping_text,
)
from repetrel_host.config import UserConfig, load_user_config
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
from repetrel_host.gcode.analysis import scan_marks, slicer_estimate
from repetrel_host.gcode.lint import Finding, Severity
from repetrel_host.links import FAKE_PORT, FakeLink
from repetrel_host.protocol.dialects import create_dialect
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.flow import FlowMode
from repetrel_host.session import history as print_history
from repetrel_host.session.connect import connect
from repetrel_host.session.events import (
    Message,
    Notice,
    Paused,
    PauseReason,
    Resend,
    State,
    StopDelayed,
)
from repetrel_host.session.job import HostAction
from repetrel_host.session.planning import (
    PORT_ENV,
    JobPlan,
    JobRequest,
    LinkRequest,
    choose_port,
    default_history_dir,
    history_file,
    layer_line,
    link_settings,
    plan_job,
    replan_for_firmware,
    resumed,
)
from repetrel_host.session.print_job import PrintJob
from repetrel_host.session.printer import Printer
from repetrel_host.session.pump import Outcome, Summary
from repetrel_host.session.resume import (
    RESUME_SOURCE,
    HomeAxes,
    resume_command,
    resume_from,
    resume_window,
)
from repetrel_host.session.settings import RECONNECT_WAIT

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import TaskID

    from repetrel_host.cli.display import JobProgress, JobStatus

# Exit codes: distinct per kind of failure so scripts can tell them apart.
EXIT_OK = 0
EXIT_BAD_INPUT = 2  # also what typer uses for a bad option
EXIT_LINK_FAILURE = 3
EXIT_CONTROLLER_ERROR = 4
EXIT_NOT_SAFE = 5  # stopped, but the safe stop was not confirmed: go and look at the machine
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C

PROGRESS_REFRESH = 0.1  # seconds between progress bar updates
TEMPERATURE_POLL = 2.0  # seconds between M105s (or M155's reports) for the status line
# Every line sent, the job not done this long after: the controller holds the rest
# (Hyrel's 8 KB), which is said once.
FINISHING_NOTE = 1.0
_CONTROL = re.compile(r"[\x00-\x09\x0b-\x1f]")


class Protocol(StrEnum):
    REPRAP = "reprap"
    HYREL = "hyrel"


app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)


class Out:
    """A terminal stream through rich, imported on first use: a job's first line goes out
    before rich's modules (a good share of the start-up) have been read."""

    def __init__(self, stderr: bool = False) -> None:
        self._stderr = stderr
        self._console: Console | None = None

    @property
    def console(self) -> Console:
        if self._console is None:
            from rich.console import Console

            self._console = Console(stderr=self._stderr, highlight=False, soft_wrap=True)
        return self._console

    def print(self, text: str, markup: bool | None = None) -> None:
        # A terminal that went away (a closed window, a dropped ssh session: SIGHUP) takes
        # no more words; the run goes on to its safe stop, and its record says how it ended.
        with contextlib.suppress(OSError):
            self.console.print(text, markup=markup)

    def bell(self) -> None:
        self.console.bell()


@dataclass(frozen=True)
class Options:
    """What the command line says about the run, beyond the job's plan."""

    port: str | None
    link: LinkRequest
    reply_timeout: float
    reconnect_wait: float
    history: Path | None
    no_history: bool
    fake_log: Path | None
    force: bool
    report: bool = False
    command_line: tuple[str, ...] = ()  # hyrel-send's arguments, for the resume hint


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
    resume_home: Annotated[
        HomeAxes,
        typer.Option(
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
    resume: Annotated[
        int | None,
        typer.Option(
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
                _list_ports(console)
            if history_list:
                _history_list(console, history, config)
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
            if resume is None and (from_line is not None or from_layer is not None):
                raise UsageError("with --farm, --from-line and --from-layer go with --resume ID")
            request = ServerRequest(printer, api_key, job, list_jobs, cancel, release)
            farm_request = FarmRequest(
                require or [], priority, copies, resume, from_line, from_layer
            )
            raise typer.Exit(_with_farm(console, server, request, farm_request))
        if server is not None and (from_line is not None or from_layer is not None):
            raise UsageError("--from-line and --from-layer resume on a port, not with --server")
        if require or farm or priority or copies != 1 or resume is not None:
            raise UsageError(
                "--farm, --require, --priority, --copies and --resume go with --server URL"
            )
        if server is not None:
            request = ServerRequest(printer, api_key, job, list_jobs, cancel, release)
            code = _with_server(console, server, request)
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
        plan = plan_job(job, JobRequest(loadout, machine, not no_header), user)
        if from_layer is not None:
            from_line = layer_line(job, from_layer)
        if from_line is not None:
            plan = resumed(plan, from_line, resume_home)
            _announce_resume(errors if dry_run or check else console, plan, from_layer)
        if check or dry_run or not plan.checked_as_it_streams:
            findings = _check(plan, errors)
            if check:
                refused = [f for f in findings if f.severity is Severity.ERROR]
                verdict = "refused" if refused else "ok"
                console.print(
                    f"{plan.job.name}: {verdict} ({len(findings)} findings) with machine "
                    f"profile {plan.profile.describe()}",
                    markup=False,
                )
                raise typer.Exit(EXIT_BAD_INPUT if refused else EXIT_OK)
            if dry_run:  # a preview: shown even when the findings would refuse the job
                link = link_settings(LinkRequest(protocol=_value(protocol)), plan.machine)
                # On stderr: stdout holds the commands alone, for a script to read.
                errors.print(
                    f"{plan.job.name}: a dry run, nothing sent; machine profile "
                    f"{plan.profile.describe()}, {link.protocol} protocol",
                    markup=False,
                )
                _dry_run(plan, framed, link.protocol)
                raise typer.Exit(EXIT_OK)
            plan.refuse(findings, force, "--force")
        options = Options(
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
        code = asyncio.run(_send(console, errors, plan, user, options))
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


@dataclass(frozen=True)
class ServerRequest:
    """What hyrel-send --server was asked to do."""

    printer: str | None
    api_key: str | None
    job: Path | None
    list_jobs: bool
    cancel: int | None
    release: bool


@dataclass(frozen=True)
class FarmRequest:
    """What hyrel-send --server URL --farm asks of the farm's job."""

    requires: list[str]
    priority: int
    copies: int
    resume: int | None = None  # a farm job to go on with, on the printer that printed it
    from_line: int | None = None
    from_layer: int | None = None


def _with_farm(console: Out, url: str, request: ServerRequest, farm: FarmRequest) -> int:
    """hyrel-send --server URL --farm: submit to the farm and follow, list, cancel."""
    from repetrel_host.server import client

    server = client.ServerClient(url, request.api_key)

    def show(text: str) -> None:
        console.print(text, markup=False)

    if request.cancel is not None:
        answer = client.farm_cancel(server, request.cancel)
        how = "cancelling (its node stops it, the safe stop first)" * bool(answer.get("cancelling"))
        show(f"farm job {request.cancel}: {how or answer['state']}")
        return EXIT_OK
    if request.list_jobs:
        for line in client.farm_jobs(server):
            show(line)
        if request.job is None:
            return EXIT_OK
    events = server.events(None, "/v1/farm/events")
    if farm.resume is not None:
        if request.job is not None:
            raise UsageError("--resume ID goes on with the farm's own file: give no JOB")
        next(events)  # subscribed before the job exists: nothing is missed
        answer = client.farm_resume(server, farm.resume, farm.from_line, farm.from_layer)
        (made,) = answer["jobs"]
        show(
            f"farm job {farm.resume}: the rest, from line {answer['from_line']}, queued as "
            f"farm job {made} for the printer that printed it"
        )
        return client.farm_follow(server, [made], events, show)
    if request.job is None:
        raise UsageError("give the JOB to send to the farm (or --list, --cancel ID, --resume ID)")
    next(events)  # subscribed before the job exists: nothing is missed
    queued = client.farm_submit(server, request.job, farm.requires, farm.priority, farm.copies)
    for finding in queued["findings"]:
        show(finding)
    ids = ", ".join(map(str, queued["jobs"]))
    show(
        f"{queued['name']}: queued in the farm as job {ids} ({queued['requires']}); "
        f"printers that can take it: {', '.join(queued['eligible'])}"
    )
    return client.farm_follow(server, queued["jobs"], events, show)


def _with_server(console: Out, url: str, request: ServerRequest) -> int:
    """hyrel-send --server: submit and follow a job, list jobs, cancel one, release."""
    from repetrel_host.server import client

    server = client.ServerClient(url, request.api_key)
    if request.cancel is not None:
        ended = client.cancel(server, request.cancel)
        stopping = f" (stopping: {ended['stopping']})" if ended.get("stopping") else ""
        console.print(
            f"job {request.cancel} ({ended['name']}): {ended['state']}{stopping}", markup=False
        )
        return EXIT_OK
    name = server.printer(request.printer)
    job = request.job
    if job is None and request.release:
        server.request("POST", f"/v1/printers/{name}/release")
        console.print(f"printer {name}: the queue goes on", markup=False)
    if request.list_jobs:
        for line in client.list_jobs(server, name):
            console.print(line, markup=False)
    if job is None:
        if request.list_jobs or request.release:
            return EXIT_OK
        raise UsageError("give the JOB to send to the server (or --list, --cancel ID, --release)")
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn

    progress = Progress(
        TextColumn(f"[bold]{escape(job.name)}"),
        BarColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[lines]} lines"),
        console=console.console,
    )
    task = progress.add_task(job.name, total=1, lines=0)

    def update(done: int, size: int, lines: int) -> None:
        progress.start()
        progress.update(task, completed=done, total=max(size, 1), lines=lines)

    def show(text: str) -> None:
        console.print(text, markup=False)

    try:
        return client.follow(server, name, job, show, update, request.release)
    finally:
        progress.stop()


def _check(plan: JobPlan, errors: Out) -> list[Finding]:
    """Check the whole file and print the findings."""
    findings = plan.check()
    for finding in findings:
        errors.print(finding.format(plan.job.name), markup=False)
    return findings


def _dry_run(plan: JobPlan, framed: bool, protocol: str) -> None:
    """The commands on stdout, exactly as they would go; host actions noted on stderr."""
    pause_sync = create_dialect(protocol).pause_command  # M0 where the controller waits
    # A resumed job's preamble is shown with why each line is there (not on the wire).
    notes = iter(plan.resume.preamble if plan.resume is not None and not framed else [])

    def commands() -> Iterator[str]:
        for item in plan.items(pause_sync=pause_sync):
            if isinstance(item, HostAction):
                sys.stderr.write(f"{item.position}: host {item.kind}: {item.message}\n")
            elif item.source == RESUME_SOURCE and (note := next(notes, None)) is not None:
                yield f"{item.command} ; {note.why}"
            else:
                yield item.command

    if framed:
        from repetrel_host.session.loopback import wire_preview  # only a preview needs it

        for data in wire_preview(commands(), protocol=protocol):
            # Hyrel's control bytes (the ping, 0x07, would ring the terminal's bell) shown.
            text = data.decode("ascii", errors="replace")
            sys.stdout.write(_CONTROL.sub(lambda m: f"<0x{ord(m.group()):02x}>", text))
    else:
        for command in commands():
            sys.stdout.write(command + "\n")
    sys.stdout.flush()


def _list_ports(console: Out) -> None:
    """hyrel-send --list-ports: one line a port, candidates marked."""
    from repetrel_host.links.ports import describe, list_ports

    found = list_ports()
    for port in found:
        console.print(describe(port), markup=False)
    if not found:
        console.print("no serial ports found", markup=False)


def _history_list(console: Out, folder: Path | None, config: Path | None) -> None:
    """hyrel-send --history-list: the newest runs, how each ended."""
    user = load_user_config(config)
    folder = folder or user.host.history_dir or default_history_dir()
    entries = print_history.entries(folder)
    if not entries:
        console.print(f"no prints in {folder} yet", markup=False)
        return
    console.print(f"Print history in {folder} (newest first):", markup=False)
    for entry in entries:
        line = print_history.describe(entry.run, entry.record, entry.progress, entry.alive)
        console.print(line, markup=False)
        if entry.killed and entry.progress is not None:
            console.print(f"  {_killed_resume(entry.progress, entry.run.stream)}", markup=False)


def _killed_resume(progress: print_history.Progress, stream: Path) -> str:
    """How a killed run resumes: from its progress record's line, uncertainly (what was
    sent after the last acknowledged line may have run, and the record may be a moment
    behind the stream)."""
    line = progress.resume_line
    if line is None and progress.all_sent:
        ran = "known to have run" if progress.known_to_run else "acknowledged"
        return f"nothing to resume: every line of the job was {ran}"
    after = print_history.lines_after(stream, progress.stream_bytes)
    later = (
        ""
        if after == 0
        else f"; the stream has {after if after is not None else 'more'} lines after that, "
        "sent later"
    )
    if progress.sent:
        uncertain = f"uncertain: lines up to {progress.sent} were sent and may have run{later}"
    else:
        uncertain = f"uncertain: no line of the job was sent when last recorded{later}"
    what = "to resume" if line is not None else "no line is known to have run: to start again"
    if not progress.command:  # a library user's run: the line only
        where = f"print({progress.path!r}, from_line={line})" if line is not None else "again"
        return f"{what} ({uncertain}): {where}"
    if line is not None:
        command = resume_command(progress.command, line)
    else:
        command = shlex.join(["hyrel-send", *progress.command])
    if progress.cwd and progress.cwd != os.getcwd():  # a job's relative path is from there
        command = f"cd {shlex.quote(progress.cwd)} && {command}"
    return f"{what} ({uncertain}): {command}"


async def _send(
    console: Out, errors: Out, plan: JobPlan, user: UserConfig, options: Options
) -> int:
    link = link_settings(options.link, plan.machine)
    port, chosen_because = choose_port(options.port, user)
    if chosen_because is not None:
        console.print(f"{chosen_because}.", markup=False)
    # On stderr, as the failure's sentence: stdout holds the run's own story.
    connecting = Connecting(lambda text: errors.print(text, markup=False))
    connecting.start(port, link.baud)
    printer = await connect(
        port,
        flow=link.flow,
        baud=link.baud,
        protocol=link.protocol,
        checksum=link.checksum,
        config=user,
        # A link that fails mid-job is reopened only to send the safe stop it missed: the
        # job ends then (or after reconnect_wait), and the session with it.
        reconnect_wait=options.reconnect_wait,
        poll_interval=TEMPERATURE_POLL,
        poll_while_printing=True,
        reply_timeout=options.reply_timeout,
        fake_log=options.fake_log,
        on_event=connecting,
    )
    connecting.connected = True
    try:
        plan = _plan_for(printer, plan, user, errors, options.force)
        job, estimate = await _stream(console, errors, printer, plan, user, options)
    except (LinkError, ControllerError, ProtocolError, SafeStopError):
        if printer.last_job is not None:  # the job failed: then the failure's sentence
            _print_resume_hint(console, printer.last_job, options)
        raise
    finally:
        await printer.close()
    summary = await job.wait()
    _print_summary(console, summary, plan, job.where(), estimate)
    if summary.outcome is not Outcome.COMPLETED:
        _print_resume_hint(console, job, options)
    _print_report(console, job, options.report)
    if job.history is not None:
        console.print(f"Print history (the stream as transmitted): {job.history}", markup=False)
    if isinstance(printer.link, FakeLink) and options.fake_log is not None:
        console.print(
            f"The fake controller's log of executed commands: {printer.link.log_path}",
            markup=False,
        )
    return exit_code_of_stop() if summary.outcome is Outcome.CANCELLED else EXIT_OK


def _announce(console: Out, printer: Printer, plan: JobPlan) -> None:
    """What the run is talking to and why, once its first lines are on their way."""
    if isinstance(printer.link, FakeLink) and printer.link.port == FAKE_PORT:
        console.print(
            "No printer port given: streaming to the built-in fake controller on "
            f"{printer.link.device}.",
            markup=False,
        )
    if printer.probe is ProbeKind.COMMAND:
        console.print(
            "The controller's answer to a bad checksum names a line it never got: "
            "probing with numbered M105 lines (they run; they are harmless), and, as "
            "OctoPrint's virtual printer, at most 64 bytes in flight."
        )
    elif printer.probe is ProbeKind.ANSWER:
        console.print(
            "Hyrel's own link: the job is done once the controller ran its last line "
            "(it asks M115 to be sure, and the link stays alive until then)."
        )
    console.print(f"Machine profile: {plan.profile.describe()}", markup=False)
    if plan.checked_as_it_streams:
        console.print(
            f"{plan.job.name} is {plan.job.size / 1e6:.0f} MB: checked as it streams; a line "
            "it would refuse stops the job safely there (--check checks it all first).",
            markup=False,
        )


def _plan_for(
    printer: Printer, plan: JobPlan, user: UserConfig, errors: Out, force: bool
) -> JobPlan:
    """The plan for the controller that answered: its M115 identity may choose the profile."""
    if printer.firmware is None:
        return plan
    chosen = replan_for_firmware(plan, printer.firmware, user)
    if chosen.profile.name != plan.profile.name and not chosen.checked_as_it_streams:
        chosen.refuse(_check(chosen, errors), force, "--force")
    return chosen


async def _stream(
    console: Out,
    errors: Out,
    printer: Printer,
    plan: JobPlan,
    user: UserConfig,
    options: Options,
) -> tuple[PrintJob, float | None]:
    """Stream the job with a progress bar; returns it once it ended (however it did), and
    the slicer's estimate of the whole print in seconds (None: the file gives none)."""
    loop = asyncio.get_running_loop()
    stream_file = history_file(options.history, user, plan.job)
    history = None if options.no_history else stream_file
    reports = stream_file.with_name(f"{stream_file.stem}-reports.log")  # the same run's name
    snapshots = stream_file.with_name(f"{stream_file.stem}-snapshots")
    actions = ConsoleActions(console, user.host, reports, snapshots)
    job = await printer.print(
        plan,
        force=options.force,
        history=history or False,
        on_action=actions.perform,
        on_warning=lambda text: errors.print(text, markup=False),
        report=options.report,
        command_line=options.command_line,
    )
    _announce(console, printer, plan)
    from rich.markup import escape
    from rich.progress import BarColumn, TaskProgressColumn, TextColumn

    from repetrel_host.cli.display import JobProgress, JobStatus, Keys, TimeLeftColumn

    progress = JobProgress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[lines]} lines"),
        TextColumn("{task.fields[rate]:.0f} lines/s"),
        TimeLeftColumn(),
        console=console.console,
        transient=False,
    )
    task = progress.add_task(escape(job.name), total=max(job.size, 1), lines=0, rate=0.0)
    status = JobStatus(printer, plan.job.path)
    started = time.monotonic()
    interrupts = 0
    keys = Keys(sys.stdin)
    enter: asyncio.Future[None] | None = None  # an M0 waiting for Enter (or p)

    def interrupt(signum: int) -> None:
        nonlocal interrupts
        interrupts += 1
        if job.reconnecting_for_safe_stop:
            console.print("giving up: the safe stop will not be sent")
            job.stop()
            return
        if interrupts == 1:
            job.stop()
            console.print(stopping_text(signum))
            return
        job.stop()  # abandoned (or the wait for a reconnect given up): the end says what

    async def pause_or_resume() -> None:
        with contextlib.suppress(UsageError):  # the job ended meanwhile
            if printer.state is State.PRINTING and not job.stopping:
                console.print("pausing: the controller finishes what it was sent (p resumes)")
                await printer.pause()
            elif printer.state is State.PAUSED:
                await printer.resume()
                console.print("resumed")

    def key(pressed: str) -> None:
        nonlocal enter
        if enter is not None and pressed in "\r\npP":
            enter.set_result(None)
            enter = None
        elif pressed in "pP":
            tasks.add(loop.create_task(pause_or_resume()))
        elif pressed in "eE" and job.stopping and not job.done:
            # Only while a stop is under way (and said to be held up): never by a stray key.
            console.print("emergency stop: M112 sent (the controller halts until it is reset)")
            with contextlib.suppress(HostError):
                printer.emergency_stop()

    async def wait_for_enter() -> bool:
        """Enter at the keyboard (or p); False when standard input is closed."""
        nonlocal enter
        if not keyboard:
            return await read_line(sys.stdin) is not None
        enter = loop.create_future()
        await enter
        return True

    async def refresh() -> None:
        sent_at: float | None = None
        while True:
            _update(progress, task, job, started, status)
            await asyncio.sleep(PROGRESS_REFRESH)
            if sent_at is None and job.all_sent:
                sent_at = time.monotonic()
            elif sent_at is not None and time.monotonic() - sent_at > FINISHING_NOTE:
                sent_at = float("inf")  # said once
                console.print(
                    "every line is sent: waiting until the controller has run the last "
                    "of them (it holds the rest of the job)"
                )

    tasks: set[asyncio.Task[None]] = set()
    signals = StopSignals(interrupt)
    signals.install()
    keyboard = keys.start(key)
    if keyboard:
        console.print("Keys: p pauses and resumes; Ctrl-C stops the job safely.")
    progress.start()
    if console.console.is_terminal:  # where the status line shows (the scan costs CPU a line)
        tasks.add(loop.create_task(status.read_marks()))
    refresher = asyncio.create_task(refresh())
    watcher = asyncio.create_task(_watch(console, printer, job, actions, wait_for_enter, keyboard))
    completed = False
    try:
        completed = (await job.wait()).outcome is Outcome.COMPLETED
    finally:
        keys.stop()
        for running in (refresher, watcher, *tasks):
            running.cancel()
        signals.remove()
        _update(progress, task, job, started, status)
        if completed:  # its last state, as output that is not a terminal keeps it
            progress.update(task, completed=job.size, left="")  # trailing comments too
            progress.status = progress.status.split(" · *")[0]  # no time left to explain
        with contextlib.suppress(OSError):  # a terminal gone (SIGHUP) takes no last frame
            progress.stop()
        await actions.close()
    # The slicer's estimate, beside the real duration in the summary (the file's ends only).
    return job, await asyncio.to_thread(slicer_estimate, plan.job.path)


async def _watch(
    console: Out,
    printer: Printer,
    job: PrintJob,
    actions: ConsoleActions,
    wait_for_enter: Callable[[], Awaitable[bool]],
    keyboard: bool = False,
) -> None:
    """Show what the job tells, and answer an M0 at the keyboard."""
    from rich.markup import escape

    async for event in job.events():
        if isinstance(event, StopDelayed):
            if event.can_emergency_stop and keyboard:
                now = "press e for an emergency stop (M112)"
            elif event.can_emergency_stop:
                now = "use its power switch (an emergency stop, M112, needs the e key here)"
            else:
                now = "use its power switch (M112 would wait its turn too)"
            console.print(
                f"[bold yellow]warning:[/] {escape(stop_delayed_text(event))}. Wait for it; "
                f"or, to stop the machine at once, {now}; or press Ctrl-C again to leave "
                "without it (what is on stays on)."
            )
        elif isinstance(event, Message):
            actions.log(event.text)
            console.print(f"[dim]controller:[/] {escape(event.text)}")
        elif isinstance(event, Resend):
            where = escape(event.position)
            console.print(f"[dim]resend: the controller asked again for {where}[/]")
        elif isinstance(event, Notice):
            console.print(f"[yellow]warning:[/] {escape(event.text)}")
        elif isinstance(event, Paused) and event.reason is PauseReason.REQUEST:
            console.print(
                f"[bold]Paused[/] at {escape(event.position)} - press p to resume "
                "(Ctrl-C stops the job)"
            )
        elif isinstance(event, Paused) and event.reason is PauseReason.M0:
            message = f": {event.message}" if event.message else ""
            console.print(
                f"[bold]Paused[/] at {escape(event.position)}{escape(message)} "
                "- press Enter to resume (Ctrl-C stops the job)"
            )
            if not await wait_for_enter():
                job.stop(
                    JobError(
                        f"{event.position}: M0 waits for the operator, but standard input is closed"
                    )
                )
            else:
                console.print("resumed")
                await printer.resume()


def _update(
    progress: JobProgress, task: TaskID, job: PrintJob, started: float, status: JobStatus
) -> None:
    elapsed = max(time.monotonic() - started, 1e-6)
    progress.status, left = status.show(job, elapsed)
    progress.update(
        task, completed=job.offset, lines=job.lines, rate=job.lines / elapsed, left=left
    )


def _print_summary(
    console: Out, summary: Summary, plan: JobPlan, last: str, estimate: float | None = None
) -> None:
    text = summary_text(plan.job.name, summary, f"interrupted; {last}")
    if estimate is not None and summary.outcome is Outcome.COMPLETED:
        from repetrel_host.cli.display import clock  # loaded with the bar already

        text += f" (the slicer estimated {clock(estimate)})"
    console.print(f"{text}; machine profile {plan.profile.name}.", markup=False)


def _announce_resume(out: Out, plan: JobPlan, layer: int | None) -> None:
    resume = plan.resume
    assert resume is not None
    where = f"layer {layer}, " if layer is not None else ""
    out.print(
        f"Resuming {plan.job.name} at line {resume.line} ({where}asked: line {resume.requested}): "
        f"{len(resume.preamble)} commands first restore what the lines before it set up.",
        markup=False,
    )


def _print_resume_hint(console: Out, job: PrintJob, options: Options) -> None:
    """The command that resumes a job that did not complete, where any of it ran."""
    found = resume_from(job, options.command_line) if options.command_line else None
    line = job.resume_line
    if found is None or line is None:
        return
    console.print(f"To resume from the first line {found[0]}: {found[1]}", markup=False)
    window = resume_window(job, options.command_line)
    if window is not None:  # neither choice is sure: which repeats, which skips
        console.print(window[0].upper() + window[1:], markup=False)
    layer = scan_marks(job.plan.job.path, until_line=line).at(line).layer
    if layer is not None:
        # A reset or a lost link also loses what the controller had taken but not yet run
        # (its queue: a few moves), which the line above would skip.
        again = resume_command(options.command_line, layer.number, "--from-layer")
        console.print(
            "Or from the start of its layer, which after a reset prints what the controller "
            f"had queued again rather than skip it: {again}",
            markup=False,
        )


def _print_report(console: Out, job: PrintJob, asked: bool) -> None:
    """The controller's M773 job report, where it sent one (and where it is kept)."""
    report = job.report
    if report is None:
        if asked:
            console.print(
                "No job report came: the job has no M30, or the controller sends none "
                "(M772 S1 went first).",
                markup=False,
            )
        return
    cut = "" if report.complete else " (cut short)"
    console.print(f"The controller's job report (M773){cut}:", markup=False)
    for line in report.lines:
        console.print(f"  {line}", markup=False)
    if job.report_path is not None:
        console.print(f"Job report: {job.report_path}", markup=False)


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
