"""hyrel-send at a terminal while a job streams: the status line, time left, the p key, an
M0 answered with Enter, Ctrl-C - all through a real pseudo-terminal."""

from __future__ import annotations

import re
import shlex
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pexpect
import pytest

from repetrel_host.gcode.analysis import scan_marks
from tests.support.helpers import CONE, MARLIN_SAFE_STOP, executed, job_commands
from tests.support.terminal import Screen


@pytest.fixture
def screens() -> Iterator[list[Screen]]:
    opened: list[Screen] = []
    yield opened
    for screen in opened:
        screen.close()


def first_layers(tmp_path: Path, layers: int = 3) -> Path:
    """The cone's first ``layers`` (a few seconds on the built-in fake), with
    PrusaSlicer's M73 progress after each layer's Z."""
    out, layer = [], 0
    end = scan_marks(CONE).layers[layers].line - 1
    for line in CONE.read_text().splitlines()[:end]:
        out.append(line)
        if line.startswith(";Z:"):
            out.append(f"M73 P{layer * 30} R{9 - layer * 3}")
            layer += 1
    path = tmp_path / "layers.gcode"
    path.write_text("\n".join([*out, "M104 S0", ""]))
    return path


def settled(log: Path) -> int:
    """The lines in ``log`` once it stopped growing for a third of a second."""
    before = -1
    while (now := len(log.read_text().splitlines())) != before:
        before = now
        time.sleep(0.33)
    return now


@pytest.mark.timeout(90)
@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_the_status_line_and_p_pausing_and_resuming(
    tmp_path: Path, screens: list, protocol: str
) -> None:
    job, log = first_layers(tmp_path), tmp_path / "fake.log"
    options = ("--fake-log", str(log), "--no-history", "--protocol", protocol)
    screen = Screen(str(job), *options, home=tmp_path)
    screens.append(screen)
    screen.expect("Keys: p pauses and resumes; Ctrl-C stops the job safely.")
    # Layer and Z as the slicer marked them, M73's percent, the temperatures heard.
    screen.expect(r"layer 2/3 · Z 0\.65 · 30 % \(M73\) · T \d+\.\d/200")
    # The plan's time left and the end (no figure but the plan's: "estimating" before it).
    screen.expect(r"\ds left, ends \d\d:\d\d")
    screen.send("p")
    screen.expect("pausing: the controller finishes what it was sent")
    paused = screen.expect(r"Paused at layers\.gcode:(\d+) - press p to resume")
    # Nothing more runs while paused (the built-in fake of Hyrel's link runs what its
    # receive buffer held before the hold byte, as it reads the bytes in order).
    ran = settled(log)
    time.sleep(1)
    assert len(log.read_text().splitlines()) == ran
    assert int(paused.group(1)) < len(job.read_text().splitlines())
    screen.send("p")
    screen.expect("resumed")
    screen.expect(r"layers\.gcode: done: \d+ lines")
    assert screen.wait() == 0
    # Hyrel's link: its syncs (M115) and temperature polls (M105) are the host's.
    done = [c for c in executed(log) if protocol == "reprap" or c not in ("M115", "M105")]
    assert done == job_commands(job)  # each line once, the pause in between


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_time_left_is_the_plans_or_estimating_never_a_stand_in(
    tmp_path: Path, screens: list
) -> None:
    """A file without slicer marks: no rate's figure before the plan's (one rose 35 times
    over while a printer heated), and the plan's from the first seconds."""
    job = tmp_path / "plain.gcode"
    job.write_text("".join(f"G1 X{i % 100} Y{i % 7}\n" for i in range(8000)))
    screen = Screen(str(job), "--no-history", home=tmp_path)
    screens.append(screen)
    screen.expect(r"\d+ lines/s (estimating|\S+ left, ends \d\d:\d\d)")
    screen.expect(r"\d+ lines/s \S+ left, ends")
    assert "layer" not in screen.text() and "*time left" not in screen.text()
    # Every time left shown came with its end: the plan's (a rate's figure had none).
    assert not re.search(r"\ds left(?!, ends)", screen.text()), screen.text()[-2000:]
    screen.send("\x03")  # Ctrl-C: the safe stop, as without a terminal
    screen.expect("stopping: sending the safe-stop sequence")
    assert screen.wait() == 130


@pytest.mark.timeout(60)
def test_an_m0_waits_for_enter_at_the_terminal(tmp_path: Path, screens: list) -> None:
    job, log = tmp_path / "m0.gcode", tmp_path / "fake.log"
    job.write_text("G28\nM0 ; look at the bed\nG1 X10\n")
    screen = Screen(str(job), "--fake-log", str(log), "--no-history", home=tmp_path)
    screens.append(screen)
    screen.expect(r"Paused at m0\.gcode:2: look at the bed - press Enter to resume")
    time.sleep(0.5)
    assert "G1 X10" not in log.read_text()
    screen.send("\r")
    screen.expect("resumed")
    assert screen.wait() == 0
    assert executed(log) == job_commands(job)


@pytest.mark.timeout(90)
@pytest.mark.slow
def test_ctrl_c_at_the_terminal_sends_the_safe_stop(tmp_path: Path, screens: list) -> None:
    log = tmp_path / "fake.log"
    screen = Screen(str(CONE), "--fake-log", str(log), "--no-history", home=tmp_path)
    screens.append(screen)
    screen.expect("layer 2/82")
    screen.send("\x03")
    screen.expect(r"stopping: sending the safe-stop sequence \(Ctrl-C again to abandon it\)")
    screen.expect(r"stopped \(interrupted; the last line the controller acknowledged")
    assert screen.wait() == 130
    done = executed(log)
    assert done[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    assert done[: -len(MARLIN_SAFE_STOP)] == job_commands(CONE)[: len(done) - 7]


@pytest.mark.timeout(60)
def test_in_the_background_it_leaves_the_terminal_alone(tmp_path: Path) -> None:
    """``hyrel-send JOB &`` at a shell with job control: a change to the terminal's modes
    from a background job would stop it (SIGTTOU), so no keys there, and it streams on."""
    job = tmp_path / "small.gcode"
    job.write_text("G28\nG1 X10\nG1 Y10\n")
    python = shlex.quote(sys.executable)
    script = f"set -m; {python} -m repetrel_host.cli {job} --no-history & wait $!"
    child = pexpect.spawn("bash", ["-c", script], cwd=str(tmp_path), encoding="utf-8")
    try:
        child.expect(pexpect.EOF, timeout=40)
    finally:
        child.close(force=True)
    assert child.exitstatus == 0, child.before
    assert "small.gcode: done: 3 lines" in child.before
    assert "Keys:" not in child.before
