"""Temperatures while a job prints (item 6 of issue 22): a controller slow to say who it is
still gets its M155 (once, mid-job if need be), a firmware without auto-reports is polled
between the job's lines, Hyrel's link asks with its status byte; and no poll ever moves
the job's lines (each runs exactly once, in order; a stop stays safe)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.links import SimLink
from repetrel_host.session import identify
from tests.support.helpers import MARLIN_SAFE_STOP, job_file, run

pytestmark = pytest.mark.timeout(60)

HEAT = ["M104 S200", "M140 S60"]
MOVES = [f"G1 X{i % 200} Y{i % 7}" for i in range(600)]


def executed(printer: rh.Printer) -> list[str]:
    assert isinstance(printer.link, SimLink)
    simulator = printer.link.controller.simulator
    assert simulator is not None
    return list(simulator.executed)


def job_lines(printer: rh.Printer) -> list[str]:
    """What ran but the session's own lines: its greeting, M115s, polls and M155."""
    own = ("M110", "M115", "M105", "M155 S1")
    return [c for c in executed(printer) if not c.startswith(own)]


async def targets_seen(printer: rh.Printer, job: rh.PrintJob) -> list[float | None]:
    """The hotend targets the session heard while ``job`` printed."""
    seen: list[float | None] = []
    ending = asyncio.ensure_future(job.wait())
    events = printer.events()
    while not ending.done():
        reading = asyncio.ensure_future(anext(events))
        await asyncio.wait({reading, ending}, return_when=asyncio.FIRST_COMPLETED)
        if not reading.done():
            reading.cancel()
            break
        event = reading.result()
        if isinstance(event, rh.Temperatures) and printer.state is rh.State.PRINTING:
            seen.append(event.readings["T"][1])
    await ending
    return seen


@pytest.mark.slow
def test_a_controller_slow_to_say_who_it_is_gets_its_m155_once_mid_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Its M115 runs 1.5 s, past the session's patience: the session is READY without
    # knowing the firmware, the job starts behind that M115, and the answer comes mid-job.
    monkeypatch.setattr(identify, "FIRMWARE_PATIENCE", 0.5)
    settings = ControllerSettings(latency=0.0005, move_time=0.004, identify_time=1.5)
    path = job_file(tmp_path, HEAT + MOVES)

    async def scenario() -> None:
        connecting = rh.connect("sim", sim=settings, poll_interval=0.2, poll_while_printing=True)
        async with connecting as printer:
            assert printer.firmware is None
            job = await printer.print(path, header=False, history=False)
            seen = await targets_seen(printer, job)
            assert printer.firmware is not None and printer.firmware.can("AUTOREPORT_TEMP")
            assert 200.0 in seen  # reported (M155) as the job went
            ran = executed(printer)
            assert ran.count("M155 S1") == 1
            assert ran.index("M155 S1") > ran.index(HEAT[0])  # mid-job
            assert job_lines(printer) == HEAT + MOVES

    run(scenario)


@pytest.mark.parametrize("faults", ["", "corrupt=0.02 drop_ok=0.02 seed=3"])
def test_m105_polls_between_a_jobs_lines_are_none_of_them(tmp_path: Path, faults: str) -> None:
    # No auto-reports: M105 every 50 ms among the job's lines, on a noisy link too (resends).
    settings = ControllerSettings(
        latency=0.0005, move_time=0.002, autoreport=False, faults=Faults.parse(faults)
    )
    path = job_file(tmp_path, HEAT + MOVES)

    async def scenario() -> None:
        connecting = rh.connect("sim", sim=settings, poll_interval=0.05, poll_while_printing=True)
        async with connecting as printer:
            assert printer.firmware is not None and not printer.firmware.can("AUTOREPORT_TEMP")
            job = await printer.print(path, header=False, history=False)
            seen = await targets_seen(printer, job)
            summary = await job.wait()
            assert summary.lines == len(HEAT + MOVES) and job.last is not None
            assert job.last.command == MOVES[-1]
            ran = executed(printer)
            assert ran.count("M105") >= 3 and 200.0 in seen
            assert job_lines(printer) == HEAT + MOVES

    run(scenario)


def test_a_cancel_among_polls_ends_safe_and_runs_no_line_twice(tmp_path: Path) -> None:
    settings = ControllerSettings(latency=0.0005, move_time=0.005, autoreport=False)
    path = job_file(tmp_path, HEAT + MOVES)

    async def scenario() -> None:
        connecting = rh.connect("sim", sim=settings, poll_interval=0.02, poll_while_printing=True)
        async with connecting as printer:
            job = await printer.print(path, header=False, history=False)
            while job.lines < 100:
                await asyncio.sleep(0.01)
            await printer.cancel()
            assert (await job.wait()).outcome is rh.Outcome.CANCELLED
            assert printer.state is rh.State.READY
            ran = job_lines(printer)
            assert ran[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
            job_part = ran[: -len(MARLIN_SAFE_STOP)]
            assert job_part == (HEAT + MOVES)[: len(job_part)]
            # The session goes on polling once the job ended.
            before = executed(printer).count("M105")
            await asyncio.sleep(0.2)
            assert executed(printer).count("M105") > before

    run(scenario)


def test_hyrels_link_polls_with_its_status_byte_not_a_line(tmp_path: Path) -> None:
    # An M105 would wait behind up to 8 KB of the job in the controller: the status byte
    # is answered at once, and adds no line.
    settings = ControllerSettings(latency=0.0005, move_time=0.003, rx_buffer=8192, banner=False)
    path = job_file(tmp_path, HEAT + MOVES)

    async def scenario() -> None:
        connecting = rh.connect(
            "sim", sim=settings, protocol="hyrel", poll_interval=0.1, poll_while_printing=True
        )
        async with connecting as printer:
            job = await printer.print(path, header=False, history=False)
            seen = await targets_seen(printer, job)
            assert len(seen) >= 3 and 200.0 in seen
            assert job_lines(printer) == HEAT + MOVES
            assert "M105" not in executed(printer)

    run(scenario)
