"""``hyrel-send``: stream one G-code job from a terminal. Presentation only."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from datetime import datetime
from itertools import chain
from pathlib import Path
from typing import Annotated, BinaryIO

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    Progress,
    TaskID,
    TaskProgressColumn,
    TextColumn,
    TimeRemainingColumn,
)

from repetrel_host.config import (
    Library,
    LinkDefaults,
    Loadout,
    Machine,
    UserConfig,
    find_loadout,
    load_library,
    load_loadout,
    load_user_config,
)
from repetrel_host.console import ConsoleObserver
from repetrel_host.errors import (
    ConfigError,
    ControllerError,
    HostError,
    JobError,
    LinkError,
    ProtocolError,
)
from repetrel_host.gcode import addressing
from repetrel_host.gcode.header import header_commands, safe_stop_commands
from repetrel_host.gcode.lint import Finding, Linter
from repetrel_host.job import HostAction, Job, JobItem, JobLine
from repetrel_host.link import FAKE_PORT, BuiltInFake
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.dialects.reprap import RepRapDialect as HostProtocol
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import clean_line
from repetrel_host.sender import Outcome, Sender, Summary, stream

# Exit codes: distinct per kind of failure so scripts can tell them apart.
EXIT_OK = 0
EXIT_BAD_INPUT = 2  # also what typer uses for a bad option
EXIT_LINK_FAILURE = 3
EXIT_CONTROLLER_ERROR = 4
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C

PORT_ENV = "HYREL_PORT"
# Jobs up to this size are checked whole before the first line goes (a fraction of a
# second); bigger ones are checked as they stream, so that they start at once.
PRECHECK_LIMIT = 4 << 20
PROGRESS_REFRESH = 0.1  # seconds between progress bar updates

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)


@dataclass(frozen=True)
class LinkOptions:
    """The link as given on the command line (None: not given)."""

    port: str | None
    baud: int | None
    flow: FlowMode | None
    rx_buffer: int | None
    max_lines: int | None
    reply_timeout: float


@dataclass(frozen=True)
class Plan:
    """Everything decided before the port opens."""

    job: Job
    machine: Machine | None
    loadout: Loadout | None
    header: list[JobLine]
    safe_stop: list[str]

    def items(self, check: Callable[[int, str], None] | None = None) -> Iterator[JobItem]:
        return chain(self.header, self.job.items(check))

    def linter(self, streaming: bool = False) -> Linter:
        machine = self.machine
        return Linter(
            firmware=machine.firmware if machine else None,
            positions=machine.yokes * addressing.ADDRESSES_PER_YOKE if machine else None,
            loaded_tools=self.loadout.loaded_tools if self.loadout else None,
            streaming=streaming,
        )


@app.command()
def send(
    job: Annotated[Path, typer.Argument(help="G-code file to stream.", readable=False)],
    port: Annotated[
        str | None,
        typer.Option(
            help=f"Serial port or pyserial URL; 'fake' for the built-in fake controller. "
            f"Default: ${PORT_ENV}, then [printer] port in the configuration, else the fake."
        ),
    ] = None,
    baud: Annotated[int | None, typer.Option(help="Baud rate (default 115200).", min=1)] = None,
    flow: Annotated[
        FlowMode | None,
        typer.Option(help="buffered (default): several lines in flight; unbuffered: one."),
    ] = None,
    rx_buffer: Annotated[
        int | None,
        typer.Option(help="Controller receive buffer in bytes (default 128).", min=2),
    ] = None,
    max_lines: Annotated[
        int | None, typer.Option(help="Most lines in flight at once (default 8).", min=1)
    ] = None,
    reply_timeout: Annotated[
        float,
        typer.Option(
            help="Seconds of silence after which the controller is taken as gone.", min=0.1
        ),
    ] = DEFAULT_REPLY_TIMEOUT,
    loadout: Annotated[
        Path | None,
        typer.Option(help="Loadout TOML (or the name of a shipped one): which head is where."),
    ] = None,
    machine: Annotated[
        str | None, typer.Option(help="Machine profile, when there is no loadout.")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="Configuration file (default ~/.config/repetrel-host/config.toml)."),
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
    history: Annotated[
        Path | None,
        typer.Option(help="Folder for the print history (default ~/.local/share/repetrel-host)."),
    ] = None,
    no_history: Annotated[
        bool, typer.Option("--no-history", help="Do not keep the transmitted stream.")
    ] = False,
    fake_log: Annotated[
        Path | None,
        typer.Option(help="Where the built-in fake writes the commands it executed."),
    ] = None,
) -> None:
    """Stream JOB to a Hyrel (or Marlin-style) controller and show progress."""
    console = Console(highlight=False, soft_wrap=True)
    errors = Console(stderr=True, highlight=False, soft_wrap=True)
    try:
        user = load_user_config(config)
        plan = _plan(job, loadout, machine, user, no_header)
        streaming_check = not (check or dry_run) and plan.job.size > PRECHECK_LIMIT
        findings = [] if streaming_check else _lint(plan)
        for finding in findings:
            errors.print(finding.format(plan.job.name), markup=False)
        refused = [f for f in findings if f.severity == "error"]
        if check:
            verdict = "refused" if refused else "ok"
            console.print(f"{plan.job.name}: {verdict} ({len(findings)} findings)")
            raise typer.Exit(EXIT_BAD_INPUT if refused else EXIT_OK)
        if dry_run:  # a preview: shown even when the findings would refuse the job
            _dry_run(plan, framed)
            raise typer.Exit(EXIT_OK)
        if refused and not force:
            raise JobError(f"{plan.job.name}: not sent ({len(refused)} errors; --force sends)")
        link = LinkOptions(port, baud, flow, rx_buffer, max_lines, reply_timeout)
        checker = _streaming_checker(plan, errors, force) if streaming_check else None
        if checker is not None:
            console.print(
                f"{plan.job.name} is {plan.job.size / 1e6:.0f} MB: checked as it streams; a line "
                "it would refuse stops the job safely there (--check checks it all first)."
            )
        code = _send(console, plan, user, link, history, no_history, fake_log, checker)
    except (JobError, ConfigError) as exc:
        errors.print(f"error: {exc}", markup=False)
        code = EXIT_BAD_INPUT
    except LinkError as exc:
        errors.print(f"link failure: {exc}", markup=False)
        code = EXIT_LINK_FAILURE
    except (ControllerError, ProtocolError) as exc:
        errors.print(f"controller error: {exc}", markup=False)
        code = EXIT_CONTROLLER_ERROR
    raise typer.Exit(code)


def _plan(
    job_path: Path,
    loadout_path: Path | None,
    machine_name: str | None,
    user: UserConfig,
    no_header: bool,
) -> Plan:
    loadout_path = loadout_path or user.printer.loadout
    machine_name = machine_name or (None if loadout_path else user.printer.machine)
    # Machines and heads are read only when a job names them: a plain job starts sooner.
    library = load_library(user) if loadout_path or machine_name else Library({}, {})
    loadout = load_loadout(find_loadout(loadout_path), library) if loadout_path else None
    machine = loadout.machine if loadout else None
    if machine_name is not None:
        if loadout is not None and machine_name != loadout.machine_name:
            raise ConfigError(
                f"--machine {machine_name} is not the loadout's machine, {loadout.machine_name}"
            )
        machine = library.machines.get(machine_name)
        if machine is None:
            known = ", ".join(sorted(library.machines))
            raise ConfigError(f"unknown machine '{machine_name}' (known: {known})")
    job = Job(job_path, pause_sync=machine.pause_sync if machine else "M400")
    header = [
        JobLine(0, 0, command, 0, origin)
        for command, origin in (header_commands(loadout) if loadout and not no_header else [])
    ]
    if machine is None:
        safe_stop = safe_stop_commands("v5")
    else:
        safe_stop = machine.safe_stop or safe_stop_commands(machine.firmware)
    if user.host.safe_stop is not None:
        safe_stop = user.host.safe_stop
    return Plan(job, machine, loadout, header, [clean_line(c) for c in safe_stop])


def _lint(plan: Plan) -> list[Finding]:
    """Check the whole file first: a bad line is found before anything moves."""
    linter = plan.linter()
    findings = linter.check_all((number, command) for number, command, _, _ in plan.job.commands())
    if linter.commands == 0:
        raise JobError(f"{plan.job.path}: holds no G-code command (nothing to send)")
    return findings


def _streaming_checker(plan: Plan, errors: Console, force: bool) -> Callable[[int, str], None]:
    """A check run on each command as it is read: warnings shown, an error stops the job."""
    linter = plan.linter(streaming=True)
    name = plan.job.name

    def check(number: int, command: str) -> None:
        for finding in linter.check(number, command):
            if finding.severity == "error" and not force:
                raise JobError(f"{finding.format(name)} (--force sends despite it)")
            errors.print(finding.format(name), markup=False)

    return check


def _dry_run(plan: Plan, framed: bool) -> None:
    """The commands on stdout, exactly as they would go; host actions noted on stderr."""

    def commands() -> Iterator[str]:
        for item in plan.items():
            if isinstance(item, HostAction):
                sys.stderr.write(f"{item.position}: host {item.kind}: {item.message}\n")
            else:
                yield item.command

    if framed:
        from repetrel_host.testing.loopback import wire_preview  # only a preview needs it

        for data in wire_preview(commands()):
            sys.stdout.write(data.decode("ascii"))
    else:
        for command in commands():
            sys.stdout.write(command + "\n")
    sys.stdout.flush()


def _send(
    console: Console,
    plan: Plan,
    user: UserConfig,
    options: LinkOptions,
    history: Path | None,
    no_history: bool,
    fake_log: Path | None,
    checker: Callable[[int, str], None] | None,
) -> int:
    # Command line first, then the machine profile's link defaults.
    defaults = plan.machine.link if plan.machine else LinkDefaults()
    baud = options.baud or defaults.baud
    flow_control = FlowControl(
        options.flow or FlowMode(defaults.flow),
        rx_buffer=options.rx_buffer or defaults.rx_buffer,
        max_lines=options.max_lines or defaults.max_lines,
    )
    port = options.port or os.environ.get(PORT_ENV) or user.printer.port or FAKE_PORT
    stem = f"{datetime.now():%Y%m%d-%H%M%S}-{plan.job.path.stem}"
    history_dir = history or user.host.history_dir or _default_history_dir()
    observer = ConsoleObserver(console, user.host, history_dir / f"{stem}-reports.log")
    with ExitStack() as stack:
        wire_log: BinaryIO | None = None
        if not no_history:
            history_file = history_dir / f"{stem}.gcode"
            try:
                history_dir.mkdir(parents=True, exist_ok=True)
                wire_log = stack.enter_context(history_file.open("wb"))
            except OSError as exc:
                raise ConfigError(
                    f"cannot write the print history {history_file}: {exc.strerror}"
                ) from None
        fake: BuiltInFake | None = None
        if port == FAKE_PORT:
            # The fake's link runs at the chosen baud rate: 10 bits on the wire per byte.
            fake = BuiltInFake(fake_log, ["--bandwidth", str(baud / 10), "--latency", "0.001"])
            port = fake.start()
            stack.callback(fake.stop)
            console.print(
                f"No printer port given: streaming to the built-in fake controller on {port}."
            )
        stack.callback(observer.close)
        core = HostProtocol(flow_control, reply_timeout=options.reply_timeout)
        summary = asyncio.run(
            _stream_with_progress(console, plan, port, baud, core, observer, wire_log, checker)
        )
    _print_summary(console, summary, plan.job)
    if wire_log is not None:
        console.print(f"Print history (the stream as transmitted): {wire_log.name}")
    if fake is not None:
        console.print(f"The fake controller's log of executed commands: {fake.log_path}")
    return EXIT_INTERRUPTED if summary.outcome is Outcome.CANCELLED else EXIT_OK


def _default_history_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "repetrel-host" / "history"


async def _stream_with_progress(
    console: Console,
    plan: Plan,
    port: str,
    baud: int,
    core: HostProtocol,
    observer: ConsoleObserver,
    wire_log: BinaryIO | None,
    checker: Callable[[int, str], None] | None,
) -> Summary:
    loop = asyncio.get_running_loop()
    job = plan.job
    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[lines]} lines"),
        TextColumn("{task.fields[rate]:.0f} lines/s"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )
    task = progress.add_task(job.name, total=max(job.size, 1), lines=0, rate=0.0)
    started = time.monotonic()

    async def refresh() -> None:
        while True:
            _update(progress, task, observer, started)
            await asyncio.sleep(PROGRESS_REFRESH)

    refresher: asyncio.Task[None] | None = None

    def on_open(sender: Sender) -> None:
        # The bar appears only once the port is open: a port that fails shows no bar.
        nonlocal refresher
        loop.add_signal_handler(signal.SIGINT, sender.cancel)
        progress.start()
        refresher = asyncio.create_task(refresh())

    try:
        summary = await stream(
            port,
            baud,
            core,
            plan.items(checker),
            observer,
            on_open,
            safe_stop=plan.safe_stop,
            wire_log=wire_log,
        )
        if summary.outcome is Outcome.COMPLETED:
            observer.offset = job.size  # trailing comments count as sent
    except (LinkError, ControllerError, ProtocolError, JobError) as exc:
        if refresher is None:
            raise  # the port never opened: nothing was sent
        raise type(exc)(f"{exc}; {_last_acknowledged(job, observer)}") from None
    finally:
        if refresher is not None:
            refresher.cancel()
            loop.remove_signal_handler(signal.SIGINT)
            _update(progress, task, observer, started)
            progress.stop()
    return summary


def _last_acknowledged(job: Job, observer: ConsoleObserver) -> str:
    if observer.last is None:
        return "no line of the job was acknowledged"
    line = observer.last
    return (
        f"the last line the controller acknowledged is {line.position} "
        f"(command {line.index} of the job, {line.command})"
    )


def _update(progress: Progress, task: TaskID, observer: ConsoleObserver, started: float) -> None:
    elapsed = max(time.monotonic() - started, 1e-6)
    progress.update(
        task, completed=observer.offset, lines=observer.lines, rate=observer.lines / elapsed
    )


def _print_summary(console: Console, summary: Summary, job: Job) -> None:
    rate = summary.lines / summary.seconds if summary.seconds > 0 else 0.0
    verdict = "done" if summary.outcome is Outcome.COMPLETED else "stopped (interrupted)"
    console.print(
        f"{job.name}: {verdict}: {summary.lines} lines in {summary.seconds:.2f} s "
        f"({rate:.0f} lines/s), {summary.resends} resend requests, "
        f"{summary.retransmissions} lines sent again."
    )


def main() -> None:
    """Console-script entry point."""
    try:
        app()
    except KeyboardInterrupt:
        Console(stderr=True, soft_wrap=True).print("interrupted before streaming began.")
        raise SystemExit(EXIT_INTERRUPTED) from None
    except HostError as exc:  # a last guard: one sentence, never a traceback
        Console(stderr=True, soft_wrap=True).print(f"error: {exc}", markup=False)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        Console(stderr=True, soft_wrap=True).print(f"error: {where}{exc.strerror}", markup=False)
        raise SystemExit(EXIT_BAD_INPUT) from None


if __name__ == "__main__":
    main()
