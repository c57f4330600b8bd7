"""The job a printer of the server streams now: where it is (its layer, its height, the
share of the file acknowledged), how long it has left, when it prints a layer of its file,
and the filament it used."""

from __future__ import annotations

import bisect
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

import repetrel_host as rh
from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.gcode.marks import SlicerMarks
from repetrel_host.server.events import PrintProgress
from repetrel_host.server.store import JobRecord

# How a time left was found: the plan at the pace of the run or of the printer's past jobs;
# the plan as it is; the slicer's figure; the rate so far.
LEFT_FROM = ("estimate", "plan", "slicer", "linear")
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
    def planned(self) -> tuple[float | None, str | None]:
        """The whole job's print time from its moves, and where its limits came from: its
        own plan once made (its machine's limits, its header, the heaters where they were),
        else the file's analysis' (None until either is known, or for a file without
        moves)."""
        following = self.job.following
        if following is not None and following.timeline.total > 0:
            return following.timeline.total, following.timeline.limits_from
        summary = self.summary
        return (summary.planned_seconds, summary.planned_limits_from) if summary else (None, None)

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

    def time_left(self, elapsed: float) -> tuple[float | None, str | None]:
        """Seconds left of the job after ``elapsed`` seconds of it, and how they were found
        (:data:`LEFT_FROM`): the plan's remainder (the job's ``time_left``); until the plan
        is made, the slicer's estimate where the file has one, else the rate so far (once
        0.5 % and 5 s went); (None, None) before any can tell. One figure for every face:
        OctoPrint's printTimeLeft, MQTT's progress, the page, /v1."""
        planned = self.job.time_left()
        following = self.job.following
        if planned is not None and following is not None:
            return planned, "estimate" if following.corrected else "plan"
        fraction = self.fraction
        last = self.job.last
        if self.marks is not None and last is not None:
            left = self.marks.at(last.source_line, fraction).seconds_left
            if left is not None:
                return left, "slicer"
        if fraction > 0.005 and elapsed > 5:
            return elapsed * (1 - fraction) / fraction, "linear"
        return None, None


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
    job: rh.PrintJob | None, first_line: int, last_line: int | None
) -> dict[str, int | str | None]:
    """When ``job`` prints the layer of its file from ``first_line`` to ``last_line`` (None:
    to the file's end), from its plan at the pace it keeps: ``starts_in`` and ``ends_in``
    (seconds from now, 0 once there), ``starts_at`` and ``ends_at`` (ISO 8601, UTC). None
    each without a job, or before its plan is made."""
    unknown: dict[str, int | str | None] = dict.fromkeys(LAYER_TIMES)
    if job is None:
        return unknown
    starts = job.time_until(first_line - 1)
    ends = job.time_until(FILE_END if last_line is None else last_line)
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
            left, how = running.time_left(time.time() - (record.started or time.time()))
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
