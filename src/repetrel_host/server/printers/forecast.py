"""When a printer's queued jobs should run, and when the printer should be free: each queued
job's estimate (its file's planned print time at the printer's learned pace), its start and
end in queue order from the time the printer is free of what it does now, and the end of the
last. Unknown (None) rather than guessed wherever something before it is unknown."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.server.store import JobRecord


@dataclass(frozen=True)
class QueuedTimes:
    """A queued job's estimate and when it should start and end (seconds since the epoch)."""

    seconds: float | None  # how long it should take; None: its file is not planned yet
    whole_file: bool  # the seconds are its whole file's, though it starts from a line
    start: float | None
    end: float | None

    def as_json(self) -> dict[str, Any]:
        """The job listing's fields of a queued job."""
        return {
            "estimated_time": round(self.seconds) if self.seconds is not None else None,
            "estimated_time_whole_file": self.whole_file,
            "estimated_start": iso(self.start),
            "estimated_end": iso(self.end),
        }


@dataclass(frozen=True)
class Forecast:
    """A printer's queued jobs' times, by job id, and when the printer should be free."""

    jobs: dict[int, QueuedTimes]
    free_at: float | None  # seconds since the epoch; None: unknown


def job_seconds(summary: FileSummary | None, from_line: int | None, pace: float) -> QueuedTimes:
    """How long a job of the file ``summary`` describes should take at ``pace``: its planned
    time (its moving part at the pace, its heat waits as planned), or for a job from a line
    its share after the line before it (the whole file's, said so, when the summary keeps
    no points to tell); no start or end yet."""
    planned = summary.planned if summary is not None else None
    if summary is None or planned is None:
        return QueuedTimes(None, False, None, None)
    rest = summary.planned_after(from_line - 1, pace) if from_line is not None else None
    seconds = rest if rest is not None else planned.total(pace)
    return QueuedTimes(seconds, from_line is not None and rest is None, None, None)


def forecast(
    queued: list[JobRecord],
    summaries: Mapping[int, FileSummary | None],
    pace: float,
    free_from: float | None,
    held: bool,
) -> Forecast:
    """The times of ``queued`` (in queue order; ``summaries``: their files', by job id) at
    ``pace``, the first starting at ``free_from`` (None: unknown: the printer is paused or
    offline); none starts while the queue is ``held``. The printer is free at the end of
    the last, or at ``free_from`` when none is queued."""
    times: dict[int, QueuedTimes] = {}
    start = None if held else free_from
    for record in queued:
        estimate = job_seconds(summaries.get(record.id), record.from_line, pace)
        end = (
            start + estimate.seconds if start is not None and estimate.seconds is not None else None
        )
        times[record.id] = QueuedTimes(estimate.seconds, estimate.whole_file, start, end)
        start = end
    return Forecast(times, start if queued else free_from)


def iso(when: float | None) -> str | None:
    """``when`` (seconds since the epoch) as ISO 8601, UTC, to the second; None stays."""
    if when is None:
        return None
    return datetime.fromtimestamp(when, UTC).isoformat(timespec="seconds")
