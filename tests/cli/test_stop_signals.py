"""SIGTERM, SIGHUP and SIGQUIT stop a run as Ctrl-C does (issues 35 and 48): hyrel-send and
its console send the safe stop (a second signal abandons it, and says so), whether a terminal
is left or not, and exit with 128 + the signal. Read at the fake: its heater targets and
executed log."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import pty
import signal
import subprocess
import sys
import termios
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import TWO_HOTENDS, executed, wait_for_log
from tests.support.helpers import heater_targets as targets
from tests.support.terminal import Screen

pytestmark = pytest.mark.timeout(90)
JOB = "M140 S60\nM104 T0 S200\nM104 T1 S210\nT1\n" + "".join(
    f"G1 X{i % 50} F600\n" for i in range(3000)
)
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}
SIGNALS = [signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT]


def fake_args(protocol: str, *more: str) -> list[str]:
    return ["--protocol", protocol, *TWO_HOTENDS, *more]


def on_a_terminal(*args: str, home: Path) -> tuple[subprocess.Popen[bytes], int]:
    """hyrel-send ARGS on a new pty that is its controlling terminal, so that closing the
    pty's main side sends it SIGHUP as a closed window does; the process and that side."""
    main, terminal = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    process = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", *args],
        stdin=terminal,
        stdout=terminal,
        stderr=terminal,
        env={**env, "HOME": str(home), "XDG_DATA_HOME": str(home / "data")},
        start_new_session=True,  # its own session, whose controlling terminal this is
        preexec_fn=lambda: fcntl.ioctl(0, termios.TIOCSCTTY, 0),
    )
    os.close(terminal)
    return process, main


def read_until(main: int, text: bytes) -> None:
    seen = b""
    while text not in seen:
        seen += os.read(main, 4096)


def sender(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: s.name)
def test_a_signal_stops_hyrel_send_with_its_safe_stop(
    tmp_path: Path, protocol: str, signum: signal.Signals
) -> None:
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    with BuiltInFake(log, fake_args(protocol, "--move-time", "0.01"), control=True) as fake:
        process = sender(str(job), "--port", fake.port, "--protocol", protocol, "--no-history")
        wait_for_log(log, "G1 X20 F600")
        process.send_signal(signum)
        stdout, stderr = process.communicate(timeout=60)
        heaters = targets(fake)
    assert process.returncode == 128 + signum, stdout + stderr
    assert f"{signum.name}: stopping: sending the safe-stop sequence" in stdout, stderr
    assert heaters == ALL_OFF
    done = [c for c in executed(log) if c != "M115"]
    assert done[-1] == "M84"


@pytest.mark.slow
def test_a_second_signal_abandons_the_safe_stop_and_says_so(tmp_path: Path) -> None:
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    slow = fake_args("reprap", "--move-time", "0.01", "--command-time", "0.5")
    with BuiltInFake(log, slow, control=True) as fake:
        process = sender(str(job), "--port", fake.port, "--no-history")
        wait_for_log(log, "G1 X20 F600")
        process.send_signal(signal.SIGTERM)
        wait_for_log(log, "M107")  # the safe stop is under way
        process.send_signal(signal.SIGHUP)
        stdout, stderr = process.communicate(timeout=60)
        heaters = targets(fake)
    assert process.returncode == 5, stdout + stderr
    said = " ".join((stdout + stderr).split())
    assert "the safe stop was abandoned before the controller confirmed" in said
    assert "heaters that may be on" in said
    assert heaters != ALL_OFF  # truly still on: what it said was true


def test_a_signal_before_streaming_begins_ends_it_with_one_sentence(tmp_path: Path) -> None:
    job = tmp_path / "two.gcode"
    job.write_text(JOB)
    # A port that never answers: the greeting waits (seconds) when the signal comes.
    with BuiltInFake(tmp_path / "fake.log", ["--identify-time", "30"]) as fake:
        process = sender(str(job), "--port", fake.port, "--no-history")
        time.sleep(1.5)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 143, stdout + stderr
    assert "Traceback" not in stderr
    assert stderr.strip().endswith("interrupted before streaming began.")


def test_a_closed_terminal_still_gets_the_safe_stop_and_the_history_says_how_it_ended(
    tmp_path: Path,
) -> None:
    """The terminal goes (its pty closed: the kernel sends SIGHUP); nothing can be written
    any more, but the safe stop goes and the run's record says how it ended."""
    job, log, history = tmp_path / "two.gcode", tmp_path / "fake.log", tmp_path / "history"
    job.write_text(JOB)
    more = ["--history", str(history)]
    with BuiltInFake(log, fake_args("reprap", "--move-time", "0.01"), control=True) as fake:
        process, main = on_a_terminal(str(job), "--port", fake.port, *more, home=tmp_path)
        try:
            read_until(main, b"Keys: p pauses")
            wait_for_log(log, "G1 X20 F600")
        finally:
            os.close(main)  # the terminal is gone: SIGHUP, and no more output
        status = process.wait(timeout=60)
        heaters = targets(fake)
    assert status == 129
    assert heaters == ALL_OFF
    (record,) = history.glob("*.json")
    assert json.loads(record.read_text())["outcome"] == "cancelled"


@pytest.mark.slow
def test_with_the_terminal_gone_an_abandoned_safe_stop_is_told_by_the_history_and_exit_5(
    tmp_path: Path,
) -> None:
    """No terminal to say it on: the run's record names what was not confirmed and the
    heaters that may be on, and the exit code says not safe."""
    job, log, history = tmp_path / "two.gcode", tmp_path / "fake.log", tmp_path / "history"
    job.write_text(JOB)
    slow = fake_args("reprap", "--move-time", "0.01", "--command-time", "0.5")
    with BuiltInFake(log, slow, control=True) as fake:
        process, main = on_a_terminal(
            str(job), "--port", fake.port, "--history", str(history), home=tmp_path
        )
        try:
            read_until(main, b"Keys: p pauses")
            wait_for_log(log, "G1 X20 F600")
        finally:
            os.close(main)  # SIGHUP: the safe stop begins
        wait_for_log(log, "M107")  # under way
        process.send_signal(signal.SIGTERM)
        status = process.wait(timeout=60)
        heaters = targets(fake)
    assert status == 5
    (record,) = [json.loads(path.read_text()) for path in history.glob("*.json")]
    assert record["outcome"] == "failed", record
    assert "the safe stop was abandoned before the controller confirmed" in record["error"]
    assert "heaters that may be on: bed at 60" in record["error"], record
    assert heaters != ALL_OFF  # truly still on: what it said was true


def console_printing(job: Path, port: str, *options: str) -> subprocess.Popen[str]:
    """``hyrel-send --console`` on ``port``, its input a pipe, told to print ``job``."""
    console = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", "--console", "--port", port, *options],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert console.stdin is not None
    console.stdin.write(f"!print {job}\n")
    console.stdin.flush()
    return console


@contextlib.contextmanager
def screen_printing(job: Path, port: str, home: Path) -> Iterator[Screen]:
    """The same at the interactive console, on a terminal of its own (closed after)."""
    screen = Screen("--console", "--port", port, home=home)
    try:
        screen.expect("Type G-code")
        screen.send(f"!print {job}\r")
        yield screen
    finally:
        screen.child.close(force=True)


@pytest.mark.parametrize(
    ("signum", "protocol"),
    [
        (signal.SIGTERM, "reprap"),
        (signal.SIGHUP, "reprap"),
        (signal.SIGTERM, "hyrel"),
        (signal.SIGQUIT, "reprap"),
        (signal.SIGQUIT, "hyrel"),
    ],
    ids=["SIGTERM-reprap", "SIGHUP-reprap", "SIGTERM-hyrel", "SIGQUIT-reprap", "SIGQUIT-hyrel"],
)
def test_a_signal_stops_the_consoles_job_with_its_safe_stop(
    tmp_path: Path, signum: signal.Signals, protocol: str
) -> None:
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    with BuiltInFake(log, fake_args(protocol, "--move-time", "0.01"), control=True) as fake:
        console = console_printing(job, fake.port, "--protocol", protocol)
        wait_for_log(log, "G1 X20 F600")
        console.send_signal(signum)
        stdout, stderr = console.communicate(timeout=60)
        heaters = targets(fake)
    assert console.returncode == 128 + signum, stdout + stderr
    assert f"{signum.name}: stopping: sending the safe-stop sequence" in stdout
    assert heaters == ALL_OFF


@pytest.mark.slow
def test_a_signal_at_the_interactive_console_stops_its_job_and_leaves(tmp_path: Path) -> None:
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    with BuiltInFake(log, fake_args("reprap", "--move-time", "0.01"), control=True) as fake:
        with screen_printing(job, fake.port, tmp_path) as screen:
            wait_for_log(log, "G1 X20 F600")
            screen.child.kill(signal.SIGTERM)
            status = screen.wait(timeout=60)
        heaters = targets(fake)
    assert status == 143, screen.text()[-2000:]
    assert "SIGTERM: stopping: sending the safe-stop sequence" in screen.text()
    assert heaters == ALL_OFF


@pytest.mark.slow
def test_a_second_signal_at_the_console_abandons_the_safe_stop_and_exits_5(
    tmp_path: Path,
) -> None:
    """As hyrel-send: the words name the heaters that may be on, and the exit code is not
    safe (5), not 143, which says the safe stop was confirmed."""
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    slow = fake_args("reprap", "--move-time", "0.01", "--command-time", "0.5")
    with BuiltInFake(log, slow, control=True) as fake:
        console = console_printing(job, fake.port)
        wait_for_log(log, "G1 X20 F600")
        console.send_signal(signal.SIGTERM)
        wait_for_log(log, "M107")  # the safe stop is under way
        console.send_signal(signal.SIGHUP)
        stdout, stderr = console.communicate(timeout=60)
        heaters = targets(fake)
    assert console.returncode == 5, stdout + stderr
    said = " ".join(stdout.split())
    assert "not safe: the safe stop was abandoned before the controller confirmed" in said
    assert "heaters that may be on: bed at 60" in said
    assert heaters != ALL_OFF


@pytest.mark.slow
def test_a_closed_terminal_at_the_interactive_console_stops_its_job_safely(
    tmp_path: Path,
) -> None:
    """The console's terminal goes (SIGHUP, and its prompt can no longer draw): the job's
    safe stop goes, the history says cancelled, and the exit code is 129, not a failure."""
    job, log, history = tmp_path / "two.gcode", tmp_path / "fake.log", tmp_path / "history"
    job.write_text(JOB)
    with BuiltInFake(log, fake_args("reprap", "--move-time", "0.01"), control=True) as fake:
        process, main = on_a_terminal(
            "--console", "--port", fake.port, "--history", str(history), home=tmp_path
        )
        try:
            read_until(main, b"Type G-code")
            os.write(main, f"!print {job}\r".encode())
            wait_for_log(log, "G1 X20 F600")
        finally:
            os.close(main)
        status = process.wait(timeout=60)
        heaters = targets(fake)
    assert status == 129
    assert heaters == ALL_OFF
    (record,) = history.glob("*.json")
    assert json.loads(record.read_text())["outcome"] == "cancelled"


@pytest.mark.parametrize("leave", ["!quit", "Ctrl-D"])
@pytest.mark.slow
def test_leaving_the_console_while_a_job_heats_turns_every_heater_off(
    tmp_path: Path, leave: str
) -> None:
    job, log = tmp_path / "two.gcode", tmp_path / "fake.log"
    job.write_text(JOB)
    with BuiltInFake(log, fake_args("reprap", "--move-time", "0.01"), control=True) as fake:
        with screen_printing(job, fake.port, tmp_path) as screen:
            wait_for_log(log, "G1 X20 F600")
            assert targets(fake) == {"T": 200.0, "T1": 210.0, "B": 60.0}
            screen.send("!quit\r" if leave == "!quit" else "\x04")
            status = screen.wait(timeout=60)
        heaters = targets(fake)
    assert status == 0, screen.text()[-2000:]
    assert "stopping two.gcode with the safe-stop sequence first" in screen.text()
    assert heaters == ALL_OFF
