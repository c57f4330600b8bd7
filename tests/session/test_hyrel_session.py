"""The session on Hyrel's link where it differs from the RepRap one: what the controller
holds, its M0, its refusals and its report, on the in-process simulator.

Most cases change the simulated controller in one way (a notice lost, an abort that
keeps a pause, the report after M30's notice) to show the session does not rely on it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator, Metrics
from repetrel_host.fakes.settings import ControllerSettings
from tests.support.helpers import HYREL_SAFE_STOP

pytestmark = pytest.mark.timeout(60)
SETTINGS = ControllerSettings(rx_buffer=8192, banner=False, latency=0.0005)


def run(scenario: Callable[[], Coroutine[Any, Any, None]]) -> None:
    asyncio.run(scenario())


def connect(settings: ControllerSettings = SETTINGS, **options: Any) -> Any:
    return rh.connect("sim", sim=settings, protocol="hyrel", poll_interval=None, **options)


def simulator(printer: rh.Printer) -> HyrelControllerSimulator:
    controller = printer.link.controller.simulator  # type: ignore[attr-defined]
    assert isinstance(controller, HyrelControllerSimulator)
    return controller


def ran(printer: rh.Printer) -> list[str]:
    """What the controller ran, without the session's M115s."""
    return [c for c in simulator(printer).executed if c != "M115"]


def job_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "job.gcode"
    path.write_text(text)
    return path


@pytest.mark.parametrize("reconnect", [False, True])
def test_a_refused_line_stops_the_job_with_the_safe_stop_and_the_session_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reconnect: bool
) -> None:
    def corrupt_line_200(self: HyrelControllerSimulator, piece: bytes) -> bytes:
        return piece.replace(b"N200 G1 X", b"N200 G1 Y") if b"N200 " in piece else piece

    monkeypatch.setattr(HyrelControllerSimulator, "_maybe_corrupt", corrupt_line_200)
    job = job_file(tmp_path, "".join(f"G1 X{i % 100}\n" for i in range(1000)))
    settings = ControllerSettings(rx_buffer=8192, banner=False, move_time=0.01, latency=0.0005)

    async def scenario() -> None:
        # hyrel-send connects with reconnect=False: the link must not be dropped for this.
        async with connect(settings, checksum=True, reconnect=reconnect) as printer:
            written = bytearray()
            printer.tap_wire(lambda sent, data: written.extend(data) if sent else None)
            running = await printer.print(job, history=False, header=False)
            with pytest.raises(rh.ControllerError, match=r"checksum mismatch.*at job.gcode:"):
                await running.wait()
            assert b"\x08\x09" in written  # abort, then the safe stop as urgent lines
            assert ran(printer)[-len(HYREL_SAFE_STOP) :] == HYREL_SAFE_STOP
            assert printer.state is rh.State.READY
            assert (await printer.command("M105")).lines[0].startswith(">ST: T:")

    run(scenario)


def test_an_m0_whose_notice_is_lost_pauses_all_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    reply = HyrelControllerSimulator._reply

    def losing_the_m0_notice(self: HyrelControllerSimulator, data: bytes, now: float) -> None:
        if not data.startswith(b">MC:M0:"):  # garbled past recognition
            reply(self, data, now)

    monkeypatch.setattr(HyrelControllerSimulator, "_reply", losing_the_m0_notice)
    job = job_file(tmp_path, "G28\nG1 X1\nM0 ;Remove the part\nG1 X2\n")

    async def proceed(action: rh.job.HostAction) -> bool:
        return True

    async def scenario() -> None:
        async with connect() as printer:
            running = await printer.print(job, history=False, header=False, on_action=proceed)
            # The sync just before the M0 said it was reached.
            await asyncio.wait_for(printer.wait_for(rh.State.PAUSED), 5)
            assert ran(printer) == ["G28", "G1 X1", "M0"]
            await printer.resume()  # end-wait
            await asyncio.wait_for(running.wait(), 5)
            assert ran(printer) == ["G28", "G1 X1", "M0", "G1 X2"]

    run(scenario)


def test_a_cancel_ends_the_pause_should_the_abort_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The notes do not say that abort ends a pause too: the fake's does; this one does not.
    act = HyrelControllerSimulator._act

    def abort_keeps_the_pause(self: HyrelControllerSimulator, control: Any, now: float) -> None:
        held = self._held
        act(self, control, now)
        if control == 0x08:
            self._held = held

    monkeypatch.setattr(HyrelControllerSimulator, "_act", abort_keeps_the_pause)
    job = job_file(tmp_path, "M104 S200\n" + "".join(f"G1 X{i % 100}\n" for i in range(1000)))
    settings = ControllerSettings(rx_buffer=8192, banner=False, move_time=0.01, latency=0.0005)

    async def scenario() -> None:
        async with connect(settings) as printer:
            running = await printer.print(job, history=False, header=False)
            await asyncio.sleep(0.5)
            await printer.pause()
            await asyncio.wait_for(printer.cancel(), 5)  # not the 30 s of a drain timeout
            assert (await running.wait()).outcome is rh.Outcome.CANCELLED
            assert simulator(printer).heaters.target("T") == 0.0  # the safe stop ran
            assert ran(printer)[-len(HYREL_SAFE_STOP) :] == HYREL_SAFE_STOP

    run(scenario)


def test_a_pause_that_comes_as_the_job_ends_holds_nothing_after_it(tmp_path: Path) -> None:
    job = job_file(tmp_path, "G28\nG1 X1\n")
    settings = ControllerSettings(rx_buffer=8192, banner=False, latency=0.3)

    async def scenario() -> None:
        async with connect(settings) as printer:
            controller = simulator(printer)
            running = await printer.print(job, history=False, header=False)
            while controller.executed[-2:] != ["G1 X1", "M115"]:
                await asyncio.sleep(0.01)  # it ran; the answer that says so is on its way
            await printer.pause()  # the hold (0x02) reaches a controller that ran it all
            assert (await running.wait()).outcome is rh.Outcome.COMPLETED
            assert printer.state is rh.State.READY
            reply = await printer.command("M105", timeout=5)  # end-wait went: not held
            assert any(line.startswith(">ST: T:") for line in reply.lines)

    run(scenario)


@pytest.mark.slow
def test_m108_is_refused_while_the_controller_holds_the_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    at_the_move: list[float] = []  # the head's temperature as the move after M109 ran
    answer = HyrelControllerSimulator._answer

    def recording(self: HyrelControllerSimulator, command: Any, now: float) -> None:
        if command.text == "G1 X5":
            at_the_move.append(self.temperatures(now)["T"][0])
        answer(self, command, now)

    monkeypatch.setattr(HyrelControllerSimulator, "_answer", recording)
    moves = "".join(f"G1 X{i % 50} Y1\n" for i in range(300))
    job = job_file(tmp_path, f"{moves}M109 S200\nG1 X5\n")
    settings = ControllerSettings(
        rx_buffer=8192, banner=False, latency=0.0005, heat_rate=100.0, move_time=0.01
    )

    async def scenario() -> None:
        async with connect(settings) as printer:
            running = await printer.print(job, history=False, header=False)
            await asyncio.sleep(0.2)
            await printer.pause()
            # On this link M108 is end-wait: it would end the hold behind the session's
            # back, and resume()'s end-wait then the M109's wait.
            with pytest.raises(rh.UsageError, match="resume\\(\\) ends the pause, not M108"):
                await printer.command("M108")
            # The session is paused as its pause byte goes: the controller may take one
            # more line before the byte arrives. Counted once it holds, the M108 refused.
            await asyncio.sleep(0.05)
            assert simulator(printer)._held
            held = len(simulator(printer).executed)
            await asyncio.sleep(0.3)
            assert len(simulator(printer).executed) == held
            await printer.resume()
            await asyncio.wait_for(running.wait(), 20)
        assert at_the_move == [pytest.approx(200.0)]  # the M109 waited until it got there

    run(scenario)


def test_the_m773_report_is_the_jobs_when_it_comes_after_m30s_notice(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The fake sends the report, then M30's notice; a controller may do it the other way.
    answer = HyrelControllerSimulator._answer

    def notice_then_report(self: HyrelControllerSimulator, command: Any, now: float) -> None:
        if command.word != "M30":
            answer(self, command, now)
            return
        self._reply(b">MC:M30:\n", now)
        lines = (self.metrics or Metrics()).report()
        self._reply("".join(f"{line}\n" for line in lines).encode(), now)

    monkeypatch.setattr(HyrelControllerSimulator, "_answer", notice_then_report)
    job = job_file(tmp_path, "G28\nG1 X10 F600\nM30\n")
    settings = ControllerSettings(rx_buffer=8192, banner=False, latency=0.0005, bandwidth=11_520)

    async def scenario() -> None:
        async with connect(settings) as printer:
            running = await printer.print(job, history=False, header=False, report=True)
            await running.wait()
            assert running.report is not None and running.report.complete
            assert running.report.fields["Totals"] == ["1.0", "0.010"]

    run(scenario)
