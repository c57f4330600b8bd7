"""A farm job's estimate: the planned print time of its file (or of the rest of it, for a
job recovered from a line), worked out by the node that has the file.

Planning a file takes seconds of CPU a megabyte, so :func:`planned` is called in a thread
(the analysis plans in a worker process). The plan is the file analysis' (kept with the
other analyses, so a file sent again is not planned again); the rest from a line is read
from the planned points it keeps, as a printer's own queue reads it.
"""

from __future__ import annotations

from pathlib import Path

from repetrel_host.server.analyses import Analyses, unplanned
from repetrel_host.server.printers.forecast import job_seconds

WHOLE = "file"  # the estimate is of the whole file
REST = "rest"  # of the file from the job's first line on


def planned(analyses: Analyses, path: Path, from_line: int | None) -> tuple[float, str] | None:
    """The planned seconds of the job that prints ``path`` (from ``from_line`` on, when
    given) and what they are of (:data:`WHOLE` or :data:`REST`); None for a file without
    moves. Any thread but the event loop's; :class:`OSError` when the file cannot be read."""
    summary = analyses.cached(path)
    if summary is None or unplanned(summary):
        summary = analyses.analyse(path).summary
    estimate = job_seconds(summary, from_line if from_line and from_line > 1 else None, 1.0)
    if estimate.seconds is None:
        return None
    rest = from_line is not None and from_line > 1 and not estimate.whole_file
    return estimate.seconds, REST if rest else WHOLE
