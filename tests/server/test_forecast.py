"""A printer's queue in time, worked out (server/printers/forecast.py): each queued job's
estimate at the printer's pace, its start after the one before, and what makes them
unknown."""

from __future__ import annotations

from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.server.printers.forecast import forecast, iso, job_seconds
from repetrel_host.server.store import JobRecord, JobState

PLANNED = FileSummary(planned_seconds=100.0, planned_points=((10, 20.0), (20, 100.0)))


def queued(job_id: int, from_line: int | None = None) -> JobRecord:
    return JobRecord(
        id=job_id,
        printer="bench",
        name=f"{job_id}.gcode",
        file=f"files/{job_id}.gcode",
        state=JobState.QUEUED,
        position=float(job_id),
        submitted=0.0,
        started=None,
        ended=None,
        lines=0,
        last_line=0,
        total_lines=20,
        error=None,
        from_line=from_line,
    )


def test_queued_jobs_follow_each_other_at_the_printers_pace() -> None:
    jobs = [queued(1), queued(2, from_line=16)]
    found = forecast(jobs, {1: PLANNED, 2: PLANNED}, 1.5, 1000.0, held=False)
    first, second = found.jobs[1], found.jobs[2]
    assert (first.seconds, first.start, first.end) == (150.0, 1000.0, 1150.0)
    # From line 16: the plan after line 15 (half way from 20 s to 100 s), at the pace.
    assert second.seconds == 1.5 * 40.0 and not second.whole_file
    assert (second.start, second.end) == (1150.0, 1210.0)
    assert found.free_at == 1210.0
    assert second.as_json()["estimated_end"] == iso(1210.0)


def test_what_cannot_be_told_is_none() -> None:
    jobs = [queued(1), queued(2)]
    # The first job's file not planned yet: its start is known, its end and all after not.
    found = forecast(jobs, {1: None, 2: PLANNED}, 1.0, 1000.0, held=False)
    assert found.jobs[1].start == 1000.0 and found.jobs[1].end is None
    assert found.jobs[2].seconds == 100.0 and found.jobs[2].start is None
    assert found.free_at is None
    # Held, or paused (no free time): how long each takes, and no start.
    for held, free_from in ((True, 1000.0), (False, None)):
        found = forecast(jobs, {1: PLANNED, 2: PLANNED}, 1.0, free_from, held)
        assert [t.seconds for t in found.jobs.values()] == [100.0, 100.0]
        assert [t.start for t in found.jobs.values()] == [None, None]
        assert found.free_at is None
    # Nothing queued: free when what runs ends.
    assert forecast([], {}, 1.0, 1000.0, held=False).free_at == 1000.0
    # A summary without points: a job from a line counts its whole file, and says so.
    whole = job_seconds(FileSummary(planned_seconds=100.0), 16, 1.0)
    assert whole.seconds == 100.0 and whole.whole_file
    assert job_seconds(None, None, 1.0).seconds is None
