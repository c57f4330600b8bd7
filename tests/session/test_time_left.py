"""A job's time left while it waits for a heater: the wait counts down with the controller's
temperature reports (not held at the plan's figure), on the RepRap link and on Hyrel's,
and the wait is not taken for slow moving."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.config import UserConfig
from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.gcode.heat_rates import learned_heat_rates
from repetrel_host.session.history import heat_rates, read_record
from repetrel_host.session.planning import JobRequest, plan_job
from tests.support.helpers import job_file, run

pytestmark = pytest.mark.timeout(60)

# About 1 s each, planned; 1/20 of it on the fake.
MOVES = [f"G1 X{(i % 2) * 100} Y{i} F6000" for i in range(1, 61)]
# Midway, from the room to 100 degrees: about 39 s at the plan's 2 a second, 8 s on the fake.
HEAT = ["M109 S100"]


def heating_printer(protocol: str) -> Any:
    """A simulated controller whose hotend climbs 10 degrees a second, its moves 20 times
    faster than planned, its temperatures asked for every 0.2 s."""
    settings = ControllerSettings(heat_rate=10.0, time_scale=20.0, rx_buffer=8192, banner=False)
    return rh.connect(
        "sim", sim=settings, protocol=protocol, poll_interval=0.2, poll_while_printing=True
    )


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_a_heat_wait_counts_down_with_the_heaters_reports(tmp_path: Path, protocol: str) -> None:
    path = job_file(tmp_path, MOVES + HEAT + MOVES)

    async def scenario() -> None:
        async with heating_printer(protocol) as printer:
            job = await printer.print(path, header=False, history=False)
            following = asyncio.ensure_future(job.follow_time(after=0.0))
            seen: list[tuple[float, float]] = []  # (hotend, time left) while it heats
            while not job.done:
                left = job.time_left()
                hotend = printer.temperatures.get("T", (0.0, None))[0]
                if left is not None and 21 < hotend < 95:
                    seen.append((hotend, left))
                await asyncio.sleep(0.05)
            await job.wait()
            await following
            assert job.following is not None
            moving = job.following.timeline.total - job.following.timeline.total_heating
            assert job.following.timeline.total_heating > 35  # from the room, at 2 a second
            hot = [left for hotend, left in seen if hotend > 70]
            cold = [left for hotend, left in seen if hotend < 50]
            assert cold and hot, seen
            # Near 100 degrees, the wait has a few seconds left, not the plan's 37.5.
            assert min(hot) < moving + 15 < job.following.timeline.total
            assert max(hot) < max(cold)
            if protocol == "hyrel":
                return  # its 8 KB buffer holds this whole small file: no stretch is watched
            # The wait was not watched as moving: the run's pace is about the moves' own
            # 1/20 (the wait's 8 s counted would make it 0.13 or more).
            assert job.following.watched_planned > 0
            assert job.following.pace < 0.1

    run(scenario)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_a_jobs_heaters_climbs_are_recorded_and_plan_the_next_jobs_waits(
    tmp_path: Path, protocol: str
) -> None:
    """The fake's hotend climbs at 10 degrees a second (the plan's default is 2): the job's
    record keeps about that rate, and a plan at the learned rates has a five times shorter
    heat-up."""
    path = job_file(tmp_path, HEAT + MOVES)
    history = tmp_path / "history" / "20261206-150000-job.gcode"  # as history_file names it

    async def scenario() -> None:
        async with heating_printer(protocol) as printer:
            job = await printer.print(path, header=False, history=history)
            following = asyncio.ensure_future(job.follow_time(after=0.0))
            await job.wait()
            await following

    run(scenario)
    record = read_record(history)
    assert record is not None and record.heat_rates is not None
    # Timed from reports 0.2 s apart: near the fake's 10 a second, never the plan's 2.
    assert 6.0 < record.heat_rates["hotend"] < 15.0
    learned = learned_heat_rates(heat_rates(history.parent, record.port, record.machine))
    assert learned == record.heat_rates
    plan = plan_job(path, JobRequest(header=False), UserConfig())
    as_profile = plan.timeline({"T0": 21.0}).total_heating
    as_learned = plan.timeline({"T0": 21.0}, learned).total_heating
    assert as_profile == pytest.approx(79 / 2, rel=0.01)  # from 21 to 100 at 2 a second
    assert as_learned == pytest.approx(79 / learned["hotend"], rel=0.01)
