"""A farm job's estimate: the planned print time of its file (or of the rest of it, for a
job recovered from a line), worked out by the node that has the file, at the pace of the
printer that prints it.

Planning a file takes seconds of CPU a megabyte, so :func:`planned` is called in a thread
(the analysis plans in a worker process). The plan is the file analysis' (kept with the
other analyses, so a file sent again is not planned again); the rest from a line is read
from the planned points it keeps, as a printer's own queue reads it.

The database keeps the plan's own seconds; the listing gives them at a pace
(:func:`pace_of`): each node publishes its printers' (learned from their past jobs, as each
printer's own queue uses it), and a job takes the pace of the printer it runs on, or of the
printers that could take it while it waits.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from repetrel_host.server.analyses import Analyses, unplanned
from repetrel_host.server.farm import needs
from repetrel_host.server.printers.forecast import job_seconds

WHOLE = "file"  # the estimate is of the whole file
REST = "rest"  # of the file from the job's first line on


def planned(
    analyses: Analyses, path: Path, from_line: int | None
) -> tuple[float, float, str] | None:
    """The planned seconds of the job that prints ``path`` (from ``from_line`` on, when
    given), the heat waits' share of them, and what they are of (:data:`WHOLE` or
    :data:`REST`); None for a file without moves. Any thread but the event loop's;
    :class:`OSError` when the file cannot be read."""
    summary = analyses.cached(path)
    if summary is None or unplanned(summary):
        summary = analyses.analyse(path).summary
    estimate = job_seconds(summary, from_line if from_line and from_line > 1 else None, 1.0)
    if estimate.seconds is None:
        return None
    rest = from_line is not None and from_line > 1 and not estimate.whole_file
    # The heat waits still ahead of its first line (a file heats first): not at a pace.
    heating = summary.planned_heating if summary is not None else 0.0
    if rest and summary is not None and summary.planned_seconds:
        heating = max(0.0, heating - (summary.planned_seconds - estimate.seconds))
    return estimate.seconds, heating, REST if rest else WHOLE


# Where a job's listed pace comes from.
PRINTER = "printer"  # the printer it runs on (ran on), or the one printer that can take it
PRINTERS = "printers"  # the median of the printers that could take it
PLAN = "plan"  # none of them has a past job: the plan as it is (pace 1)


def pace_of(job: Mapping[str, Any], printers: Iterable[Mapping[str, Any]]) -> tuple[float, str]:
    """The pace a farm job's estimate is listed at, and where it comes from (:data:`PRINTER`,
    :data:`PRINTERS` or :data:`PLAN`). ``printers``: the farm's, as :meth:`FarmDB.printers`
    gives them (``pace`` None: no past job, so 1, the plan's). A job claimed by a printer
    takes that printer's pace; a queued one the median of the printers that could take it
    (their needs met, not one that gave it back, their node not lost)."""
    if job["printer"] is not None:
        runs_on = [p for p in printers if p["node"] == job["node"] and p["name"] == job["printer"]]
    else:
        runs_on = [
            p
            for p in printers
            if not p["lost"]
            and f"{p['node']}/{p['name']}" not in job["refused"]
            and not needs.missing(p["caps"], job["needs"])
        ]
    paces = [p["pace"] for p in runs_on]
    if not any(pace is not None for pace in paces):
        return 1.0, PLAN
    pace = statistics.median(1.0 if pace is None else pace for pace in paces)
    return pace, PRINTER if len(paces) == 1 else PRINTERS


class Paces:
    """:func:`pace_of` for a listing's jobs: jobs that wait with the same needs (copies of a
    file, a queue of alike jobs) are matched against the printers once."""

    def __init__(self, printers: Iterable[Mapping[str, Any]]) -> None:
        self.printers = list(printers)
        self._found: dict[str, tuple[float, str]] = {}

    def of(self, job: Mapping[str, Any]) -> tuple[float, str]:
        key = json.dumps(
            [job["node"], job["printer"], job["needs"], sorted(job["refused"])], sort_keys=True
        )
        if key not in self._found:
            self._found[key] = pace_of(job, self.printers)
        return self._found[key]
