"""What ``hyrel-send`` shows while a job streams, and the keys it answers.

Below the bar, a status line: the layer and Z the last acknowledged line belongs to (as
the slicer marked them, :mod:`repetrel_host.gcode.marks`), M73's percentage, and the
temperatures the session last heard; the time left (and the clock time of the end) is the
plan's remainder at the pace the run keeps (:meth:`PrintJob.time_left`): "estimating" in
the second or two before the plan is made, never a stand-in figure (the slicer's leaves
out the heat-up; the rate's reads a heat wait as a slow job). Imported only once a job
streams (rich is slow to load).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import termios
import tty
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from rich.console import RenderableType
from rich.progress import Progress, ProgressColumn, Task
from rich.text import Text

from repetrel_host.cli.times import clock_in, duration
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
    """The ``left`` field :class:`JobStatus` computes (``12m 33s left, ends 20:05``)."""

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

    def show(self, job: PrintJob) -> tuple[str, str]:
        """The status line (``layer 12/82 · Z 3.65 · 42 % (M73) · T 200.1/200 · B 60.0/60``)
        and the time left with the clock time of the end (``12m 33s left, ends 20:05``):
        the job's :meth:`~PrintJob.time_left`, "estimating" until its plan is made."""
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
        left = job.time_left()
        shown = "estimating" if left is None else f"{duration(left)} left, ends {clock_in(left)}"
        return " · ".join(parts), shown

    def _where(self, job: PrintJob) -> Position | None:
        last = job.last
        if self.marks is None or last is None or not last.source_line:
            return None
        return self.marks.at(last.source_line, job.offset / max(job.size, 1))


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
