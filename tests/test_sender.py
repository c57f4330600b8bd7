"""The asyncio sender in-process against the pty fake: safe stop, host actions, tags."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest
from rich.console import Console

from repetrel_host.config import HostSettings
from repetrel_host.console import ConsoleObserver
from repetrel_host.errors import ControllerError, JobError, LinkError
from repetrel_host.job import HostAction, JobItem, JobLine
from repetrel_host.link import BuiltInFake
from repetrel_host.protocol.dialects.reprap import RepRapDialect as HostProtocol
from repetrel_host.protocol.events import Failed, FailureKind
from repetrel_host.sender import Observer, Outcome, _failure_error, stream
from tests.helpers import executed

pytestmark = pytest.mark.timeout(30)
SAFE = ["M104 S0", "M84"]


def line(n: int, command: str) -> JobLine:
    return JobLine(n, n, command, n, "job.gcode")


class Recorder(Observer):
    def __init__(self, answer: bool = True) -> None:
        self.acknowledged: list[str] = []
        self.actions: list[HostAction] = []
        self.answer = answer

    def on_acknowledged(self, line: JobLine) -> None:
        self.acknowledged.append(line.position)

    async def perform(self, action: HostAction) -> bool:
        self.actions.append(action)
        await asyncio.sleep(0.05)
        return self.answer


def run(fake: BuiltInFake, items: Iterator[JobItem] | list[JobItem], observer: Observer):  # type: ignore[no-untyped-def]
    return asyncio.run(stream(fake.port, 115200, HostProtocol(), items, observer, safe_stop=SAFE))


def test_a_bad_line_mid_job_stops_with_the_safe_stop_first(tmp_path: Path) -> None:
    def items() -> Iterator[JobItem]:
        yield line(1, "G28")
        yield line(2, "G1 X1")
        raise JobError("job.gcode:3: the command is not ASCII text")

    with BuiltInFake(tmp_path / "log") as fake, pytest.raises(JobError, match=r"job\.gcode:3"):
        run(fake, items(), Recorder())
    # Lines read but not yet on the wire are dropped like on a cancel; the safe stop goes.
    done = executed(fake.log_path)
    assert done[-2:] == SAFE
    assert done[:-2] == ["G28", "G1 X1"][: len(done) - 2]


def test_host_action_runs_after_everything_before_it_is_acknowledged(tmp_path: Path) -> None:
    action = HostAction("actions", "", (("BEEP", ""),), 2, "job.gcode")
    recorder = Recorder()
    with BuiltInFake(tmp_path / "log") as fake:
        summary = run(fake, [line(1, "G28"), action, line(3, "G1 X1")], recorder)
    assert summary.outcome is Outcome.COMPLETED
    assert recorder.actions == [action]
    assert recorder.acknowledged == ["job.gcode:1", "job.gcode:3"]
    assert executed(fake.log_path) == ["G28", "G1 X1"]


def test_an_action_that_declines_stops_the_job_safely(tmp_path: Path) -> None:
    action = HostAction("pause", "", (), 2, "job.gcode")
    with BuiltInFake(tmp_path / "log") as fake:
        summary = run(fake, [line(1, "G28"), action, line(3, "G1 X1")], Recorder(answer=False))
    assert summary.outcome is Outcome.CANCELLED
    assert executed(fake.log_path) == ["G28", *SAFE]


def test_failures_name_the_source_position() -> None:
    where = JobLine(0, 0, "M6 T1 O2 X0 Y0 Z0", 0, "header: head T1 (MK1-250)")
    error = _failure_error(
        Failed(FailureKind.CONTROLLER, "the controller reported an error: x", where)
    )
    assert isinstance(error, ControllerError)
    assert str(error).endswith("(at header: head T1 (MK1-250))")
    assert isinstance(
        _failure_error(Failed(FailureKind.TIMEOUT, "silence", line(7, "G1"))), LinkError
    )


def test_resends_are_shown_with_the_source_position() -> None:
    console = Console(record=True, width=200)
    observer = ConsoleObserver(console, HostSettings(), Path("unused.log"))
    observer.on_resend(line(1234, "G1 X1"))
    assert "resend: the controller asked again for job.gcode:1234" in console.export_text()
