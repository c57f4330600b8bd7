"""A target set is the session's at once (issue 50): once the controller acknowledged a
heater's command, the session's reading of that heater has the new target (and a
Temperatures event tells it), before the controller's next report; on both links, for a
hotend by its T word (a Hyrel head by its address), the bed, and a job's own M104 where
the ok says the line ran."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.session.targets import with_target
from tests.support.helpers import job_file, run

pytestmark = pytest.mark.timeout(60)


def connect(protocol: str, **options: Any) -> Any:
    """A session that never asks for temperatures itself: only the greeting's report."""
    sim = ControllerSettings(latency=0.0005, banner=False, **options)
    return rh.connect("sim", sim=sim, protocol=protocol, poll_interval=None)


async def reported(printer: rh.Printer) -> None:
    """Once the controller reported its temperatures (a report names the sensors)."""
    if not printer.temperatures:
        await printer.command("M105")
    assert printer.temperatures


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_a_hotend_and_bed_target_reads_back_as_the_command_returns(protocol: str) -> None:
    async def scenario() -> None:
        async with connect(protocol) as printer:
            await reported(printer)
            events = printer.events()
            await printer.command("M104 S200")
            assert printer.temperatures["T"][1] == 200
            await printer.command("M140 S60")
            assert printer.temperatures["B"][1] == 60
            heard = []
            while len(heard) < 2:
                event = await asyncio.wait_for(anext(events), 5)
                if isinstance(event, rh.Temperatures):
                    heard.append(event.readings)
            assert heard[0]["T"][1] == 200 and heard[1]["B"][1] == 60
            # The controller's next report says the same (the target was its own).
            await printer.command("M105")
            assert printer.temperatures["T"][1] == 200 and printer.temperatures["B"][1] == 60

    run(scenario)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_a_target_set_before_any_report_reads_back_too(protocol: str) -> None:
    # Nothing to set it in yet: the session asks for a report before the command returns.
    async def scenario() -> None:
        async with connect(protocol) as printer:
            assert not printer.temperatures
            await printer.command("M140 S50")
            assert printer.temperatures["B"][1] == 50

    run(scenario)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_a_second_hotend_is_set_by_its_t_word_and_the_first_keeps_its_target(
    protocol: str,
) -> None:
    async def scenario() -> None:
        async with connect(protocol, extruders=2) as printer:
            await reported(printer)
            assert "T1" in printer.temperatures
            await printer.command("M104 T1 S150")
            assert printer.temperatures["T1"][1] == 150
            assert printer.temperatures["T"][1] == 0  # T is the active one: T0
            assert printer.temperatures["T0"][1] == 0

    run(scenario)


def test_a_jobs_own_m104_reads_back_at_its_ok(tmp_path: Path) -> None:
    path = job_file(tmp_path, ["M104 S180", *(f"G1 X{i}" for i in range(200))])

    async def scenario() -> None:
        async with connect("reprap", move_time=0.01) as printer:
            await reported(printer)
            job = await printer.print(path, header=False, history=False)
            for _ in range(200):
                if printer.temperatures["T"][1] == 180:
                    break
                await asyncio.sleep(0.01)
            assert printer.temperatures["T"][1] == 180
            assert not job.done  # while it printed, not at its end
            await job.cancel()

    run(scenario)


def test_hyrel_addresses_name_heads_groups_and_other_devices() -> None:
    readings = {"T": (21.0, 0.0), "T0": (21.0, 0.0), "T1": (22.0, 0.0), "B": (20.0, 0.0)}
    # v4: yoke 1's heads are T11..T15; v5: T0..T19; a group sets every head.
    assert with_target(readings, "M104 T12 S200", 0, "v4") == {**readings, "T1": (22.0, 200.0)}
    assert with_target(readings, "M104 T1 S200", 0, "v5") == {**readings, "T1": (22.0, 200.0)}
    every = with_target(readings, "M104 T47 S90", 0, "v5")
    assert every is not None and {every[s][1] for s in ("T", "T0", "T1")} == {90.0}
    assert with_target(readings, "M104 T21 S90", 0, "v5") is None  # the laser: no head
    assert with_target(readings, "M109 T0", 0, "v5") is None  # a wait: no target given
    # Marlin: no T word is the active tool; M109 R sets the target too.
    active = with_target(readings, "M109 R190", 1, None)
    assert active is not None and active["T1"][1] == 190 and active["T"][1] == 190
    assert active["T0"][1] == 0
    assert with_target({}, "M104 S200", 0, None) is None  # nothing read yet: nothing made up
