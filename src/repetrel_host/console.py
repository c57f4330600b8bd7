"""What ``hyrel-send`` shows and does at a terminal: messages, resends, host actions.

Host actions (M0 pauses, M792 actions, M718/M719 report logging) run here, on
the operator's machine. ``M792 SHELL`` runs a program only when the user's
configuration says ``[host] allow_shell = true``.
"""

from __future__ import annotations

import asyncio
import os
import shlex
import shutil
import sys
from pathlib import Path
from typing import TextIO

from rich.console import Console
from rich.markup import escape

from repetrel_host.config import HostSettings
from repetrel_host.errors import JobError
from repetrel_host.job import HostAction, JobLine
from repetrel_host.protocol import replies
from repetrel_host.sender import Observer

SPEECH_PROGRAMS = ("espeak-ng", "espeak", "spd-say", "say")
ACTION_TIMEOUT = 60.0  # seconds an action's program may run before it is abandoned


class ConsoleObserver(Observer):
    """Counts acknowledgements for the progress bar and carries out host actions."""

    def __init__(
        self, console: Console, host: HostSettings, reports_path: Path, stdin: TextIO = sys.stdin
    ) -> None:
        self.console = console
        self.host = host
        self.reports_path = reports_path
        self.stdin = stdin
        self.lines = 0
        self.offset = 0
        self.last: JobLine | None = None
        self._reports: TextIO | None = None

    # --- stream events ------------------------------------------------------

    def on_acknowledged(self, line: JobLine) -> None:
        if line.index:  # header and safe-stop lines are not the job's
            self.lines = line.index
            self.offset = line.end_offset
            self.last = line

    def on_resend(self, line: JobLine) -> None:
        self.console.print(
            f"[dim]resend: the controller asked again for {escape(line.position)}[/]"
        )

    def on_notice(self, text: str) -> None:
        self.console.print(f"[yellow]warning:[/] {escape(text)}")

    def on_message(self, text: str, reply: replies.Reply) -> None:
        if self._reports is not None:
            self._reports.write(text + "\n")
        if isinstance(reply, replies.Busy | replies.Wait | replies.Start | replies.Error):
            return  # keepalives; line errors are shown as the resend that follows
        self.console.print(f"[dim]controller:[/] {escape(text)}")

    # --- host actions -------------------------------------------------------

    async def perform(self, action: HostAction) -> bool:
        if action.kind == "log_start":
            self._start_reports()
            self.console.print(f"logging the controller's reports to {self.reports_path}")
        elif action.kind == "log_stop":
            self.close()
        else:
            for verb, argument in action.actions:
                await self._act(verb, argument, action)
            if action.kind == "pause":
                return await self._pause(action)
        return True

    async def _pause(self, action: HostAction) -> bool:
        message = f": {action.message}" if action.message else ""
        self.console.print(
            f"[bold]Paused[/] at {escape(action.position)}{escape(message)} "
            "- press Enter to resume (Ctrl-C stops the job)"
        )
        line = await _read_line(self.stdin)
        if line is None:
            raise JobError(
                f"{action.position}: M0 waits for the operator, but standard input is closed"
            )
        self.console.print("resumed")
        return True

    async def _act(self, verb: str, argument: str, action: HostAction) -> None:
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
                    "set allow_shell = true under [host] in your configuration to allow it"
                )
                return
            self.console.print(f"shell ({where}): {escape(argument)}")
            await _run(shlex.split(argument))
        else:  # PIC, VID, SEND: no display or aux port here, so say what was asked
            self.console.print(f"{verb.lower()} ({where}): {escape(argument)}")

    # --- report log ---------------------------------------------------------

    def _start_reports(self) -> None:
        if self._reports is None:
            self.reports_path.parent.mkdir(parents=True, exist_ok=True)
            self._reports = self.reports_path.open("a", encoding="utf-8")

    def close(self) -> None:
        if self._reports is not None:
            self._reports.close()
            self._reports = None


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


async def _read_line(stream: TextIO) -> str | None:
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
