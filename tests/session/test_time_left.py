"""The time left of a running job, against the fake controller (its own process, on a pty)
whose moves take their planned time: ``--time-scale 12``, so the cone's first four layers,
3 minutes planned, run in 16 s. Both plan with Marlin's defaults (the job has no slicer
settings block, and the fake is given none).

This tests the plumbing (the plan made as the job starts, the acknowledged line, the run's
pace, the pace learned from the printer's last job), not the model: the fake's moves take
the time the same planner gives them. The pace of a printer that keeps to the plan is
1/12 here: what "as planned" is for a printer 12 times faster than the plan. Faster than
that, the cone's short moves need more lines a second than the link feeds one by one (the
fake's planner runs dry and the run goes at the link's pace: 8 % slow at x25).

How close it comes is a figure (``bench/time_left.py`` prints it: within 2 or 3 % at 25,
50 and 75 %); the bounds here are looser, since a loaded machine's fake strays from its
plan, but tight enough to catch plumbing gone wrong (a wrong line, a lost pace, the
controller's lead not counted: each 20 % or more)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.session.history import paces
from tests.support.paths import DATA

pytestmark = pytest.mark.timeout(120)

CONE = DATA / "cone-prusaslicer.gcode"
SCALE = 12.0
Sample = tuple[float, float, float | None]  # share of the file, when, the time left


def first_layers(folder: Path, layers: int = 4) -> Path:
    """The cone's first ``layers`` layers (without its slicer's settings, at its end)."""
    lines = CONE.read_text().splitlines()
    end = scan_marks(CONE).layers[layers].line - 1
    path = folder / "cone.gcode"
    path.write_text("\n".join(lines[:end]) + "\n")
    return path


async def sampled_run(
    job_file: Path, scale: float, prior: float, history: Path
) -> tuple[list[Sample], float, rh.PrintJob]:
    """``job_file`` on a controller ``scale`` times faster than the plan: the time left
    every 20 ms, and when its last move was done."""
    fake = ["--time-scale", str(scale)]
    # A USB link (2 Mbaud: the fake's bandwidth 200 KB/s), which keeps its planner fed.
    async with rh.connect("fake", baud=2_000_000, fake_args=fake, poll_interval=None) as printer:
        job = await printer.print(job_file, history=history)
        await job.follow_time(prior)
        samples = []
        while not job.done:
            samples.append((job.offset / job.size, time.monotonic(), job.time_left()))
            await asyncio.sleep(0.02)
        await job.wait()
        await printer.command("M400")  # answered once every move the controller held ran
        return samples, time.monotonic(), job


def errors_at(samples: list[Sample], end: float, shares: tuple[float, ...]) -> list[float]:
    """The time left's error against the real remainder, where the job first reached each
    share of the file."""
    found = []
    for share in shares:
        _, when, left = next(s for s in samples if s[0] >= share)
        assert left is not None, f"no time left at {share:.0%}"
        found.append((left - (end - when)) / (end - when))
    return found


def test_the_time_left_is_the_real_remainder_on_a_machine_that_keeps_to_the_plan(
    tmp_path: Path,
) -> None:
    job_file = first_layers(tmp_path)
    # The printer's pace as its last jobs taught it: 12 times the plan's.
    history = tmp_path / "20261204-100000-cone.gcode"
    samples, end, job = asyncio.run(sampled_run(job_file, SCALE, 1 / SCALE, history))
    assert job.following is not None
    assert job.following.measured == pytest.approx(1 / SCALE, rel=0.05)
    errors = errors_at(samples, end, (0.25, 0.5, 0.75))
    assert all(abs(error) <= 0.1 for error in errors), errors


def test_a_machine_slower_than_the_plan_is_found_out_and_its_pace_learned(
    tmp_path: Path,
) -> None:
    job_file = first_layers(tmp_path)
    slower = SCALE / 1.1  # 10 % slower than the plan; the printer's pace thought as planned
    first = tmp_path / "20261204-100000-cone.gcode"
    samples, end, job = asyncio.run(sampled_run(job_file, slower, 1 / SCALE, first))
    errors = errors_at(samples, end, (0.25, 0.5, 0.75))
    assert all(abs(error) <= 0.1 for error in errors), errors
    # The run's record keeps its pace; the next job starts from it, right from the start.
    learned = learned_pace(paces(tmp_path, job.printer.port, job.plan.profile.name or ""))
    assert learned == pytest.approx(1.1 / SCALE, rel=0.05)
    second = tmp_path / "20261204-110000-cone.gcode"
    samples, end, _ = asyncio.run(sampled_run(job_file, slower, learned, second))
    errors = errors_at(samples, end, (0.05, 0.25, 0.5, 0.75))
    assert all(abs(error) <= 0.1 for error in errors), errors
