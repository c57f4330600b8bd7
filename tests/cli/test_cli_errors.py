"""Bad input gets one clear sentence and a distinct exit code, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest
import serial

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import (
    CONE,
    MARLIN_SAFE_STOP,
    executed,
    hyrel_send,
    job_commands,
    start_streaming,
)

pytestmark = pytest.mark.timeout(60)


def assert_one_clear_line(stderr: str, *words: str) -> None:
    assert "Traceback" not in stderr
    lines = [
        line
        for line in stderr.splitlines()
        if line.strip() and ": warning: " not in line and not line.startswith("connecting to ")
    ]
    assert len(lines) == 1, stderr
    for word in words:
        assert word in lines[0]


def test_missing_file(tmp_path: Path) -> None:
    result = hyrel_send(str(tmp_path / "nope.gcode"))
    assert result.returncode == 2
    assert_one_clear_line(result.stderr, "no such file")


def test_directory(tmp_path: Path) -> None:
    result = hyrel_send(str(tmp_path))
    assert result.returncode == 2
    assert_one_clear_line(result.stderr, "directory")


def test_missing_port(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(str(job), "--port", str(tmp_path / "ttyUSB9"))
    assert result.returncode == 3
    assert_one_clear_line(result.stderr, "no such port")


def test_not_a_serial_port(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(str(job), "--port", "/dev/null")
    assert result.returncode == 3
    assert_one_clear_line(result.stderr, "not a serial port")


def test_a_folder_for_a_port(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(str(job), "--port", str(tmp_path))
    assert result.returncode == 3
    assert_one_clear_line(result.stderr, f"cannot open {tmp_path}: it is a folder, not a serial")


def test_busy_port(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        holder = serial.Serial(fake.port, 115200, exclusive=True)
        try:
            result = hyrel_send(str(job), "--port", fake.port)
        finally:
            holder.close()
    assert result.returncode == 3
    assert_one_clear_line(result.stderr, "busy")


def test_link_lost_mid_job_reports_the_last_acknowledged_line(tmp_path: Path) -> None:
    log = tmp_path / "lost.log"
    fake = BuiltInFake(log, ["--move-time", "0.002"])
    fake.start()
    process = start_streaming(CONE, fake.port, log, "--reconnect-wait", "1")
    try:
        assert fake.process is not None
        # The controller vanishes, as when a cable is pulled: its port goes with it (as udev
        # removes /dev/ttyUSB0). The port first: a pty's number is free again once the fake
        # is gone, and another test's fake could take it while the link still named it.
        Path(fake.port).unlink()
        fake.process.kill()
        _, stderr = process.communicate(timeout=30)
    finally:
        fake.stop()
    # It tried to reopen the port to send the safe stop; it could not: not safe (exit 5).
    assert process.returncode == 5, stderr
    assert_one_clear_line(
        stderr, "not safe: ", "lost", f"acknowledged is {CONE.name}:", "could not be sent"
    )
    done = executed(log)
    assert done == job_commands(CONE)[: len(done)]


def test_bad_flow_mode(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(str(job), "--flow", "sideways")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr


def test_non_ascii_line_is_refused_before_anything_moves(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_bytes(b"G28\nG1 X1\nG1 X2\nM117 caf\xe9\nG1 X3\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port)
    assert result.returncode == 2
    assert_one_clear_line(result.stderr, "job.gcode:4", "not ASCII")
    assert executed(log) == []  # the whole file is checked before the first line goes


def test_a_reset_mid_job_stops_and_names_the_last_acknowledged_line(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("".join(f"G1 X{i}\n" for i in range(30)) + "!!DEBUG:reset\nG1 X99\nG1 X100\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port)
    assert result.returncode == 4
    assert_one_clear_line(result.stderr, "reset", "job.gcode:", "the safe stop went once")
    # Nothing after, nothing again: then, greeted again, the safe stop it had missed.
    # The owed safe stop's M108 first (it ends a heat wait that would hold the stop up).
    assert executed(log) == [f"G1 X{i}" for i in range(30)] + ["M108", *MARLIN_SAFE_STOP]


@pytest.mark.slow
def test_a_controller_that_stops_answering_is_a_link_failure(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\nG1 X1\n!!DEBUG:hang\nG1 X2\nG1 X3\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(
            str(job), "--port", fake.port, "--reply-timeout", "1", "--reconnect-wait", "1"
        )
    # A hung controller takes no safe stop: the machine may not be safe (exit 5).
    assert result.returncode == 5
    assert_one_clear_line(result.stderr, "stopped answering", "job.gcode:2", "check the machine")


@pytest.mark.slow
def test_a_link_that_disappears_mid_job_is_a_link_failure(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("".join(f"G1 X{i}\n" for i in range(20)) + "!!DEBUG:link_drop 1\nG1 X99\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port)
    assert result.returncode == 3
    assert_one_clear_line(result.stderr, "lost", "job.gcode:", "the safe stop went once")
    # What reached the controller before the cable went ran once, in order; then, once it
    # was back, the safe stop (its M108 first: it ends a heat wait that would hold it up).
    sent = [f"G1 X{i}" for i in range(20)] + ["G1 X99"]
    done = executed(log)
    assert done[-len(MARLIN_SAFE_STOP) - 1 :] == ["M108", *MARLIN_SAFE_STOP]
    done = done[: -len(MARLIN_SAFE_STOP) - 1]
    assert len(done) >= 20 and done == sent[: len(done)]
