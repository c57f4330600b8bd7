"""hyrel-send on Hyrel's own link: real processes over a real pty."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.protocol.dialects.hyrel import SYNC_EVERY_MIN, SYNC_INTERVAL
from repetrel_host.session.job import Job
from tests.support.helpers import (
    CONE,
    EXAMPLE,
    HYREL_SAFE_STOP,
    hyrel_send,
    job_commands,
    start_streaming,
)

pytestmark = pytest.mark.timeout(60)


def ran(log: Path) -> list[str]:
    """What the fake executed, without the session's M115s (who are you; what ran?) and
    M105s (temperatures for the status line; the test jobs have none)."""
    return [c for c in log.read_text().splitlines() if c not in ("M115", "M105")]


def test_the_readme_job_streams_to_the_built_in_fake_on_hyrels_link(tmp_path: Path) -> None:
    log = tmp_path / "fake.log"
    result = hyrel_send(str(EXAMPLE), "--protocol", "hyrel", "--fake-log", str(log))
    assert result.returncode == 0, result.stderr
    assert "Hyrel's own link: the job is done once the controller ran its last line" in (
        result.stdout
    )
    assert "Machine profile: hyrel (from the firmware: >Hy: repetrel-host-fake_1.0)" in (
        result.stdout
    )
    assert ran(log) == job_commands(EXAMPLE)


@pytest.mark.slow
def test_hyrel_send_returns_only_once_the_controller_ran_the_jobs_end(tmp_path: Path) -> None:
    job = tmp_path / "dwell.gcode"
    moves = [f"G1 X{i % 100} Y{i % 30}" for i in range(300)]
    job.write_text("\n".join(["G28", *moves, "G4 S3", "M104 S0"]) + "\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--protocol", "hyrel"], control=True) as fake:
        started = time.monotonic()
        result = hyrel_send(str(job), "--port", fake.port, "--protocol", "hyrel")
        elapsed = time.monotonic() - started
        fake.request("status")  # the fake's log is complete
    assert result.returncode == 0, result.stderr
    # Every line was received within a fraction of a second; the end ran 3 s later.
    assert "every line is sent: waiting until the controller has run the last" in result.stdout
    assert elapsed >= 3 and ran(log)[-2:] == ["G4 S3", "M104 S0"]
    assert "done: 303 lines" in result.stdout


def test_report_shows_the_controllers_m773_report_and_keeps_it(tmp_path: Path) -> None:
    job = tmp_path / "part.gcode"
    job.write_text("G28\nG90\nM83\nG1 X10 Y0 F600\nG1 X20 E1.5\nG1 Y10 E1\nM30\n")
    history = tmp_path / "history"
    result = hyrel_send(str(job), "--protocol", "hyrel", "--report", "--history", str(history))
    assert result.returncode == 0, result.stderr
    assert "The controller's job report (M773):" in result.stdout
    # 10 mm of travel, then 20 mm extruding 2.5 mm, at 10 mm/s.
    assert "  Totals:                    3.0       0.030" in result.stdout
    reports = list(history.glob("*-part-report.txt"))
    assert len(reports) == 1 and "**  End M773 Report" in reports[0].read_text()
    assert f"Job report: {reports[0]}" in result.stdout


def test_ctrl_c_aborts_what_the_controller_holds_then_the_safe_stop_runs(tmp_path: Path) -> None:
    log, received = tmp_path / "slow.log", tmp_path / "received.bin"
    args = ["--protocol", "hyrel", "--move-time", "0.01", "--received", str(received)]
    with BuiltInFake(log, args, control=True) as slow:
        process = start_streaming(CONE, slow.port, log, "--protocol", "hyrel")
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
        slow.request("status")
    assert process.returncode == 130, stderr
    assert "stopping: sending the safe-stop sequence" in stdout
    done = ran(log)
    assert done[-len(HYREL_SAFE_STOP) :] == HYREL_SAFE_STOP
    sent = done[: -len(HYREL_SAFE_STOP)]
    assert 0 < len(sent) < len(job_commands(CONE)) and sent == job_commands(CONE)[: len(sent)]
    # Abort (0x08), then the safe stop as urgent lines (0x09 first): hundreds of received
    # lines never ran.
    wire = received.read_bytes()
    abort = wire.index(b"\x08")
    assert wire[abort + 1 :].startswith(b"\x09N") and b"\x09N" not in wire[:abort]
    assert wire[:abort].count(b"\n") - len(sent) > 100


def test_a_framed_dry_run_shows_hyrels_wire() -> None:
    result = hyrel_send(str(EXAMPLE), "--protocol", "hyrel", "--dry-run", "--framed")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "<0x07>N1 M107"  # the ping, then numbered lines
    assert lines[-1].endswith(" M115")  # the sync that confirms the end
    # And one among every SYNC_EVERY_MIN lines: the simulated controller runs them in no
    # time, so no answer says how many run in a second.
    commands = len(job_commands(EXAMPLE))
    syncs = [line for line in lines if line.endswith(" M115")]
    assert len(syncs) == commands // SYNC_EVERY_MIN + 1 and len(lines) == commands + len(syncs)


MOVE_TIME = 0.02  # 50 moves a second: a slow job, as a fake can run it


@pytest.mark.parametrize("progress", [False, True], ids=["as-sliced", "m73-first"])
@pytest.mark.timeout(90)
@pytest.mark.slow
def test_ctrl_c_names_a_resume_line_close_behind_what_ran_and_never_past_it(
    tmp_path: Path, progress: bool
) -> None:
    job = CONE  # its M82 (line 20) is never noticed; with PrusaSlicer's M73 first, nor that
    if progress:
        job = tmp_path / "cone-m73.gcode"
        job.write_text("M73 P0 R12\n" + CONE.read_text())
    log = tmp_path / "fake.log"
    fake_args = ["--protocol", "hyrel", "--move-time", str(MOVE_TIME)]
    with BuiltInFake(log, fake_args, control=True) as fake:
        process = start_streaming(job, fake.port, log, "--protocol", "hyrel", "--no-history")
        deadline = time.monotonic() + 30
        while len(ran(log)) < 250 and time.monotonic() < deadline:
            time.sleep(0.05)  # a few hundred lines in: before the first 256 lines ran
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
        fake.request("status")  # the fake's log is complete
    assert process.returncode == 130, stderr
    prefix = "To resume from the first line not known to have run: "
    (hint,) = [line for line in stdout.splitlines() if line.startswith(prefix)]
    assert hint.split()[-2] == "--from-line"
    resume = int(hint.split()[-1])
    lines = list(Job(job).lines())
    done = ran(log)[: -len(HYREL_SAFE_STOP)]
    assert done == [line.command for line in lines[: len(done)]]  # once each, in order
    claimed = [line for line in lines if line.source_line < resume]
    # Every line the hint says ran did: resuming skips none.
    assert len(claimed) <= len(done)
    # And it is close behind: what ran since the last answer that said so, at most what
    # runs in a SYNC_INTERVAL between two syncs, and as much again (the answer on its way
    # as the stop came, and the lines the controller had taken, that the abort stopped).
    assert len(done) - len(claimed) <= 2 * SYNC_INTERVAL / MOVE_TIME, (resume, len(done))
