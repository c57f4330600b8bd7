"""A job's time left while it waits for a heater: the wait counts down with the controller's
temperature reports (not held at the plan's figure), on the RepRap link and on Hyrel's,
and the wait is not taken for slow moving."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings
from tests.support.helpers import job_file, run

pytestmark = pytest.mark.timeout(60)

# About 1 s each, planned; 1/20 of it on the fake.
MOVES = [f"G1 X{(i % 2) * 100} Y{i} F6000" for i in range(1, 61)]
# Midway, from the room to 100 degrees: about 39 s at the plan's 2 a second, 8 s on the fake.
HEAT = ["M109 S100"]


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_a_heat_wait_counts_down_with_the_heaters_reports(tmp_path: Path, protocol: str) -> None:
    settings = ControllerSettings(heat_rate=10.0, time_scale=20.0, rx_buffer=8192, banner=False)
    path = job_file(tmp_path, MOVES + HEAT + MOVES)

    async def scenario() -> None:
        connecting = rh.connect(
            "sim", sim=settings, protocol=protocol, poll_interval=0.2, poll_while_printing=True
        )
        async with connecting as printer:
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
