"""A test's job (:class:`HyrelJob`) and how it went (:class:`PrintResult`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import repetrel_host as rh

FILE_SUFFIXES = (".gcode", ".gco", ".g", ".nc")


@dataclass(frozen=True)
class HyrelJob:
    """A job for :meth:`HyrelPrinter.print`: a G-code file, with the loadout's header or not."""

    path: Path
    header: bool = True
    history: Path | None = None  # where the stream as transmitted is kept


def as_job(job: HyrelJob | Path | str) -> HyrelJob:
    if isinstance(job, HyrelJob):
        return job
    if isinstance(job, str) and "\n" in job:
        raise ValueError(
            "print() takes hyrel_job(...) or a file's path; for G-code text, use hyrel_job(text)"
        )
    return HyrelJob(Path(job))


class PrintResult:
    """How a job went: which of its lines the controller acknowledged, and how it ended."""

    def __init__(
        self,
        job: HyrelJob,
        running: rh.PrintJob,
        summary: rh.Summary | None,
        error: rh.HostError | None,
    ) -> None:
        self.job = job
        self.summary = summary  # None when it failed
        self.error = error
        plan = running.plan
        self.header = [line.command for line in plan.header]  # the header it was sent with
        self.header_acknowledged = self.header[: running.header_lines]
        last = running.last
        self.last_line = last.source_line if last is not None else 0  # file line; 0: none
        # Safe-stop commands not confirmed, when the job was stopped.
        self.safe_stop_missing = running.safe_stop_missing if running.stopping else []
        self._file = plan.job  # read with the machine's own pause command for M0
        self._count = running.lines

    @property
    def completed(self) -> bool:
        """Every line was acknowledged and the job was not cancelled."""
        from repetrel_host.session.pump import Outcome

        return self.summary is not None and self.summary.outcome is Outcome.COMPLETED

    @cached_property
    def commands(self) -> list[str]:
        """The job's lines as sent (an M0 becomes the machine's pause command)."""
        return [line.command for line in self._file.lines()]

    @cached_property
    def acknowledged(self) -> list[str]:
        """Those the controller acknowledged, in order (they go and are confirmed in order)."""
        return [line.command for line in islice(self._file.lines(), self._count)]

    def __repr__(self) -> str:
        how = "completed" if self.completed else f"ended ({self.error or 'cancelled'})"
        return f"<PrintResult {self.job.path.name}: {how}; {self._count} lines acknowledged>"
