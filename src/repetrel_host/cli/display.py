"""What ``hyrel-send`` shows while a job streams, and the keys it answers.

Below the bar, a status line: the layer and Z the last acknowledged line belongs to (as
the slicer marked them, :mod:`repetrel_host.gcode.marks`), M73's percentage, and the
temperatures the session last heard; the time left (and the clock time of the end) is the
plan's remainder at the pace the run keeps (:meth:`PrintJob.time_left`), until the plan is
made the slicer's estimate when the file has one, else the measured rate's. Imported only
once a job streams (rich is slow to load).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import termios
import tty
from collections.abc import Callable, Iterable
from datetime import datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from rich.console import RenderableType
from rich.progress import Progress, ProgressColumn, Task
from rich.text import Text

from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.gcode.marks import Position, SlicerMarks
from repetrel_host.protocol.reports import format_temperatures

if TYPE_CHECKING:
    from repetrel_host.session.print_job import PrintJob
    from repetrel_host.session.printer import Printer


class JobProgress(Progress):
    """A rich progress bar with a status line under it."""

    status = ""

    def get_renderables(self) -> Iterable[RenderableType]:
        yield self.make_tasks_table(self.tasks)
        if self.status:
            yield Text(self.status, style="dim")


class TimeLeftColumn(ProgressColumn):
    """The ``left`` field :class:`JobStatus` computes (``12:33 left``)."""

    def render(self, task: Task) -> Text:
        return Text(str(task.fields.get("left", "")), style="progress.remaining")


class JobStatus:
    """The status line and time left of one job, from its slicer marks and the session."""

    def __init__(self, printer: Printer, path: Path) -> None:
        self.printer = printer
        self.path = path
        self.marks: SlicerMarks | None = None  # until read (in a thread, beside the job)

    async def read_marks(self) -> None:
        self.marks = await asyncio.to_thread(scan_marks, self.path)

    def show(self, job: PrintJob, elapsed: float) -> tuple[str, str]:
        """The status line (``layer 12/82 · Z 3.65 · 42 % (M73) · T 200.1/200 · B 60.0/60``)
        and the time left with the clock time of the end: the plan's (the job's
        :meth:`~PrintJob.time_left`); until it is made, the slicer's estimate where it gave
        one (starred), else the measured rate's (bytes acknowledged per second); empty
        until there is one."""
        parts = []
        where = self._where(job)
        if where is not None and self.marks is not None:
            if where.layer is not None:
                parts.append(f"layer {where.layer.number}/{len(self.marks.layers)}")
            if where.z is not None:
                parts.append(f"Z {where.z:g}")
            if where.percent is not None:
                parts.append(f"{where.percent:g} % (M73)")
        parts.extend(format_temperatures(self.printer.temperatures))
        done = job.offset
        planned = job.time_left()
        if planned is not None:
            ends = (datetime.now() + timedelta(seconds=planned)).strftime("%H:%M")
            left = f"{clock(planned)} left, ends {ends}"
        elif where is not None and where.seconds_left is not None:
            parts.append("*time left: the slicer's estimate")
            left = f"{clock(where.seconds_left)} left*"
        elif done > 0 and elapsed > 0:
            left = f"{clock(elapsed / done * max(job.size - done, 0))} left"
        else:
            left = ""
        return " · ".join(parts), left

    def _where(self, job: PrintJob) -> Position | None:
        last = job.last
        if self.marks is None or last is None or not last.source_line:
            return None
        return self.marks.at(last.source_line, job.offset / max(job.size, 1))


def spoken(seconds: float) -> str:
    """A duration as a person says it: ``52m 55s``, ``1h 2m 3s``, ``40s``."""
    minutes, second = divmod(int(seconds + 0.5), 60)
    hours, minute = divmod(minutes, 60)
    parts = [f"{hours}h"] if hours else []
    if hours or minute:
        parts.append(f"{minute}m")
    return " ".join([*parts, f"{second}s"])


def clock(seconds: float) -> str:
    minutes, second = divmod(int(seconds + 0.5), 60)
    hours, minute = divmod(minutes, 60)
    return f"{hours}:{minute:02d}:{second:02d}" if hours else f"{minute}:{second:02d}"


class Keys:
    """Single keypresses from a terminal: no Enter needed, no echo; Ctrl-C still sends
    SIGINT (cbreak mode keeps the terminal's signals). :meth:`stop` restores it."""

    def __init__(self, stream: TextIO = sys.stdin) -> None:
        self.stream = stream
        self._saved: list[Any] | None = None
        self._fd = -1

    def start(self, on_key: Callable[[str], None]) -> bool:
        """Call ``on_key`` with each key pressed; False (and nothing) if not a terminal."""
        try:
            fd = self.stream.fileno()
        except (OSError, ValueError):
            return False
        if not os.isatty(fd) or not _in_foreground(fd):
            return False  # in the background (hyrel-send JOB &): a tty change would stop it
        self._fd = fd
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)

        def readable() -> None:
            try:
                data = os.read(fd, 64)
            except OSError:
                data = b""
            if not data:  # the terminal went away: stop listening
                asyncio.get_running_loop().remove_reader(fd)
                return
            for key in data.decode(errors="replace"):
                on_key(key)

        asyncio.get_running_loop().add_reader(fd, readable)
        return True

    def stop(self) -> None:
        if self._saved is None:
            return
        with contextlib.suppress(RuntimeError, ValueError, OSError):
            asyncio.get_running_loop().remove_reader(self._fd)
        with contextlib.suppress(termios.error, OSError):
            termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)
        self._saved = None


def _in_foreground(fd: int) -> bool:
    """Whether this process is the terminal's foreground job (it may change its modes)."""
    try:
        return os.tcgetpgrp(fd) == os.getpgrp()
    except OSError:
        return False
