"""The job a printer of the server streams now: where it is (its layer, its height, the
share of the file acknowledged), how long it has left, when it prints a layer of its file,
and the filament it used."""

from __future__ import annotations

import asyncio
import bisect
import logging
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import repetrel_host as rh
from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.gcode.marks import SlicerMarks
from repetrel_host.gcode.timeline import Countdown, PlannedTime
from repetrel_host.server.analyses import Analyses
from repetrel_host.server.events import PrintProgress
from repetrel_host.server.store import JobRecord

# How a time left was found: the plan at the pace of the run or of the printer's past jobs;
# the plan as it is; the slicer's figure (a file never planned, in its first seconds).
LEFT_FROM = ("estimate", "plan", "slicer")
log = logging.getLogger("repetrel_host.server")
FILE_END = 1 << 62  # a line past the last of any file
LAYER_TIMES = ("starts_in", "ends_in", "starts_at", "ends_at")  # when a layer is printed


@dataclass
class Running:
    """The job streaming now."""

    record: JobRecord
    job: rh.PrintJob
    layers: list[int] = field(default_factory=list)  # byte offsets where marks.layers begin
    new_layers: int = 0  # the M790s reached
    marks: SlicerMarks | None = None  # the slicer's (layers, Z, estimates), once read
    summary: FileSummary | None = None  # the file's analysis (filament, boxes), once read
    prior: float = 1.0  # the printer's pace from its past jobs, as the job started
    shown: Countdown = field(default_factory=Countdown)  # the time left given last

    @property
    def layer(self) -> int:
        """The layer the acknowledged lines have reached (0: before the first marker)."""
        return bisect.bisect_right(self.layers, self.job.offset)

    @property
    def z(self) -> float | None:
        """Z of the last acknowledged line, as the slicer marked it."""
        last = self.job.last
        if self.marks is None or last is None:
            return None
        return self.marks.at(last.source_line).z

    @property
    def planned(self) -> tuple[PlannedTime | None, str | None]:
        """The whole job's plan from its moves, split, and where its limits came from: its
        own plan once made (its machine's limits, its header, the heaters where they were),
        else the file's analysis' (planned as this printer plans; None until either is
        known, or for a file without moves)."""
        following = self.job.following
        if following is not None and following.timeline.total > 0:
            return following.timeline.planned, following.timeline.limits_from
        summary = self.summary
        if summary is None:
            return None, None
        return summary.planned, summary.planned_limits_from

    @property
    def pace(self) -> float:
        """The pace its time is given at: the run's as it was watched, blended in from the
        printer's past jobs' (:attr:`prior`)."""
        following = self.job.following
        return following.pace if following is not None else self.prior

    @property
    def expected(self) -> float | None:
        """The whole job's seconds: while it runs, the time it ran and its time left (so
        that "12 s of about 40 s" and "28 s left" agree); else its plan at :attr:`pace`.
        The one figure every face gives for it (/v1's ``estimated_time``, OctoPrint's
        ``estimatedPrintTime``, the page)."""
        started = self.record.started
        left = self.time_left()[0] if started is not None and not self.job.done else None
        if started is not None and left is not None:
            return time.time() - started + left
        planned = self.planned[0]
        return planned.total(self.pace) if planned is not None else None

    @property
    def slicer_seconds(self) -> float | None:
        """The slicer's own estimate of the whole job, where the file states one."""
        if self.marks is not None and self.marks.total_seconds is not None:
            return self.marks.total_seconds
        return self.summary.slicer_seconds if self.summary is not None else None

    @property
    def fraction(self) -> float:
        """The share of the file's bytes the controller acknowledged (0 to 1)."""
        return min(self.job.offset / max(self.job.size, 1), 1.0)

    def time_left(self) -> tuple[float | None, str | None]:
        """Seconds left of the job, and how they were found (:data:`LEFT_FROM`): the plan's
        remainder at the pace (the job's ``time_left``); in the seconds before the job's own
        plan is made, the file's (its analysis', the same plan from room temperature), else
        the slicer's remainder, at the printer's pace; (None, None) for a file none can tell
        of. Given as a :class:`~repetrel_host.gcode.timeline.Countdown`, as the job's own
        figure is (across the change from the one to the other too). One figure for every
        face: OctoPrint's printTimeLeft, Moonraker's, MQTT's progress, the page, /v1."""
        planned = self.job.time_left()
        following = self.job.following
        if planned is not None and following is not None:
            left: float | None = planned
            how: str | None = "estimate" if following.corrected else "plan"
        else:
            left, how = self._before_plan()
        if left is not None:
            paused = self.job.printer.state is rh.State.PAUSED
            left = self.shown.show(left, time.monotonic(), not paused)
        return left, how

    def time_until(self, line: int) -> float | None:
        """Seconds until the file's ``line`` is done (0 once run): the job's plan at its
        pace; before it is made, the file's plan at the printer's (None: neither known)."""
        until = self.job.time_until(line)
        if until is not None or self.job.done:
            return until
        last = self.job.last
        now, then = self._file_after(last.source_line if last else 0), self._file_after(line)
        return max(0.0, now - then) if now is not None and then is not None else None

    def _file_after(self, line: int) -> float | None:
        """The file's planned seconds after ``line`` at the printer's pace (its analysis'
        plan, the heat waits' share as planned); None when it keeps no points."""
        summary = self.summary
        return summary.planned_after(line, self.prior) if summary is not None else None

    def _before_plan(self) -> tuple[float | None, str | None]:
        last = self.job.last
        line = last.source_line if last is not None else 0
        rest = self._file_after(line)
        if rest is not None:
            return rest, "estimate" if self.prior != 1.0 else "plan"
        said = self.marks.at(line, self.fraction).seconds_left if self.marks else None
        if said is None and self.summary is not None and self.summary.slicer_seconds:
            said = self.summary.slicer_seconds * (1 - self.fraction)  # its marks not read yet
        return (said * self.prior, "slicer") if said is not None else (None, None)


async def read_file(running: Running, analyses: Analyses, path: Path, printer: str) -> None:
    """The ``running`` job's file, read once (in a thread): its layers' marks and offsets,
    and its summary (kept since its upload; else made now, and kept)."""

    def read() -> None:
        summary = analyses.cached(path)
        # Its print time is the job's own plan (follow_time): not planned twice.
        found = analyses.analyse(path, moves=summary is None, planned=False)
        running.marks, running.layers = found.marks, found.layer_offsets
        running.summary = summary or found.summary

    try:
        await asyncio.to_thread(read)
    except OSError:
        pass  # gone or unreadable: the job streams what it opened, without layers
    except Exception:  # a bug: the job is followed all the same
        log.exception("printer %s: job %d's file was not analysed", printer, running.record.id)


def filament_used(running: Running, completed: bool) -> dict[str, dict[str, float]] | None:
    """The file's filament by tool, times the share of it the controller acknowledged (all
    of it for a completed job); None when the file's analysis is not known."""
    summary = running.summary
    if summary is None:
        return None
    share = 1.0 if completed else running.fraction
    return {
        tool: {"length": used.length * share, "volume": used.volume * share}
        for tool, used in summary.filament.items()
    }


def _ends(left: float) -> str:
    """When a job with ``left`` seconds to go should end: ISO 8601, UTC, to the second."""
    return (datetime.now(UTC) + timedelta(seconds=left)).isoformat(timespec="seconds")


def layer_times(
    running: Running | None, first_line: int, last_line: int | None
) -> dict[str, int | str | None]:
    """When the ``running`` job prints the layer of its file from ``first_line`` to
    ``last_line`` (None: to the file's end), from its plan at its pace
    (:meth:`Running.time_until`): ``starts_in`` and ``ends_in`` (seconds from now, 0 once
    there), ``starts_at`` and ``ends_at`` (ISO 8601, UTC). None each without a job, or
    while its time is not known."""
    unknown: dict[str, int | str | None] = dict.fromkeys(LAYER_TIMES)
    if running is None:
        return unknown
    starts = running.time_until(first_line - 1)
    ends = running.time_until(FILE_END if last_line is None else last_line)
    if starts is None or ends is None:
        return unknown
    return {
        "starts_in": round(starts),
        "ends_in": round(ends),
        "starts_at": _ends(starts),
        "ends_at": _ends(ends),
    }


def progress_event(
    printer: str, record: JobRecord, job: rh.PrintJob, running: Running | None, completed: bool
) -> PrintProgress:
    """The progress event of ``record``'s ``job`` on ``printer`` (``running``: what is known
    of it while it streams; ``completed``: it ended complete): its lines and bytes, its
    layer, its completion and the time it has left."""
    last = job.last
    last_line = last.source_line if last else 0
    completion: float | None = None
    left: float | None = None
    how: str | None = None
    if completed:
        completion, left = 100.0, 0.0
    elif running is not None:
        completion = 100.0 * running.fraction
        if not job.done:
            left, how = running.time_left()
    return PrintProgress(
        printer=printer,
        job=record.id,
        lines=job.lines,
        last_line=last_line,
        offset=job.offset,
        size=job.size,
        layer=running.layer if running else 0,
        layers=len(running.layers) if running else 0,
        completion=round(completion, 2) if completion is not None else None,
        time_left=round(left) if left is not None else None,
        time_left_from=how,
        ends=_ends(left) if left is not None and not completed else None,
    )
