"""A farm job's estimate: the planned print time of its file (or of the rest of it, for a
job recovered from a line), worked out by the node that has the file.

Planning a file takes seconds of CPU a megabyte, so nothing here runs on the event loop:
:func:`planned` is called in a thread, and plans in a worker process. A file's whole plan
is the file analysis' (kept with the other analyses, so a file sent again is not planned
again); the rest from a line is planned with a timeline of the whole file.
"""

from __future__ import annotations

import math
from pathlib import Path

from repetrel_host.gcode.estimate import estimate_file
from repetrel_host.gcode.timeline import Timeline
from repetrel_host.server.analyses import Analyses, unplanned
from repetrel_host.session.workers import in_worker

WHOLE = "file"  # the estimate is of the whole file
REST = "rest"  # of the file from the job's first line on


def planned(analyses: Analyses, path: Path, from_line: int | None) -> tuple[float, str] | None:
    """The planned seconds of the job that prints ``path`` (from ``from_line`` on, when
    given) and what they are of (:data:`WHOLE` or :data:`REST`); None for a file without
    moves. Any thread but the event loop's; :class:`OSError` when the file cannot be read."""
    if from_line is not None and from_line > 1:
        rest = in_worker(planned_rest, path, from_line)
        return (rest, REST) if rest is not None else None
    summary = analyses.cached(path)
    if summary is None or unplanned(summary):
        summary = analyses.analyse(path).summary
    if summary is None or summary.planned_seconds is None:
        return None
    return summary.planned_seconds, WHOLE


def planned_rest(path: Path, from_line: int) -> float | None:
    """The planned seconds of ``path`` from ``from_line`` on (the whole file is planned, and
    the time before that line taken off); None for a file without moves."""
    timeline = Timeline()
    try:
        estimate = estimate_file(path, on_time=timeline.add, on_heat=timeline.heated)
    except ArithmeticError:  # numbers past a float's range: no plan (as the analysis)
        return None
    timeline.finish()
    if not estimate.moves or not math.isfinite(estimate.seconds):
        return None
    before, _ = timeline.at(from_line - 1)
    return max(estimate.seconds - before, 0.0)
