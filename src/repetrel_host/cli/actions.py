"""What ``hyrel-send`` does at a terminal for a job's host actions.

Host actions (M792 actions, an M0's SAY..., M718/M719 report logging, M791/M790
snapshots) run here, on the operator's machine. ``M792 SHELL`` runs a program only when
the user's configuration says ``[host] allow_shell = true``; the camera is
``[host] camera``.
"""

from __future__ import annotations

import asyncio
import os
import shlex
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, TextIO

from repetrel_host.cli.times import duration
from repetrel_host.config import HostSettings
from repetrel_host.links import FAKE_PORT, SIM_PORT
from repetrel_host.session.camera import Camera
from repetrel_host.session.events import NoAnswerYet, PrinterEvent, StopDelayed
from repetrel_host.session.job import ActionKind, HostAction
from repetrel_host.session.pump import Outcome, Summary

SPEECH_PROGRAMS = ("espeak-ng", "espeak", "spd-say", "say")
ACTION_TIMEOUT = 60.0  # seconds an action's program may run before it is abandoned


class Terminal(Protocol):
    def print(self, text: str, markup: bool | None = None) -> None: ...

    def bell(self) -> None: ...


class TerminalActions:
    """Carries out a job's host actions at a terminal, and keeps the report log."""

    def __init__(
        self, console: Terminal, host: HostSettings, reports_path: Path, snapshots: Path
    ) -> None:
        self.console = console
        self.host = host
        self.reports_path = reports_path
        self._reports: TextIO | None = None
        self._layer = 0
        self.camera: Camera | None = None
        if host.camera is not None:
            self.camera = Camera(
                host.camera,
                snapshots,
                on_taken=lambda path: console.print(f"snapshot: {path}", markup=False),
                on_failed=lambda why: console.print(f"no snapshot: {why}", markup=False),
            )

    def log(self, text: str) -> None:
        """A controller line, kept while M719 asked for the reports."""
        if self._reports is not None:
            self._reports.write(text + "\n")

    async def perform(self, action: HostAction) -> bool:
        """What the session calls at an M0, M792, M718 or M719 (the pause itself is the
        session's: it waits for resume)."""
        if action.kind is ActionKind.LOG_START:
            self._start_reports()
            self.console.print(f"logging the controller's reports to {self.reports_path}")
        elif action.kind is ActionKind.LOG_STOP:
            self._stop_reports()
        elif action.kind is ActionKind.LAYER:
            self._layer += 1
            if self.host.layer_snapshots:
                self._snap(action)
        elif action.kind is ActionKind.SNAPSHOT:
            self._snap(action)
        else:
            for verb, argument in action.actions:
                await self._act(verb, argument, action)
        return True

    async def _act(self, verb: str, argument: str, action: HostAction) -> None:
        from rich.markup import escape

        where = escape(action.position)
        if verb == "SAY":
            program = self.host.speech_program or next(
                (p for p in SPEECH_PROGRAMS if shutil.which(p)), None
            )
            self.console.print(f"say ({where}): {escape(argument)}")
            if program:
                await _run([program, argument])
        elif verb == "BEEP":
            self.console.bell()
            self.console.print(f"beep ({where})")
        elif verb == "SHELL":
            if not self.host.allow_shell:
                self.console.print(
                    f"[yellow]refused[/] ({where}): M792 SHELL {escape(argument)} - "
                    "set allow_shell = true under \\[host] in your configuration to allow it"
                )
                return
            self.console.print(f"shell ({where}): {escape(argument)}")
            await _run(shlex.split(argument))
        else:  # PIC, VID, SEND: no display or aux port here, so say what was asked
            self.console.print(f"{verb.lower()} ({where}): {escape(argument)}")

    def _snap(self, action: HostAction) -> None:
        """A snapshot beside the stream: the job does not wait for the camera."""
        if self.camera is None:
            self.console.print(
                f"no snapshot ({action.position}): no camera is set (camera = "
                '"a command line" under [host] in your configuration)',
                markup=False,
            )
        elif not self.camera.take(
            f"{action.source_line:07d}-layer{self._layer}",
            wait_turn=action.kind is ActionKind.SNAPSHOT,  # asked for: after the one being taken
        ):
            self.console.print(
                f"no snapshot ({action.position}): the last one is still being taken",
                markup=False,
            )

    # --- report log ---------------------------------------------------------

    def _start_reports(self) -> None:
        if self._reports is None:
            self.reports_path.parent.mkdir(parents=True, exist_ok=True)
            self._reports = self.reports_path.open("a", encoding="utf-8")

    def _stop_reports(self) -> None:
        if self._reports is not None:
            self._reports.close()
            self._reports = None

    async def close(self) -> None:
        """The job ended: the report log closed, the last snapshot taken."""
        self._stop_reports()
        if self.camera is not None:
            await self.camera.close()


async def _run(argv: list[str]) -> None:
    try:
        process = await asyncio.create_subprocess_exec(
            *argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
    except OSError:
        return
    try:
        await asyncio.wait_for(process.wait(), ACTION_TIMEOUT)
    except (TimeoutError, asyncio.CancelledError):
        process.kill()
        raise


async def read_line(stream: TextIO) -> str | None:
    """One line from ``stream`` without blocking the event loop; None at end of input."""
    fd = stream.fileno()
    loop = asyncio.get_running_loop()
    future: asyncio.Future[None] = loop.create_future()

    def readable() -> None:
        if not future.done():
            future.set_result(None)

    try:
        loop.add_reader(fd, readable)
    except (PermissionError, ValueError):
        pass  # a regular file never blocks: read it directly
    else:
        try:
            await future
        finally:
            loop.remove_reader(fd)
    data = b""
    while not data.endswith(b"\n"):
        chunk = os.read(fd, 1)
        if not chunk:
            return data.decode(errors="replace") if data else None
        data += chunk
    return data.decode(errors="replace")


class Connecting:
    """What ``hyrel-send`` (and its ``--console``) says while ``connect()`` greets the
    controller, so that a port that does not answer is no silence: where, at once, then
    each greeting that goes again, as it goes (the session's ``on_event``). Quiet once
    :attr:`connected`: the session's own events say what follows."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.connected = False

    def start(self, port: str, baud: int) -> None:
        if port not in (FAKE_PORT, SIM_PORT):  # started here, answering at once
            self.say(f"connecting to {port} at {baud} baud...")

    def __call__(self, event: PrinterEvent) -> None:
        if isinstance(event, NoAnswerYet) and not self.connected:
            self.say(event.text)


def summary_text(name: str, summary: Summary, where: str, expected: str = "") -> str:
    """How a job ended, as hyrel-send's summary and the console's say it; ``where``: the
    last line acknowledged, said of a job that stopped; ``expected``: what it was expected
    to take, said beside what it took (``" (planned 13m 15s)"``)."""
    rate = summary.lines / summary.seconds if summary.seconds > 0 else 0.0
    done = summary.outcome is Outcome.COMPLETED
    verdict = "done" if done else f"stopped ({where})"
    return (
        f"{name}: {verdict}: {summary.lines} lines in {duration(summary.seconds)}{expected}, "
        f"{rate:.0f} lines/s, {summary.resends} resend requests, "
        f"{summary.retransmissions} lines sent again"
    )


def stop_delayed_text(event: StopDelayed) -> str:
    """A held-up stop in words: by what, and the heaters that may be on meanwhile."""
    on = f"; heaters that may be on: {', '.join(event.heaters)}" if event.heaters else ""
    return f"the safe stop is held up: {event.reason}{on}"
