"""A farm job's states and the moves between them: the one table every change of a job's
state in the database (db.py) is checked against.

queued -> claimed (a printer took it) -> printing <-> paused -> completed, cancelled,
failed or interrupted; an ended job that did not complete -> resumed (its rest was queued
as a new job: once). A claim goes back to queued (its printer cannot print it, or its node
was lost before it started). Interrupted by the farm (its node's lease ran out) is the
farm's guess: the node's own record, once it is back, says what happened.
"""

from __future__ import annotations

QUEUED, CLAIMED, PRINTING, PAUSED = "queued", "claimed", "printing", "paused"
COMPLETED, CANCELLED, FAILED, INTERRUPTED = "completed", "cancelled", "failed", "interrupted"
RESUMED = "resumed"  # its rest was queued as another job (``resumed_by``)

ACTIVE = (CLAIMED, PRINTING, PAUSED)
RESUMABLE = (INTERRUPTED, FAILED, CANCELLED)
STATES = (QUEUED, *ACTIVE, COMPLETED, *RESUMABLE, RESUMED)
# What a node may report of a job it holds (its own record's states).
REPORTED = (PRINTING, PAUSED, COMPLETED, CANCELLED, FAILED, INTERRUPTED)
# What a node reports of a job that was not stopped after all (cut from the database).
WENT_ON = (PRINTING, PAUSED, COMPLETED)

MOVES: dict[str, frozenset[str]] = {
    QUEUED: frozenset({CLAIMED, CANCELLED}),
    CLAIMED: frozenset({QUEUED, *REPORTED}),
    PRINTING: frozenset(REPORTED),
    PAUSED: frozenset(REPORTED),
    # The farm's guess (a lost lease) gives way to the node's record; a person may resume.
    INTERRUPTED: frozenset({*REPORTED, RESUMED}),
    FAILED: frozenset({RESUMED}),
    CANCELLED: frozenset({RESUMED}),
    COMPLETED: frozenset(),
    # Only when its node says it went on and its rest had not started (db.report cancels
    # the rest then): else resumed is the end.
    RESUMED: frozenset(WENT_ON),
}


class MoveRefused(ValueError):
    """A move the job's state does not allow, in one sentence."""


def allowed(was: str, to: str) -> bool:
    """``was`` may become ``to`` (staying in a state is no move: always allowed)."""
    return was == to or to in MOVES.get(was, frozenset())


def after_report(was: str, reported: str) -> str:
    """The state a job in ``was`` takes when its node reports ``reported``: the node's
    word, unless the job ended for good (completed) or was resumed (the farm keeps
    ``resumed`` but where db.report finds its rest not needed)."""
    if was != RESUMED and allowed(was, reported):
        return reported
    return was


def resume_refusal(job: int, state: str, resumed_by: int | None) -> str:
    """Why job ``job`` in ``state`` cannot be resumed."""
    if state == RESUMED:
        return (
            f"farm job {job} was resumed already, as farm job {resumed_by}: "
            f"that job prints its rest (resume that one if it did not complete)"
        )
    if state == COMPLETED:
        return f"farm job {job} is completed: nothing to resume"
    if state in (QUEUED, *ACTIVE):
        return f"farm job {job} is {state}: it has not ended, nothing to resume"
    return f"farm job {job} is {state}: nothing to resume"
