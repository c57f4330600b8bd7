"""What a newcomer meets at the command line: help, version, the profile chosen and why,
option mistakes, and Ctrl-C while the machine is moving."""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path

import pytest

from repetrel_host import __version__
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

pytestmark = pytest.mark.timeout(60)


def test_help_shows_plain_flags_and_the_true_defaults() -> None:
    result = hyrel_send("--help")
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    assert "<bool>" not in text
    assert "--check Only check the job" in text and "--framed With --dry-run" in text
    assert "[printer] port in the configuration" in text
    assert "--history DIR Folder for the print history (default" in text
    assert "~/.local/share/repetrel-host/history" in text


def test_version() -> None:
    result = hyrel_send("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == f"hyrel-send (repetrel-host) {__version__}"


def test_framed_without_a_dry_run_is_an_error(tmp_path: Path) -> None:
    result = hyrel_send(str(EXAMPLE), "--framed")
    assert result.returncode == 2
    assert result.stderr.strip() == "error: --framed shows the wire of a dry run: add --dry-run"


def test_a_mistyped_loadout_lists_the_known_ones() -> None:
    result = hyrel_send(str(EXAMPLE), "--loadout", "wiki-two-head", "--check")
    assert result.returncode == 2
    assert "no such loadout" in result.stderr
    assert "wiki-one-head, wiki-two-heads" in result.stderr


def test_check_names_the_profile_from_the_slicer(tmp_path: Path) -> None:
    # A PrusaSlicer file is written for a Marlin-style firmware: its safe stop must not
    # use Hyrel's group addresses.
    result = hyrel_send(str(CONE), "--check")
    assert result.returncode == 0, result.stderr
    assert "machine profile marlin (from the slicer: PrusaSlicer)" in result.stdout
    plain = tmp_path / "plain.gcode"
    plain.write_text("G28\nG1 X1\n")
    result = hyrel_send(str(plain), "--check")
    assert "machine profile hyrel (default: no machine given)" in result.stdout
    result = hyrel_send(str(plain), "--check", "--machine", "esr")
    assert "machine profile esr (--machine)" in result.stdout


@pytest.mark.timeout(60)
def test_check_names_the_print_time_from_the_moves_beside_the_slicers(tmp_path: Path) -> None:
    no_history = ("--history", str(tmp_path / "history"))  # no past job tells a pace
    result = hyrel_send(str(CONE), "--check", *no_history)
    assert result.returncode == 0, result.stderr
    # PrusaSlicer wrote 12m 33s; ours is from the moves, with its settings' limits, and its
    # M109 S200's wait (which a slicer does not count) apart.
    assert re.search(
        r"cone-prusaslicer.gcode: estimated time 13m \d\ds as planned \(12m 3\ds moving, "
        r"1m 2\ds heating\): no past job on port fake with the marlin profile tells its pace; "
        r"limits from the file's slicer settings; the slicer's: 12m 33s",
        result.stdout,
    ), result.stdout
    plain = tmp_path / "plain.gcode"
    plain.write_text("G28\nG1 X100 F600\n")  # 10 mm/s, below every jerk: 10 s flat
    result = hyrel_send(str(plain), "--check", *no_history)
    assert (
        "plain.gcode: estimated time 10s as planned (10s moving, 0.0s heating): no past job "
        "on port fake with the hyrel profile tells its pace; limits from Marlin's defaults\n"
    ) in result.stdout
    plain.write_text("M104 S200\n")
    result = hyrel_send(str(plain), "--check")
    assert "plain.gcode: no moves: no print time" in result.stdout


def test_the_profile_comes_from_the_firmware_and_is_named(tmp_path: Path) -> None:
    job = tmp_path / "plain.gcode"
    job.write_text("G28\nG1 X1\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(str(job), "--port", fake.port, "--no-history")
    assert result.returncode == 0, result.stderr
    expected = "Machine profile: marlin (from the firmware: repetrel-host fake controller"
    assert expected in result.stdout
    assert "machine profile marlin." in result.stdout  # in the summary too


def test_no_history_file_when_the_port_does_not_open(tmp_path: Path) -> None:
    history = tmp_path / "history"
    result = hyrel_send(
        str(EXAMPLE), "--port", str(tmp_path / "ttyUSB9"), "--history", str(history)
    )
    assert result.returncode == 3
    assert not history.exists() or not any(history.iterdir())


def test_a_second_ctrl_c_says_what_the_safe_stop_did_not_confirm(tmp_path: Path) -> None:
    log = tmp_path / "slow.log"
    # 20 ms a move and a 16-block planner: the safe stop waits a third of a second
    # behind the moves already planned.
    with BuiltInFake(log, ["--move-time", "0.02"]) as slow:
        process = start_streaming(CONE, slow.port, log, "--no-history")
        process.send_signal(signal.SIGINT)
        time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 5, stderr  # not safe: the safe stop was not confirmed
    assert "stopping: sending the safe-stop sequence (Ctrl-C again to abandon it)" in stdout
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("not safe: the safe stop was abandoned before the controller confirmed")
    assert "M107" in last and "check the machine" in last
    # What ran is a part of the job, once and in order, then what the controller took of
    # the safe stop before it was abandoned.
    done, commands = executed(log), job_commands(CONE)
    assert any(
        done[: len(done) - j] == commands[: len(done) - j]
        and done[len(done) - j :] == MARLIN_SAFE_STOP[:j]
        for j in range(len(MARLIN_SAFE_STOP) + 1)
    ), done[-10:]


def test_a_dry_run_says_which_machine_profile_it_used(tmp_path: Path) -> None:
    job = tmp_path / "part.gcode"
    job.write_text("; generated by PrusaSlicer 2.8.1\nG28\nG1 X10 F3000\n")
    result = hyrel_send(str(job), "--dry-run")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-2:] == ["G28", "G1 X10 F3000"]
    assert result.stderr.strip() == (
        "part.gcode: a dry run, nothing sent; machine profile marlin (from the slicer: "
        "PrusaSlicer), reprap protocol"
    )


def test_output_that_is_not_a_terminal_ends_at_100_percent_with_the_slicers_estimate(
    tmp_path: Path,
) -> None:
    job = tmp_path / "part.gcode"
    moves = "".join(f"G1 X{i % 100} Y{i % 7} F3000\n" for i in range(300))
    footer = "".join(f"; setting_{i} = {i}\n" for i in range(400))  # PrusaSlicer's footer
    job.write_text(
        "; generated by PrusaSlicer 2.8.1\nG28\n" + moves
        + "; estimated printing time (normal mode) = 1h 2m 5s\n" + footer
    )  # fmt: skip
    result = hyrel_send(str(job))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    bar = next(line for line in lines if line.startswith("part.gcode ━"))
    assert " 100% 301 lines " in bar and "left" not in bar
    # Beside the real duration, the plan's figure (where it was made in time) and the slicer's.
    assert re.search(
        r"part.gcode: done: 301 lines in [\d.]+s \((planned [\d.]+s; )?the slicer's "
        r"1h 02m 05s\), \d+ lines/s, .*; machine profile marlin\.",
        result.stdout,
    ), result.stdout
