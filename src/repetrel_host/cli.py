"""``hyrel-send``: stream one G-code job from a terminal. Presentation only."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from pathlib import Path
from typing import Annotated

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

from repetrel_host.errors import ControllerError, HostError, JobError, LinkError, ProtocolError
from repetrel_host.job import Job, JobLine
from repetrel_host.link import FAKE_PORT, BuiltInFake
from repetrel_host.protocol import replies
from repetrel_host.protocol.host import FlowControl, FlowMode, HostProtocol
from repetrel_host.sender import Observer, Outcome, Sender, Summary, stream

# Exit codes: distinct per kind of failure so scripts can tell them apart.
EXIT_OK = 0
EXIT_BAD_INPUT = 2  # also what typer uses for a bad option
EXIT_LINK_FAILURE = 3
EXIT_CONTROLLER_ERROR = 4
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C

PORT_ENV = "HYREL_PORT"
PROGRESS_REFRESH = 0.1  # seconds between progress bar updates

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)


class ProgressObserver(Observer):
    """Counts acknowledgements; the bar reads them on a timer, not per line."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.lines = 0
        self.offset = 0
        self.last: JobLine | None = None

    def on_acknowledged(self, line: JobLine) -> None:
        self.lines = line.index
        self.offset = line.end_offset
        self.last = line

    def on_message(self, text: str, reply: replies.Reply) -> None:
        if isinstance(reply, replies.Busy | replies.Wait | replies.Start):
            return
        if isinstance(reply, replies.Error):
            return  # line errors: the resend that follows is counted instead
        self.console.print(f"[dim]controller:[/] {text}", highlight=False, markup=True)


@app.command()
def send(
    job: Annotated[Path, typer.Argument(help="G-code file to stream.")],
    port: Annotated[
        str | None,
        typer.Option(
            help=f"Serial port or pyserial URL; 'fake' for the built-in fake controller. "
            f"Default: ${PORT_ENV}, else the fake."
        ),
    ] = None,
    baud: Annotated[int, typer.Option(help="Baud rate.", min=1)] = 115200,
    flow: Annotated[
        FlowMode, typer.Option(help="buffered: several lines in flight; unbuffered: one.")
    ] = FlowMode.BUFFERED,
    rx_buffer: Annotated[
        int, typer.Option(help="Controller receive buffer in bytes (buffered mode).", min=2)
    ] = 128,
    max_lines: Annotated[
        int, typer.Option(help="Most lines in flight at once (buffered mode).", min=1)
    ] = 8,
    fake_log: Annotated[
        Path | None,
        typer.Option(help="Where the built-in fake writes the commands it executed."),
    ] = None,
) -> None:
    """Stream JOB to a Hyrel (or Marlin-style) controller and show progress."""
    console = Console(highlight=False, soft_wrap=True)
    errors = Console(stderr=True, highlight=False, soft_wrap=True)
    try:
        code = _send(console, job, port, baud, flow, rx_buffer, max_lines, fake_log)
    except JobError as exc:
        errors.print(f"error: {exc}", markup=False)
        code = EXIT_BAD_INPUT
    except LinkError as exc:
        errors.print(f"link failure: {exc}", markup=False)
        code = EXIT_LINK_FAILURE
    except (ControllerError, ProtocolError) as exc:
        errors.print(f"controller error: {exc}", markup=False)
        code = EXIT_CONTROLLER_ERROR
    raise typer.Exit(code)


def _send(
    console: Console,
    job_path: Path,
    port: str | None,
    baud: int,
    flow: FlowMode,
    rx_buffer: int,
    max_lines: int,
    fake_log: Path | None,
) -> int:
    job = Job(job_path)
    port = port or os.environ.get(PORT_ENV) or FAKE_PORT
    fake: BuiltInFake | None = None
    if port == FAKE_PORT:
        # The fake's link runs at the chosen baud rate: 10 bits on the wire per byte.
        fake = BuiltInFake(fake_log, ["--bandwidth", str(baud / 10), "--latency", "0.001"])
        port = fake.start()
        console.print(
            f"No printer port given: streaming to the built-in fake controller on {port}."
        )
    try:
        core = HostProtocol(FlowControl(flow, rx_buffer=rx_buffer, max_lines=max_lines))
        observer = ProgressObserver(console)
        summary = asyncio.run(_stream_with_progress(console, job, port, baud, core, observer))
    finally:
        if fake is not None:
            fake.stop()
    _print_summary(console, summary, job)
    if fake is not None:
        console.print(f"The fake controller's log of executed commands: {fake.log_path}")
    return EXIT_INTERRUPTED if summary.outcome is Outcome.CANCELLED else EXIT_OK


async def _stream_with_progress(
    console: Console, job: Job, port: str, baud: int, core: HostProtocol, observer: ProgressObserver
) -> Summary:
    loop = asyncio.get_running_loop()
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
        summary = await stream(port, baud, core, job.lines(), observer, on_open)
        if summary.outcome is Outcome.COMPLETED:
            observer.offset = job.size  # trailing comments count as sent
    except (LinkError, ControllerError, ProtocolError) as exc:
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


def _last_acknowledged(job: Job, observer: ProgressObserver) -> str:
    if observer.last is None:
        return "no line of the job was acknowledged"
    line = observer.last
    return (
        f"the last line the controller acknowledged is {job.name}:{line.source_line} "
        f"(command {line.index} of the job, {line.command})"
    )


def _update(progress: Progress, task: TaskID, observer: ProgressObserver, started: float) -> None:
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
        Console(stderr=True, soft_wrap=True).print(
            "interrupted before streaming began; nothing was sent."
        )
        raise SystemExit(EXIT_INTERRUPTED) from None
    except HostError as exc:  # a last guard: one sentence, never a traceback
        Console(stderr=True, soft_wrap=True).print(f"error: {exc}")
        raise SystemExit(EXIT_BAD_INPUT) from None


if __name__ == "__main__":
    main()
