"""Every way a run ends leaves every heater off (issue 35): each path (a cancel, a link
lost and found) in each phase of a job (printing, a heat wait, paused, the safe stop
itself), on both links, against the pty fake. What is asserted is read at the fake: its
heater targets and what it executed, never the host's own account.

The job heats two hotends and the bed, as the bug report's did: T0, T1 and the bed must
all be off at the end, whichever hotend was active when the run ended.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.gcode.heaters import Heater, HeaterLog, complete_safe_stop, turns_off
from tests.support.helpers import TWO_HOTENDS, executed
from tests.support.helpers import heater_targets as targets

pytestmark = pytest.mark.timeout(90)
MOVES = "".join(f"G1 X{i % 50} F600\n" for i in range(3000))
HEATING = "M140 S60\nM104 T0 S200\nM104 T1 S210\n"
PHASES = ["printing", "heat wait", "paused", "safe stop"]
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}


async def until(check: Any, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        await asyncio.sleep(0.02)


def ran(log: Path, command: str) -> bool:
    return log.exists() and command in log.read_text().splitlines()


def fake_args(protocol: str, phase: str) -> list[str]:
    args = ["--protocol", protocol, *TWO_HOTENDS, "--move-time", "0.01"]
    if phase == "heat wait":
        args += ["--heat-rate", "1"]  # the job's M109 waits minutes
    if phase == "safe stop":
        args += ["--command-time", "0.3"]  # each line of the safe stop takes a while
    return args


def job_text(phase: str) -> str:
    # T1 is active when the run ends: a bare M104 S0 would leave T0 hot.
    wait = "M109 T1 S210\n" if phase == "heat wait" else ""
    return HEATING + "T1\n" + wait + MOVES


async def into_phase(printer: rh.Printer, job: rh.PrintJob, log: Path, phase: str) -> None:
    """Run the job until it is in ``phase``."""
    if phase == "heat wait":
        await until(lambda: ran(log, "T1"))
        await asyncio.sleep(0.5)  # M109 waits for its heater now
        return
    await until(lambda: ran(log, "G1 X20 F600"))
    if phase == "paused":
        await printer.pause()
    elif phase == "safe stop":
        job.stop()
        await until(lambda: ran(log, "M107") or ran(log, "M107 T47"))


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("path", ["cancel", "link lost and found"])
@pytest.mark.slow
def test_every_heater_is_off_however_the_run_ends(
    tmp_path: Path, protocol: str, phase: str, path: str
) -> None:
    log = tmp_path / "fake.log"
    job_path = tmp_path / "two.gcode"
    job_path.write_text(job_text(phase))

    async def scenario(fake: BuiltInFake) -> None:
        async with rh.connect(fake.port, protocol=protocol, poll_interval=None) as printer:
            job = await printer.print(job_path, history=False)
            await into_phase(printer, job, log, phase)
            if path == "link lost and found":
                assert fake.request("link_drop 2")["ok"]
                try:
                    await job.wait()
                except rh.HostError as error:  # it says the stop went after the reconnect
                    assert phase == "safe stop" or "safe stop went" in str(error), error
            elif phase != "safe stop":
                await printer.cancel()
                assert (await job.wait()).outcome is rh.Outcome.CANCELLED
            else:  # a second stop abandons the one under way, and says what may be on
                assert job.stop()
                with pytest.raises(rh.SafeStopError, match="abandoned before the controller"):
                    await job.wait()
                # Its lines still go as the controller takes them, the session open.
                await until(lambda: ran(log, "M84"))

    with BuiltInFake(log, fake_args(protocol, phase), control=True) as fake:
        asyncio.run(scenario(fake))
        done = executed(log)
        assert targets(fake) == ALL_OFF, done[-12:]
    assert done.count("G0 Z10") <= 1, done[-20:]  # a second lift would lift twice


def test_hyrels_urgent_safe_stop_keeps_the_lift_in_order_whatever_order_urgent_lines_run(
    tmp_path: Path,
) -> None:
    """Hyrel's urgent lines promise no order: a controller that runs the newest first must
    still lift relative (G91, G0 Z10, G90), never an absolute move to Z10 into the part."""
    log = tmp_path / "fake.log"
    job_path = tmp_path / "two.gcode"
    job_path.write_text(job_text("printing"))

    async def scenario(fake: BuiltInFake) -> None:
        async with rh.connect(fake.port, protocol="hyrel", poll_interval=None) as printer:
            job = await printer.print(job_path, history=False)
            await until(lambda: ran(log, "G1 X20 F600"))
            await printer.cancel()
            assert (await job.wait()).outcome is rh.Outcome.CANCELLED

    args = ["--protocol", "hyrel", "--extruders", "2", "--move-time", "0.01"]
    with BuiltInFake(log, [*args, "--command-time", "0.1"], control=True) as fake:
        assert fake.request("urgent_order newest")["ok"]
        asyncio.run(scenario(fake))
        heaters = targets(fake)
    done = executed(log)
    stop = done[done.index("M107 T47") :]
    motion = [c for c in stop if c in ("G91", "G0 Z10", "G90", "M84")]
    assert motion == ["G91", "G0 Z10", "G90", "M84"], stop
    assert heaters == ALL_OFF


# --- the one safe stop, made whole (pure) ---------------------------------------------


def logged(*commands: str) -> HeaterLog:
    log = HeaterLog()
    for command in commands:
        log.note(command)
    return log


def test_the_safe_stop_names_every_hotend_bed_chamber_and_fan_turned_on() -> None:
    log = logged("M104 T0 S200", "T1", "M109 S210", "M141 S40", "M106 P1 S255")
    marlin = ["M107", "M104 S0", "M140 S0", "G91", "G0 Z10", "G90", "M84"]
    assert complete_safe_stop(marlin, log) == [
        "M107", "M107 P1", "M104 T0 S0", "M104 T1 S0", "M140 S0", "M141 S0",
        "G91", "G0 Z10", "G90", "M84",
    ]  # fmt: skip


def test_a_configured_safe_stop_that_forgets_a_heater_still_turns_it_off() -> None:
    log = logged("M140 S60", "M104 S200")
    assert complete_safe_stop(["M107", "G91", "G0 Z10", "G90"], log) == [
        "M107", "M104 S0", "M140 S0", "G91", "G0 Z10", "G90"
    ]  # fmt: skip
    # Made whole once: doing it again changes nothing.
    done = complete_safe_stop(["M107", "M104 S0"], logged("M104 T1 S200", "M106 P2"))
    assert complete_safe_stop(done, logged("M104 T1 S200")) == done


def test_hyrels_group_addresses_are_left_as_they_are() -> None:
    hyrel = ["M107 T47", "M620 T47 E0", "M104 T47 S0", "M140 T46 S0", "M5", "G91", "G0 Z10"]
    assert complete_safe_stop(hyrel, logged("M104 T1 S200", "M140 S60")) == hyrel


def test_only_lines_that_turn_something_off_may_run_in_any_order() -> None:
    anywhere = ["M107", "M107 T47", "M104 T47 S0", "M140 S0", "M620 T47 E0", "M5", "M141 S0"]
    in_order = ["G91", "G0 Z10", "G90", "M84", "M104 S200", "M620 T47 E1", "M106 S255"]
    assert all(turns_off(c) for c in anywhere)
    assert not any(turns_off(c) for c in in_order)


def test_the_heater_log_tells_when_the_heaters_on_change_and_takes_them_back() -> None:
    log = HeaterLog()
    changes: list[list[str]] = []
    log.on_change = lambda: changes.append([h.describe() for h in log.on()])
    log.note("M104 T1 S210")
    log.note("M104 T1 S215")  # still on: no change
    log.note("M104 T1 S0", confirmed=True)
    assert changes == [["hotend T1 at 210 °C (M104 T1 S210)"], []]
    again = HeaterLog()
    again.restore([Heater("hotend", 1, 210.0, "M104 T1 S210")])
    assert complete_safe_stop(["M104 S0"], again) == ["M104 T0 S0", "M104 T1 S0"]


def test_hyrels_group_address_confirmed_at_0_turns_every_head_off_in_the_log() -> None:
    log = logged("M104 T0 S200", "M104 T1 S210", "M140 S60")
    log.note("M104 T47 S0", confirmed=True)
    assert [h.describe() for h in log.on()] == ["bed at 60 °C (M140 S60)"]
    log.note("M140 T46 S0", confirmed=True)
    assert log.on() == []
