"""``hyrel-send JOB``: one job streamed to a printer from a terminal.

Opens the session, draws the progress bar and the status line, tells what the job
tells, answers M0 pauses at the keyboard (p pauses and resumes), turns Ctrl-C into the
safe stop, and ends with the summary, the recovery hint of a job that did not complete and
the controller's job report.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from repetrel_host.cli import stop_signals
from repetrel_host.cli.actions import (
    Connecting,
    TerminalActions,
    read_line,
    stop_delayed_text,
    summary_text,
)
from repetrel_host.cli.exit_codes import EXIT_OK
from repetrel_host.cli.heat_ledger import HeatLedger
from repetrel_host.cli.offline import check_job
from repetrel_host.cli.out import Out
from repetrel_host.cli.stop_signals import StopSignals, exit_code_of_stop, stopping_text
from repetrel_host.cli.times import duration
from repetrel_host.config import UserConfig
from repetrel_host.errors import (
    ControllerError,
    HostError,
    JobError,
    LinkError,
    ProtocolError,
    SafeStopError,
    UsageError,
)
from repetrel_host.gcode.analysis import scan_marks, slicer_estimate
from repetrel_host.gcode.heat_rates import learned_heat_rates
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.links import FAKE_PORT, FakeLink
from repetrel_host.protocol.events import ProbeKind
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
from repetrel_host.session.history import heat_rates, paces
from repetrel_host.session.planning import (
    JobPlan,
    LinkRequest,
    choose_port,
    history_file,
    link_settings,
    replan_for_firmware,
)
from repetrel_host.session.print_job import PLAN_AFTER, PrintJob
from repetrel_host.session.printer import Printer
from repetrel_host.session.pump import Outcome, Summary
from repetrel_host.session.recovery import recovery_command, recovery_from, recovery_window
from repetrel_host.session.workers import in_worker, stop_workers

if TYPE_CHECKING:
    from rich.progress import TaskID

    from repetrel_host.cli.display import JobProgress, JobStatus

PROGRESS_REFRESH = 0.1  # seconds between progress bar updates
TEMPERATURE_POLL = 2.0  # seconds between M105s (or M155's reports) for the status line
# Every line sent, the job not done this long after: the controller holds the rest
# (Hyrel's 8 KB), which is said once.
FINISHING_NOTE = 1.0


@dataclass(frozen=True)
class SendOptions:
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
    command_line: tuple[str, ...] = ()  # hyrel-send's arguments, for the recovery hint


async def send_job(
    console: Out, errors: Out, plan: JobPlan, user: UserConfig, options: SendOptions
) -> int:
    """Connect, stream the job and tell how it ended; hyrel-send's exit code."""
    link = link_settings(options.link, plan.machine)
    port, chosen_because = choose_port(options.port, user)
    if chosen_because is not None:
        console.print(f"{chosen_because}.", markup=False)
    # On stderr, as the failure's sentence: stdout holds the run's own story.
    connecting = Connecting(lambda text: errors.print(text, markup=False))
    ledger = HeatLedger(port)
    owed = ledger.owed()
    if owed is not None:
        errors.print(f"{owed[1]}.", markup=False)
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
        owe_safe_stop=owed[0] if owed is not None else None,
    )
    connecting.connected = True
    ledger.keep(printer)
    try:
        plan = _plan_for(printer, plan, user, errors, options.force)
        job, estimate = await _stream(console, errors, printer, plan, user, options)
    except (LinkError, ControllerError, ProtocolError, SafeStopError):
        if printer.last_job is not None:  # the job failed: then the failure's sentence
            _print_recovery_hint(console, printer.last_job, options)
        raise
    finally:
        await printer.close()
        ledger.closed(printer)
    summary = await job.wait()
    _print_summary(console, summary, job, job.where(), estimate)
    if summary.outcome is not Outcome.COMPLETED:
        _print_recovery_hint(console, job, options)
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
    if printer.probe is ProbeKind.CHECKSUM:
        console.print(
            "The controller answers M105 with a plain ok: where the host must ask which "
            "lines it holds, it sends a line whose checksum is wrong on purpose, and the "
            "controller answers each with an error."
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
        chosen.refuse(check_job(chosen, errors), force, "--force")
    return chosen


async def _stream(
    console: Out,
    errors: Out,
    printer: Printer,
    plan: JobPlan,
    user: UserConfig,
    options: SendOptions,
) -> tuple[PrintJob, float | None]:
    """Stream the job with a progress bar; returns it once it ended (however it did), and
    the slicer's estimate of the whole print in seconds (None: the file gives none)."""
    loop = asyncio.get_running_loop()
    stream_file = history_file(options.history, user, plan.job)
    history = None if options.no_history else stream_file
    reports = stream_file.with_name(f"{stream_file.stem}-reports.log")  # the same run's name
    snapshots = stream_file.with_name(f"{stream_file.stem}-snapshots")
    actions = TerminalActions(console, user.host, reports, snapshots)
    interrupts = 0
    begun: list[PrintJob] = []  # the job, once printer.print has started it

    def interrupt(signum: int) -> None:
        nonlocal interrupts
        interrupts += 1
        if not begun:  # still starting: stopped as soon as it has started
            return
        if begun[0].reconnecting_for_safe_stop:
            console.print("giving up: the safe stop will not be sent")
            begun[0].stop()
            return
        if interrupts == 1:
            begun[0].stop()
            console.print(stopping_text(signum))
            return
        begun[0].stop()  # abandoned (or the wait for a reconnect given up): the end says what

    # The run's own handling from before the job starts: a signal that came while its first
    # lines went out (or that the default handling lost inside an import) stops it safely.
    early = bool(stop_signals.received)
    signals = StopSignals(interrupt)
    signals.install()
    try:
        job = await printer.print(
            plan,
            force=options.force,
            history=history or False,
            on_action=actions.perform,
            on_warning=lambda text: errors.print(text, markup=False),
            report=options.report,
            command_line=options.command_line,
        )
    except BaseException:
        signals.remove()
        raise
    begun.append(job)
    if early or interrupts:
        interrupts = 0
        interrupt(stop_signals.received[-1])
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
    keys = Keys(sys.stdin)
    enter: asyncio.Future[None] | None = None  # an M0 waiting for Enter (or p)

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
    keyboard = keys.start(key)
    if keyboard:
        console.print("Keys: p pauses and resumes; Ctrl-C stops the job safely.")
    progress.start()
    if console.console.is_terminal:  # where the status line shows (the scan costs CPU a line)
        tasks.add(loop.create_task(status.read_marks()))
    # The plan's time at each line, in a worker process: the time left, and this run's pace
    # for the printer's next jobs (kept in its record).
    ran = (stream_file.parent, printer.port, plan.profile.name or "")
    prior, rates = learned_pace(paces(*ran)), learned_heat_rates(heat_rates(*ran))
    after = 0.0 if console.console.is_terminal else PLAN_AFTER  # a person reads it at once
    tasks.add(loop.create_task(job.follow_time(prior, in_worker, after, rates)))
    refresher = asyncio.create_task(refresh())
    watcher = asyncio.create_task(_watch(console, printer, job, actions, wait_for_enter, keyboard))
    completed = False
    try:
        completed = (await job.wait()).outcome is Outcome.COMPLETED
    finally:
        keys.stop()
        for running in (refresher, watcher, *tasks):
            running.cancel()
        stop_workers()  # a long file's planning is not waited for
        signals.remove()
        _update(progress, task, job, started, status)
        if completed:  # its last state, as output that is not a terminal keeps it
            progress.update(task, completed=job.size, left="")  # trailing comments too
        with contextlib.suppress(OSError):  # a terminal gone (SIGHUP) takes no last frame
            progress.stop()
        await actions.close()
    # The slicer's estimate, beside the real duration in the summary (the file's ends only).
    return job, await asyncio.to_thread(slicer_estimate, plan.job.path)


async def _watch(
    console: Out,
    printer: Printer,
    job: PrintJob,
    actions: TerminalActions,
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
    progress.status, left = status.show(job)
    progress.update(
        task, completed=job.offset, lines=job.lines, rate=job.lines / elapsed, left=left
    )


def _print_summary(
    console: Out, summary: Summary, job: PrintJob, last: str, slicer: float | None = None
) -> None:
    expected = estimates_text(job, slicer) if summary.outcome is Outcome.COMPLETED else ""
    text = summary_text(job.name, summary, f"interrupted; {last}", expected)
    console.print(f"{text}; machine profile {job.plan.profile.name}.", markup=False)


def estimates_text(job: PrintJob, slicer: float | None) -> str:
    """What the job was expected to take, beside what it took: the whole job as the status
    line started from it (the plan at the printer's pace from its past jobs, or as planned
    for a printer never seen), and the slicer's figure where the file gives one;
    ``" (planned 13m 15s at this printer's pace; the slicer's 12m 33s)"``, "" when
    neither is known (a job over before its plan was made)."""
    said = []
    following, planned = job.following, job.planned_time
    if following is not None and planned is not None:
        at_pace = " at this printer's pace" if following.prior != 1.0 else ""
        said.append(f"planned {duration(planned.total(following.prior))}{at_pace}")
    if slicer is not None:
        said.append(f"the slicer's {duration(slicer)}")
    return f" ({'; '.join(said)})" if said else ""


def announce_recovery(out: Out, plan: JobPlan, layer: int | None) -> None:
    """Where a recovered job starts, and how many commands restore what led up to it."""
    recovery = plan.recovery
    assert recovery is not None
    where = f"layer {layer}, " if layer is not None else ""
    out.print(
        f"Resuming {plan.job.name} at line {recovery.line} "
        f"({where}asked: line {recovery.requested}): "
        f"{len(recovery.preamble)} commands first restore what the lines before it set up.",
        markup=False,
    )


def _print_recovery_hint(console: Out, job: PrintJob, options: SendOptions) -> None:
    """The command that recovers a job that did not complete, where any of it ran."""
    found = recovery_from(job, options.command_line) if options.command_line else None
    line = job.recovery_line
    if found is None or line is None:
        return
    console.print(f"To resume from the first line {found[0]}: {found[1]}", markup=False)
    window = recovery_window(job, options.command_line)
    if window is not None:  # neither choice is sure: which repeats, which skips
        console.print(window[0].upper() + window[1:], markup=False)
    layer = scan_marks(job.plan.job.path, until_line=line).at(line).layer
    if layer is not None:
        # A reset or a lost link also loses what the controller had taken but not yet run
        # (its queue: a few moves), which the line above would skip.
        again = recovery_command(options.command_line, layer.number, "--from-layer")
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
