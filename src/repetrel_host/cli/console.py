"""``hyrel-send --console``: an interactive terminal on one printer session.

Type a G-code line and see the controller's reply; ``!print FILE`` streams a job on the
same session while the prompt stays live (``!pause``, ``!resume``, ``!cancel``,
``!status``). At a terminal, prompt_toolkit edits the line, keeps its history in the data
folder and draws a status line (state, temperatures, the job's progress) that replies
and controller messages print above. From a pipe, lines are read plainly, one command
after the other's reply, and end of input waits for a running job to end.

Everything goes through the session's public API (``Printer.command``, ``print``,
``pause``, ``resume``, ``cancel``), so the console refuses what the API refuses, with the
API's sentences. Models: Printrun's pronsole, OctoPrint's terminal tab.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shlex
import signal
import sys
from collections import deque
from collections.abc import Coroutine, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from repetrel_host.cli.actions import (
    Connecting,
    TerminalActions,
    read_line,
    stop_delayed_text,
    summary_text,
)
from repetrel_host.cli.exit_codes import EXIT_NOT_SAFE, EXIT_OK
from repetrel_host.cli.heat_ledger import HeatLedger
from repetrel_host.cli.stop_signals import StopSignals, exit_code_of_stop, stopping_text
from repetrel_host.config import UserConfig
from repetrel_host.errors import HostError, JobError, SafeStopError, UsageError
from repetrel_host.gcode.commands import command_word
from repetrel_host.links import FAKE_PORT, FakeLink
from repetrel_host.protocol.reports import format_temperatures
from repetrel_host.session.connect import connect
from repetrel_host.session.events import (
    Message,
    NoAnswerYet,
    Notice,
    Paused,
    PauseReason,
    Resend,
    Resumed,
    State,
    StateChanged,
    StopDelayed,
    Temperatures,
)
from repetrel_host.session.planning import (
    JobRequest,
    LinkRequest,
    default_history_dir,
    explicit_machine,
    history_file,
    link_settings,
    resolve_port,
)
from repetrel_host.session.print_job import PrintJob
from repetrel_host.session.printer import Printer
from repetrel_host.session.pump import Outcome
from repetrel_host.session.recovery import recovery_from, recovery_window

if TYPE_CHECKING:
    from prompt_toolkit.application import Application
    from prompt_toolkit.history import History

PROMPT = "> "
# Temperatures are polled this often (a job printing or not): the status line stays current.
POLL_INTERVAL = 2.0
STATUS_REFRESH = 0.5  # seconds between redraws of the status line
# A console command shown in --help and !help: (usage, what it does).
COMMANDS = (
    ("!print FILE [--force]", "stream a G-code file on this session (--force: despite errors)"),
    ("!pause", "pause the job (commands may move the machine meanwhile)"),
    ("!resume", "go on with the paused job (after !pause or the job's M0)"),
    ("!cancel", "stop the job with the safe-stop sequence"),
    ("!status", "session state, firmware, temperatures, the job's progress"),
    ("!help", "this list"),
    ("!quit", "leave (Ctrl-D too); a running job is stopped safely first"),
)
CONSOLE_HELP = (
    "An interactive terminal on the printer, without a JOB: type G-code, see the replies; "
    + ", ".join(usage for usage, _ in COMMANDS)
    + " (!help says more). Command history: "
    + "~/.local/share/repetrel-host/console-history."
)


LABEL = 32  # characters of a command that label its reply lines from a pipe


@dataclass(frozen=True)
class ConsoleOptions:
    """What the command line says about the console's session and its jobs."""

    port: str | None
    link: LinkRequest
    machine: str | None
    loadout: Path | None
    reply_timeout: float
    history: Path | None  # the print history folder of !print's jobs
    no_history: bool
    fake_log: Path | None
    header: bool = True


def console_history_file() -> Path:
    """The typed lines, kept beside the print history folder in the user's data folder."""
    return default_history_dir().parent / "console-history"


def run_console(
    options: ConsoleOptions, user: UserConfig, others: Mapping[str, object] = {}
) -> int:
    """Open the session and run the console until !quit or end of input; the exit code.
    ``others``: hyrel-send's options for a JOB, by name, each refused when given."""
    for name, value in others.items():
        if not value:
            continue
        if name == "JOB":
            raise UsageError("--console takes no JOB: type !print JOB at its prompt")
        if name == "--force":
            raise UsageError("--force goes with a job: at the console, !print FILE --force")
        raise UsageError(f"{name} does not go with --console")
    try:
        return asyncio.run(_run(options, user))
    except KeyboardInterrupt:  # SIGTERM or SIGHUP before the console's own handling
        return exit_code_of_stop()


async def _run(options: ConsoleOptions, user: UserConfig) -> int:
    link = link_settings(
        options.link, explicit_machine(JobRequest(options.loadout, options.machine), user)
    )
    port = resolve_port(options.port, user)
    # On stderr, before the console's own lines: a port that does not answer is no silence.
    connecting = Connecting(lambda text: print(text, file=sys.stderr, flush=True))
    ledger = HeatLedger(port)
    owed = ledger.owed()
    if owed is not None:
        print(f"{owed[1]}.", file=sys.stderr, flush=True)
    connecting.start(port, link.baud)
    printer = await connect(
        port,
        options.machine,
        options.loadout,
        link.flow,
        user,
        baud=link.baud,
        protocol=link.protocol,
        checksum=link.checksum,
        reply_timeout=options.reply_timeout,
        poll_interval=POLL_INTERVAL,
        poll_while_printing=True,  # the status line's temperatures during a !print too
        fake_log=options.fake_log,
        on_event=connecting,
        owe_safe_stop=owed[0] if owed is not None else None,
    )
    connecting.connected = True  # from now on, the session's events say it (_watch_printer)
    ledger.keep(printer)
    console = PrinterConsole(printer, user, options)
    try:
        code = await (console.interactive() if sys.stdin.isatty() else console.piped())
    finally:
        await console.close()
        ledger.closed(printer)
    # Left with the machine maybe not safe (a second stop signal, a lost link): say so
    # in the exit code too, whatever ended the console.
    return EXIT_NOT_SAFE if console.left_unsafe else code


class _Screen:
    """Where the console prints: stdout (patched by prompt_toolkit at a terminal, so that
    lines go above the prompt). Host actions print rich markup; it is shown as text."""

    def print(self, text: str, markup: bool | None = None) -> None:
        if markup is not False:
            from rich.text import Text

            text = Text.from_markup(text).plain
        print(text, flush=True)

    def bell(self) -> None:
        sys.stdout.write("\a")
        sys.stdout.flush()


class PrinterConsole:
    """The console's commands on one session, and what it shows of the session."""

    def __init__(self, printer: Printer, user: UserConfig, options: ConsoleOptions) -> None:
        self.printer = printer
        self.user = user
        self.options = options
        self.screen = _Screen()
        self.temperatures: dict[str, tuple[float, float | None]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._job_watcher: asyncio.Task[None] | None = None
        self._printer_watcher: asyncio.Task[None] | None = None
        # The session's and the job's streams both carry a controller message: shown once.
        self._shown: deque[object] = deque(maxlen=64)
        self._input_closed = False  # from a pipe: nobody can answer a pause any more
        self._interrupts = 0
        self._closed = False
        self._interrupted = asyncio.Event()
        self._signals = StopSignals(self._on_stop_signal)
        self._prompt: Application[str] | None = None  # the interactive prompt, while it runs
        self._last_unsafe = False  # the last job ended without its safe stop confirmed
        self.left_unsafe = False  # so, or a safe stop owed, as the console closed

    def say(self, text: str) -> None:
        with contextlib.suppress(OSError):  # a closed terminal (SIGHUP) takes no words
            self.screen.print(text, markup=False)

    # --- running ----------------------------------------------------------------

    async def interactive(self) -> int:
        """Read lines at a terminal with editing, history and the status line."""
        from prompt_toolkit import PromptSession
        from prompt_toolkit.patch_stdout import patch_stdout

        session: PromptSession[str] = PromptSession(
            history=self._history(),
            bottom_toolbar=self.status_line,
            refresh_interval=STATUS_REFRESH,
        )
        with patch_stdout(raw=True):
            self._start()
            self._prompt = session.app  # a stop signal ends its prompt (as Ctrl-D)
            while True:
                try:
                    # Ctrl-C at the prompt is a key (it clears the line); a SIGINT from
                    # elsewhere goes to our handler, which prompt_toolkit would remove.
                    line = await session.prompt_async(PROMPT, handle_sigint=False)
                except KeyboardInterrupt:
                    self._hint_cancel()
                    continue
                except (EOFError, OSError):  # Ctrl-D; or the terminal is gone (EIO)
                    line = "!quit"
                if self._interrupted.is_set() or not await self.handle(line):
                    await self.close()  # still above the prompt: what the stop prints
                    return exit_code_of_stop() if self._interrupted.is_set() else EXIT_OK

    async def piped(self) -> int:
        """Read plain lines from a pipe or a file; each command waits for its reply."""
        self._start()
        interrupted = asyncio.create_task(self._interrupted.wait())
        try:
            while True:
                reading = asyncio.create_task(read_line(sys.stdin))
                await asyncio.wait({reading, interrupted}, return_when=asyncio.FIRST_COMPLETED)
                if self._interrupted.is_set():
                    reading.cancel()
                    await self._wait_for_job()
                    return exit_code_of_stop()
                line = reading.result()
                if line is None:
                    break
                if not await self.handle(line, wait=True):
                    return EXIT_OK
            self._input_closed = True
            job = self.printer.job
            if job is not None:
                self.say(f"end of input: waiting for {job.name} to end")
                if self.printer.state is State.PAUSED:
                    self._stop_unanswerable(job, job.where())
                await self._wait_for_job()
            return exit_code_of_stop() if self._interrupted.is_set() else EXIT_OK
        finally:
            interrupted.cancel()

    def _start(self) -> None:
        self._announce()
        self._signals.install()
        self._printer_watcher = asyncio.create_task(self._watch_printer())
        # The status line's temperatures at once, not after the first poll.
        self._spawn(self._quietly("M105"))

    def _announce(self) -> None:
        printer = self.printer
        if isinstance(printer.link, FakeLink) and printer.link.port == FAKE_PORT:
            self.say(
                f"No printer port given: the built-in fake controller on {printer.link.device}."
            )
        firmware = printer.firmware.name if printer.firmware else "a controller that did not say"
        self.say(
            f"Connected to {printer.port}: {firmware}; machine profile "
            f"{printer.profile.describe()}. Type G-code, or !help; !quit or Ctrl-D leaves."
        )

    async def close(self) -> None:
        """Stop a running job safely, close the session, end the watchers."""
        if self._closed:
            return
        self._closed = True
        job = self.printer.job
        if job is not None and not job.done:
            self.say(f"stopping {job.name} with the safe-stop sequence first")
        await self.printer.close()  # a second stop signal meanwhile abandons its safe stop
        await self._wait_for_job()
        with contextlib.suppress(ValueError, RuntimeError):
            self._signals.remove()
        owed = self.printer.owed_safe_stop
        self.left_unsafe = self._last_unsafe or bool(owed)
        if owed:
            heaters = ", ".join(self.printer.heaters_on()) or "none known"
            self.say(
                f"warning: leaving without the safe stop ({', '.join(owed)} not confirmed); "
                f"heaters that may be on: {heaters}: check the machine"
            )
        for task in [*self._tasks, self._printer_watcher]:
            if task is not None:
                task.cancel()

    async def _wait_for_job(self) -> None:
        watcher = self._job_watcher
        if watcher is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await watcher

    def _history(self) -> History:
        from prompt_toolkit.history import FileHistory, InMemoryHistory

        path = console_history_file()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        except OSError as exc:
            self.say(f"the command history is not kept: {path}: {exc.strerror}")
            return InMemoryHistory()
        return FileHistory(str(path))

    # --- a typed line -----------------------------------------------------------

    async def handle(self, line: str, wait: bool = False) -> bool:
        """Carry out one typed line; False once the console is to end. A G-code line's
        reply is awaited only with ``wait``: at a terminal the prompt stays live, so that
        an M112 can follow a long M109."""
        text = line.strip()
        if not text:
            return True
        if text.startswith("!"):
            word, _, rest = text[1:].partition(" ")
            return await self._console_command(word.lower(), rest.strip())
        if wait:
            await self._command(text, label=True)
        else:
            self._spawn(self._command(text))
        return True

    async def _command(self, line: str, label: bool = False) -> None:
        """Send a typed line and show its reply; ``label``: each reply line after the
        command it answers (from a pipe, where no prompt shows what was typed)."""
        shown = line if len(line) <= LABEL else f"{line[: LABEL - 3]}..."
        say = (lambda text: self.say(f"{shown}: {text}")) if label else self.say
        try:
            reply = await self.printer.command(line)  # M112 and M108 go even mid-job
        except UsageError as exc:
            why = str(exc)
            if self.printer.state is State.PRINTING:  # the session's words are the API's
                why = "a job is printing: type !pause first (a command waits)"
            say(f"error: {why}")
            return
        except HostError as exc:
            say(f"error: {exc}")
            return
        for text in reply.lines:
            say(text)
        if reply.ok:
            say(reply.ok_line)
        elif command_word(reply.command) == "M112":
            say("M112 sent at once: emergency stop (the controller halts until reset)")
        else:
            say(f"{reply.command} sent at once")

    async def _quietly(self, command: str) -> None:
        with contextlib.suppress(HostError):
            await self.printer.command(command)

    async def _console_command(self, word: str, rest: str) -> bool:
        printer = self.printer
        try:
            if word in ("quit", "exit"):
                await self._quit()
                return False
            if word == "help":
                self._help()
            elif word == "print":
                await self._print(rest)
            elif word == "pause":
                await printer.pause()
            elif word == "resume":
                await printer.resume()
            elif word == "cancel":
                self._cancel()
            elif word == "status":
                self._status()
            else:
                self.say(f"error: there is no console command !{word}: !help lists them")
        except HostError as exc:
            self.say(f"error: {exc}")
        except OSError as exc:  # a job file that cannot be read
            self.say(f"error: {exc.filename or 'the file'}: {exc.strerror}")
        return True

    def _help(self) -> None:
        self.say("Type a G-code line to send it (M112: emergency stop). Console commands:")
        width = max(len(usage) for usage, _ in COMMANDS)
        for usage, what in COMMANDS:
            self.say(f"  {usage.ljust(width)}  {what}")

    async def _print(self, rest: str) -> None:
        try:
            words = shlex.split(rest)
        except ValueError as exc:
            raise JobError(f"!print FILE [--force]: {exc}") from None
        force = "--force" in words
        files = [w for w in words if w != "--force"]
        if len(files) != 1 or files[0].startswith("-"):
            raise JobError("!print takes one FILE, and --force to send it despite errors")
        path = Path(os.path.expanduser(files[0]))
        printer = self.printer
        if printer.job is not None:
            raise JobError(f"{printer.job.name} is running: !cancel it first, or wait")
        plan = printer.plan(path, header=self.options.header)
        if not plan.checked_as_it_streams:  # a big file is checked as it streams
            findings = plan.check()
            for finding in findings:
                self.say(finding.format(plan.job.name))
            plan.refuse(findings, force, "!print FILE --force")
        stream_file = history_file(self.options.history, self.user, plan.job)
        reports = stream_file.with_name(f"{stream_file.stem}-reports.log")
        snapshots = stream_file.with_name(f"{stream_file.stem}-snapshots")
        actions = TerminalActions(self.screen, self.user.host, reports, snapshots)
        job = await printer.print(
            plan,
            force=force,
            history=False if self.options.no_history else stream_file,
            on_action=actions.perform,
            on_warning=self.say,
        )
        self.say(
            f"printing {job.name} (machine profile {plan.profile.name}): "
            "!pause, !resume, !cancel, !status"
        )
        self._job_watcher = asyncio.create_task(self._watch_job(job, actions))

    def _cancel(self) -> None:
        job = self.printer.job
        last = self.printer.last_job
        if job is None and last is not None and last.reconnecting_for_safe_stop:
            self.say(f"{last.name}: no longer waiting to send the safe stop")
            last.stop()
            return
        if job is None:
            self.say("error: no job is running")
            return
        if job.stopping:
            self.say(f"{job.name}: no longer waiting for the safe stop (it still goes)")
            job.stop()  # abandoned: the job's watcher says what was not confirmed
            return
        self.say(f"cancelling {job.name}: sending the safe-stop sequence")
        job.stop()  # the job's watcher says how it ended

    async def _quit(self) -> None:
        job = self.printer.job
        if job is not None:
            self.say(f"quitting: stopping {job.name} with the safe-stop sequence first")
            await self.printer.cancel()
            await self._wait_for_job()

    def _status(self) -> None:
        printer = self.printer
        device = printer.link.device
        where = f" ({device})" if device and device != printer.port else ""
        self.say(f"state: {printer.state.value} on {printer.port}{where}")
        firmware = printer.firmware
        self.say(f"firmware: {firmware.name if firmware else 'not known (no answer to M115)'}")
        self.say(f"machine profile: {printer.profile.describe()}")
        readings = " · ".join(format_temperatures(self.temperatures))
        self.say(f"temperatures: {readings or 'none reported yet'}")
        job = printer.job
        self.say(f"job: {job_progress(job) if job else 'none'}")
        if job is not None and job.history is not None:
            self.say(f"job's stream as transmitted: {job.history}")
        if printer.pending:
            self.say(f"waiting for the reply to: {', '.join(printer.pending)}")

    # --- what the session and the job tell -------------------------------------

    def status_line(self) -> str:
        """The bottom line at a terminal: port and state, temperatures, the job."""
        printer = self.printer
        parts = [
            f"{printer.port} {printer.state.value}",
            " · ".join(format_temperatures(self.temperatures)) or "no temperatures yet",
        ]
        job = printer.job
        if job is not None:
            parts.append(job_progress(job))
        return " | ".join(parts)

    async def _watch_printer(self) -> None:
        async for event in self.printer.events():
            if isinstance(event, Temperatures):
                self.temperatures = event.readings
            elif isinstance(event, StateChanged):
                self._state_changed(event)
            elif isinstance(event, NoAnswerYet):
                self.say(f"session: {event.text}")
            else:
                self._show(event)

    def _state_changed(self, event: StateChanged) -> None:
        if event.state is State.DISCONNECTED:
            self.say(f"session: disconnected ({event.reason}); trying to reconnect")
        elif event.state is State.CONNECTING and event.previous is not None:
            self.say(f"session: greeting the controller again ({event.reason})")
        elif event.state is State.READY and event.previous is State.CONNECTING:
            self.say("session: ready")

    def _show(self, event: Message | Notice) -> None:
        if any(shown is event for shown in self._shown):
            return
        self._shown.append(event)
        if isinstance(event, Message):
            self.say(f"controller: {event.text}")
        else:
            self.say(f"warning: {event.text}")

    async def _watch_job(self, job: PrintJob, actions: TerminalActions) -> None:
        try:
            async for event in job.events():
                if isinstance(event, Message):
                    actions.log(event.text)
                    self._show(event)
                elif isinstance(event, Notice):
                    self._show(event)
                elif isinstance(event, Resend):
                    self.say(f"resend: the controller asked again for {event.position}")
                elif isinstance(event, Paused):
                    self._paused(job, event)
                elif isinstance(event, Resumed):
                    self.say("resumed")
                elif isinstance(event, StopDelayed):
                    now = (
                        "type M112 for an emergency stop"
                        if event.can_emergency_stop
                        else "use its power switch to stop it at once (M112 would wait too)"
                    )
                    self.say(
                        f"warning: {stop_delayed_text(event)}. Wait for it; or {now}; or "
                        "!cancel again to stop waiting for it"
                    )
            self._last_unsafe = False
            try:
                summary = await job.wait()
            except SafeStopError as exc:
                self._last_unsafe = True
                self.say(f"{job.name}: not safe: {exc}")
                self._recovery_hint(job)
            except HostError as exc:
                self.say(f"{job.name}: failed: {exc}")
                self._recovery_hint(job)
            else:
                self.say(summary_text(job.name, summary, job.where()))
                if summary.outcome is not Outcome.COMPLETED:
                    self._recovery_hint(job)
        finally:
            await actions.close()

    def _recovery_hint(self, job: PrintJob) -> None:
        """The command that goes on with a job that did not complete, as hyrel-send says."""
        arguments = [str(job.plan.job.path.resolve()), "--port", self.printer.port]
        if self.options.machine:
            arguments += ["--machine", self.options.machine]
        if self.options.loadout:
            arguments += ["--loadout", str(self.options.loadout)]
        found = recovery_from(job, tuple(arguments))
        if found is not None:
            self.say(f"to resume from the first line {found[0]}: {found[1]}")
        window = recovery_window(job, tuple(arguments))
        if window is not None:
            self.say(window)

    def _paused(self, job: PrintJob, event: Paused) -> None:
        message = f": {event.message}" if event.message else ""
        at = f" at {event.position}" if event.position else ""
        if event.reason is PauseReason.M0:
            self.say(f"paused{at}{message} - !resume goes on")
        else:
            self.say(f"paused{at} - !resume goes on, !cancel stops the job safely")
        if self._input_closed:
            self._stop_unanswerable(job, event.position)

    def _stop_unanswerable(self, job: PrintJob, position: str) -> None:
        job.stop(JobError(f"{position}: the job is paused, but standard input is closed"))

    # --- Ctrl-C -----------------------------------------------------------------

    def _hint_cancel(self) -> None:
        if self.printer.job is not None:
            self.say("!cancel stops the job safely (Ctrl-C only clears the line)")

    def _on_stop_signal(self, signum: int) -> None:
        """A SIGINT outside the prompt at a terminal: the hint. Otherwise (a SIGINT from a
        pipe, a SIGTERM, a SIGHUP): stop the job safely and leave (a second one abandons
        the safe stop)."""
        if signum == signal.SIGINT and sys.stdin.isatty():
            self._hint_cancel()
            return
        self._interrupts += 1
        self._interrupted.set()
        if self._prompt is not None and self._prompt.is_running:
            self._prompt.exit(exception=EOFError())
        job = self.printer.job
        if job is None or job.done:
            return
        if self._interrupts == 1:
            self.say(stopping_text(signum))
        job.stop()  # a second one abandons it: the job's watcher says what was not confirmed

    def _spawn(self, coroutine: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


def job_progress(job: PrintJob) -> str:
    """``part.gcode 42% 1234 lines, at part.gcode:1240 (paused)``."""
    percent = 100 * job.offset // job.size if job.size else 0
    last = job.last
    at = f", at {last.position}" if last is not None else ""
    state = job.printer.state
    stopping = " (stopping)" if job.stopping else ""
    paused = " (paused)" if state is State.PAUSED and not stopping else ""
    return f"{job.name} {percent}% {job.lines} lines{at}{paused}{stopping}"
