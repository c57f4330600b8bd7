"""Real processes over a real pty: hyrel-send against the fake controller."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import (
    CONE,
    EXAMPLE,
    MARLIN_SAFE_STOP,
    executed,
    hyrel_send,
    job_commands,
    start_streaming,
)
from tests.support.paths import ROOT

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def fake(tmp_path: Path) -> Iterator[BuiltInFake]:
    controller = BuiltInFake(tmp_path / "executed.log")
    controller.start()
    yield controller
    controller.stop()


def test_readme_command_streams_the_example_to_the_built_in_fake(tmp_path: Path) -> None:
    log = tmp_path / "fake.log"
    result = hyrel_send(str(EXAMPLE), "--fake-log", str(log))
    assert result.returncode == 0, result.stderr
    assert "built-in fake controller" in result.stdout
    assert "done" in result.stdout
    assert executed(log) == job_commands(EXAMPLE)


@pytest.mark.parametrize("flow", ["buffered", "unbuffered"])
@pytest.mark.slow
def test_slicer_job_over_a_pty_executes_every_line_once(flow: str, fake: BuiltInFake) -> None:
    result = hyrel_send(str(CONE), "--port", fake.port, "--flow", flow)
    assert result.returncode == 0, result.stderr
    fake.stop()
    commands = job_commands(CONE)
    assert len(commands) > 20_000
    assert executed(fake.log_path) == commands
    assert f"{len(commands)} lines" in result.stdout


def test_port_comes_from_the_environment(fake: BuiltInFake) -> None:
    result = hyrel_send(str(EXAMPLE), env={"HYREL_PORT": fake.port})
    assert result.returncode == 0, result.stderr
    assert "built-in fake" not in result.stdout
    fake.stop()
    assert executed(fake.log_path) == job_commands(EXAMPLE)


def test_controller_messages_are_shown(tmp_path: Path, fake: BuiltInFake) -> None:
    job = tmp_path / "hello.gcode"
    job.write_text("M115 ; report firmware\nG28\n")
    result = hyrel_send(str(job), "--port", fake.port)
    assert result.returncode == 0, result.stderr
    assert "controller: FIRMWARE_NAME:repetrel-host fake controller" in result.stdout


def test_slow_uart_with_a_small_dropping_buffer_needs_no_resend(tmp_path: Path) -> None:
    log = tmp_path / "uart.log"
    args = ["--bandwidth", "11520", "--latency", "0.002", "--rx-buffer", "128"]
    with BuiltInFake(log, args) as uart:
        result = hyrel_send(str(EXAMPLE), "--port", uart.port)
    assert result.returncode == 0, result.stderr
    assert "0 resend requests" in result.stdout
    assert executed(log) == job_commands(EXAMPLE)


def test_ctrl_c_stops_cleanly_without_losing_or_repeating(tmp_path: Path) -> None:
    log = tmp_path / "slow.log"
    # 2 ms a move and a 16-block planner: the cone would take about 40 s.
    with BuiltInFake(log, ["--move-time", "0.002"]) as slow:
        process = start_streaming(CONE, slow.port, log)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
        time.sleep(0.2)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert "interrupted" in stdout
    assert "stopping: sending the safe-stop sequence (Ctrl-C again to abandon it)" in stdout
    assert f"the last line the controller acknowledged is {CONE.name}:" in stdout
    # What was sent ran once, in order, then the safe-stop sequence: no machine given, and
    # the fake says it is a Marlin-style controller, so the marlin profile's.
    assert "Machine profile: marlin (from the firmware: repetrel-host fake controller" in stdout
    done = executed(log)
    safe_stop = MARLIN_SAFE_STOP
    assert done[-len(safe_stop) :] == safe_stop
    sent = done[: -len(safe_stop)]
    commands = job_commands(CONE)
    assert 0 < len(sent) < len(commands)
    assert sent == commands[: len(sent)]


def test_fake_controller_entry_point_makes_a_link(tmp_path: Path) -> None:
    link = tmp_path / "hyrel0"
    process = subprocess.Popen(
        [sys.executable, "-m", "tools.fake_controller", "--link", str(link)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert process.stdout is not None
        assert process.stdout.readline().strip() == f"ready {link}"
        assert link.is_symlink()
        result = hyrel_send(str(EXAMPLE), "--port", str(link))
        assert result.returncode == 0, result.stderr
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert not link.exists()


def test_fake_controller_refuses_to_replace_a_file(tmp_path: Path) -> None:
    precious = tmp_path / "notes.txt"
    precious.write_text("keep me")
    result = subprocess.run(
        [sys.executable, "-m", "repetrel_host.fakes.fake_controller", "--link", str(precious)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2
    assert "exists and is not a link" in result.stderr
    assert precious.read_text() == "keep me"


def test_a_link_that_pushes_back_holds_the_sender_without_spinning(tmp_path: Path) -> None:
    # A window far larger than the pty's buffer: writes meet a full port and must wait
    # for it to drain, with the event loop free (no busy retry, no stuck writer).
    job = tmp_path / "moves.gcode"
    commands = [f"G1 X{i % 100}.{i % 10} Y{i % 77}.5 E{i}.25" for i in range(4000)]
    job.write_text("\n".join(commands) + "\n")
    log = tmp_path / "fake.log"
    slow = ["--overflow", "block", "--slots", "1", "--planner", "1", "--move-time", "0.0002"]
    with BuiltInFake(log, slow) as fake:
        result = hyrel_send(
            str(job), "--port", fake.port, "--rx-buffer", "200000", "--max-lines", "4000"
        )
    assert result.returncode == 0, result.stderr
    assert "Exception" not in result.stderr and "Traceback" not in result.stderr
    assert executed(log) == commands
