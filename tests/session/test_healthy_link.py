"""A healthy link draws no error from the controller, whatever the session does on it: its
greeting, commands typed at the printer, heat waits, dwells, long moves, a pause, a cancel,
the polls of an idle printer. Read from the fake's own count of the errors it answered, on
both links, in this process and through a pty."""

import asyncio
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.links import FakeLink, SimLink
from tests.support.helpers import job_file, run

pytestmark = pytest.mark.timeout(120)

SCALE = 20  # moves and dwells take a twentieth of their planned time
JOB = [
    "M140 S40", "M104 S60", "M190 S40", "M109 S60", "G28", "G92 E0",
    *(f"G1 X{(i * 37) % 200} Y{(i * 17) % 150} E{i * 0.1:.1f} F{600 * (1 + i % 5)}"
      for i in range(60)),
    "G4 S2", "G1 X0 Y0 F300", "M400", "M104 S0", "M140 S0",
]  # fmt: skip


def connect(kind: str, protocol: str, **options: Any) -> Any:
    if kind == "sim":
        settings = ControllerSettings(
            bandwidth=11_520, latency=0.001, time_scale=SCALE, heat_rate=20.0, residency=1.0,
            rx_buffer=8192 if protocol == "hyrel" else 128, banner=protocol != "hyrel",
        )  # fmt: skip
        return rh.connect("sim", sim=settings, protocol=protocol, **options)
    args = ["--time-scale", str(SCALE), "--heat-rate", "20", "--residency", "1"]
    return rh.connect("fake", fake_args=args, protocol=protocol, **options)


async def errors(printer: rh.Printer) -> int:
    """The errors the controller answered so far, by its own count."""
    link = printer.link
    if isinstance(link, SimLink):
        assert link.controller.simulator is not None
        return link.controller.simulator.link.errors
    assert isinstance(link, FakeLink)
    status = await asyncio.to_thread(link.fake.request, "status")
    return int(status["errors"])


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("kind", ["sim", "fake"])
@pytest.mark.slow
def test_a_session_draws_no_error_from_a_healthy_link(
    kind: str, protocol: str, tmp_path: Path
) -> None:
    async def scenario() -> None:
        async with connect(kind, protocol, poll_interval=0.2) as printer:
            assert await errors(printer) == 0  # the greeting
            for command in ("M105", "G28", "G4 S1", "M400", "M104 S30", "M109 S30", "M114"):
                await printer.command(command)
            assert await errors(printer) == 0  # commands typed at the printer
            job = await printer.print(job_file(tmp_path, JOB), header=False, history=False)
            while job.lines < 20:
                await asyncio.sleep(0.01)
            await printer.pause()
            await asyncio.sleep(0.5)
            await printer.resume()
            assert (await job.wait()).outcome is rh.Outcome.COMPLETED
            assert await errors(printer) == 0  # heat waits, moves, a dwell, a pause
            job = await printer.print(job_file(tmp_path, JOB), header=False, history=False)
            while job.lines < 30:
                await asyncio.sleep(0.01)
            await printer.cancel()
            assert (await job.wait()).outcome is rh.Outcome.CANCELLED
            await asyncio.sleep(1.5)  # an idle printer, polled
            assert await errors(printer) == 0  # a cancel, its safe stop, the polls

    run(scenario)
