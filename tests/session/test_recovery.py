"""Resuming a failed print: the state the skipped lines leave, the preamble that restores it,
and hyrel-send's --from-line / --from-layer and resume hint, through real processes and ptys."""

from __future__ import annotations

import shlex
import signal
from pathlib import Path

import pytest

from repetrel_host.config import load_user_config
from repetrel_host.errors import UsageError
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.fakes.hyrel_simulator import RX_BUFFER
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.protocol.dialects.hyrel import SYNC_EVERY
from repetrel_host.session.job import Job, JobLine
from repetrel_host.session.machine_state import HomeAxes, MachineState, back_to_job, preamble, track
from repetrel_host.session.planning import JobRequest, plan_job, recovery_plan
from repetrel_host.session.recovery import recovery_command
from tests.support.helpers import (
    CONE,
    MARLIN_SAFE_STOP,
    executed,
    hyrel_send,
    job_commands,
    start_streaming,
)


def state_of(text: str) -> MachineState:
    lines = (line.split(";")[0].strip() for line in text.splitlines())
    return track((n, c) for n, c in enumerate(lines, start=1) if c)


def commands_of(lines: list[str]) -> list[str]:
    return [line.split(";")[0].strip() for line in lines]


# --- the state and the preamble -------------------------------------------------------


def test_temperatures_are_set_together_then_waited_for_before_any_move() -> None:
    state = state_of(
        "M140 S60\nM104 T12 S200\nM104 T11 S180\nM141 S40\nM190 S60\nM109 T12 S210\n"
        "M104 T100 S150 ; a Hyrel group: set, never waited for\nG1 Z0.3 F600\nG1 X5 Y5\n"
    )
    commands = [line.command for line in preamble(state)]
    sets = ["M141 S40", "M140 S60", "M104 T11 S180", "M104 T12 S210", "M104 T100 S150"]
    waits = ["M191 S40", "M190 S60", "M109 T11 S180", "M109 T12 S210"]
    assert commands[: len(sets) + len(waits)] == sets + waits
    assert "M109 T100 S150" not in commands
    first_move = next(i for i, c in enumerate(commands) if c.startswith(("G0", "G28")))
    assert first_move == len(sets) + len(waits) + 2  # after G21 and G90


def test_a_hotend_set_without_a_t_word_is_the_current_tools() -> None:
    # The preamble heats before it selects the tool: a bare M104 would heat another one.
    state = state_of("T1\nM104 S210\nM109 S210\nG1 Z0.3 F600\nT0\nM104 S190\n")
    commands = [line.command for line in preamble(state)]
    assert commands[:4] == ["M104 T0 S190", "M104 T1 S210", "M109 T0 S190", "M109 T1 S210"]


def test_a_heater_turned_off_is_not_restored() -> None:
    state = state_of("M104 S200\nM140 S60\nG1 Z1\nM140 S0\n")
    commands = [line.command for line in preamble(state)]
    assert "M104 S200" in commands and "M109 S200" in commands
    assert not [c for c in commands if c.startswith(("M140", "M190"))]


def test_the_moves_back_lift_home_xy_never_z_then_lower_and_set_e() -> None:
    state = state_of("G28\nG92 E0\nG1 Z0.2 F1200\nG1 X10 Y20 E1.5 F1800\nG1 Z0.6\nG1 X12 E2\n")
    commands = [line.command for line in preamble(state)]
    tail = commands[commands.index("G21") :]
    assert tail == [
        "G21",
        "G90",
        "G0 Z10.6 F600",  # above the highest Z of the part
        "G28 X0 Y0",
        "G0 X12 Y20 F3000",
        "G0 Z0.6 F600",
        "G92 E2",
        "M82",
        "G1 F1800",
    ]
    assert not [c for c in commands if c.startswith("G28") and "Z" in c]
    no_home = [line.command for line in preamble(state, HomeAxes.NONE)]
    assert not [c for c in no_home if c.startswith("G28")]


def test_relative_positioning_and_extrusion_are_followed_and_restored() -> None:
    state = state_of(
        "G90\nG1 X10 Y10 Z1\nG91\nG1 X2 Z0.5 E1\nG1 X2 E1\nG90\nM83\nG1 Y15 E0.7\nG91\n"
    )
    assert (state.x, state.y, state.z) == (14, 15, 1.5)
    assert not state.absolute and not state.absolute_e
    commands = [line.command for line in preamble(state)]
    assert not [c for c in commands if c.startswith("G92")]  # relative E: nothing to set
    assert commands[-2:] == ["G91", "M83"]  # no feed rate: the file gave none
    assert commands.index("G0 Z1.5 F600") < commands.index("G91")  # moves back absolute


def test_g92_and_homing_reset_what_is_known() -> None:
    state = state_of("G1 X5 Y5 Z5 E9\nG92 E0\nG28 X\n")
    assert (state.x, state.y, state.z, state.e) == (None, 5, 5, 0)
    assert state_of("G1 X5 E3\nG92\n").e == 0
    assert state_of("G1X5Y6Z0.3E0.5F900\n").feed == 900  # words written together


def test_fans_tool_and_factors_are_replayed_as_the_file_wrote_them() -> None:
    state = state_of(
        "M106 C255\nT1\nM106 T1 S128\nM106 T1 P200\nM106 P2 S100\nM106 S255\nM107\n"
        "M221 S95\nM220 S110\nM229 E1 D1\nT0\nM107 T1\nM106 T0 S50\nG1 Z1\nM221 S97\n"
    )
    commands = [line.command for line in preamble(state)]
    assert "T0" in commands and "T1" not in commands
    assert [c for c in commands if c.startswith(("M106", "M107"))] == [
        "M106 C255",  # Hyrel's range before any fan
        "M106 P2 S100",
        "M106 T0 S50",
    ]
    assert [c for c in commands if c.startswith(("M220", "M221", "M229"))] == [
        "M220 S110",
        "M229 E1 D1",
        "M221 S97",
    ]
    # The tool, factors and fans go before the moves back over the part.
    assert commands.index("T0") < commands.index("M106 T0 S50") < commands.index("G0 Z1 F600")


def test_inches_scale_the_preamble_feeds_and_lift() -> None:
    state = state_of("G20\nG1 X1 Y1 Z0.1 F40\n")
    commands = [line.command for line in preamble(state)]
    assert "G20" in commands and "G21" not in commands
    assert "G0 Z0.4937 F23.622" in commands  # 10 mm above, at 600 mm/min, in inches


def test_the_cone_at_a_late_layer() -> None:
    # By line 3000 the cone has heated (M104/M109 S200), gone absolute (G90, M82), reset E
    # (G92 E0 at every layer) and turned its fan on (M106 S242.25 at line 2656).
    job = Job(CONE)
    skipped = [(n, c) for n, c, _, _ in job.commands() if n < 3000]
    state = track(skipped)
    assert state.heaters[("hotend", None)].target == 200
    assert state.absolute and state.absolute_e
    last_z = [c for _, c in skipped if c.startswith("G1 Z")][-1]
    assert state.z == float(last_z.split()[1][1:])
    commands = [line.command for line in preamble(state)]
    assert commands[:2] == ["M104 S200", "M109 S200"]
    assert "M106 S242.25" in commands
    e_words = [w for _, c in skipped for w in c.split() if w.startswith("E")]
    assert f"G92 E{float(e_words[-1][1:]):g}" in commands or state.e == 0


# --- the resumed plan -------------------------------------------------------------------


def test_a_resumed_plan_sends_the_preamble_then_the_file_from_the_line(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("M104 S200\nG1 Z1 F600\n; a comment\n\nM0 ; a pause skipped\nG1 X1\nG1 X2\n")
    plan = plan_job(job, JobRequest(), load_user_config(None))
    resumed_plan = recovery_plan(plan, 3)  # a comment: the next command is the start
    assert resumed_plan.recovery is not None and resumed_plan.recovery.line == 5
    items = list(resumed_plan.items())
    preamble_lines = [i for i in items if isinstance(i, JobLine) and i.source == "resume"]
    assert [i.command for i in preamble_lines][:2] == ["M104 S200", "M109 S200"]
    assert all(i.index == 0 and i.source_line == 0 for i in preamble_lines)
    rest = items[len(preamble_lines) :]
    assert [(i.source_line, i.command) for i in rest if isinstance(i, JobLine)] == [
        (5, plan.job.pause_sync),  # the M0 on the resume line is the job's
        (6, "G1 X1"),
        (7, "G1 X2"),
    ]
    first = rest[0]
    assert isinstance(first, JobLine) and first.index == 1
    assert resumed_plan.recovery.start_offset == len("M104 S200\nG1 Z1 F600\n")
    with pytest.raises(UsageError, match="no command on line 8 or after it"):
        recovery_plan(plan, 8)
    with pytest.raises(UsageError, match="lines count from 1"):
        recovery_plan(plan, 0)


# --- hyrel-send ---------------------------------------------------------------------------


def layer_start(path: Path, layer: int) -> int:
    """The source line of the file's ``layer``-th ;LAYER_CHANGE, counted independently."""
    marks = [
        n for n, line in enumerate(path.read_text().splitlines(), 1) if line == ";LAYER_CHANGE"
    ]
    return marks[layer - 1]


def commands_from(path: Path, line: int) -> list[str]:
    return [c for n, c, _, _ in Job(path).commands() if n >= line]


@pytest.mark.timeout(60)
def test_dry_run_from_a_layer_shows_the_preamble_then_the_file_from_there() -> None:
    result = hyrel_send(str(CONE), "--dry-run", "--from-layer", "3")
    assert result.returncode == 0, result.stderr
    line = layer_start(CONE, 3)
    assert f"Resuming cone-prusaslicer.gcode at line {line + 3} (layer 3, asked: line {line})" in (
        result.stderr
    )
    out = result.stdout.splitlines()
    rest = commands_from(CONE, line)
    preamble_part, sent = out[: len(out) - len(rest)], commands_of(out[len(out) - len(rest) :])
    assert sent == rest
    assert all(" ; " in p for p in preamble_part)  # each with why it is there
    assert commands_of(preamble_part)[:2] == ["M104 S200", "M109 S200"]
    assert "G28 X0 Y0" in commands_of(preamble_part)
    assert preamble_part[-1].startswith("G1 F")


@pytest.mark.timeout(60)
def test_a_resumed_run_executes_the_preamble_then_exactly_the_lines_from_n(
    tmp_path: Path,
) -> None:
    job = tmp_path / "job.gcode"
    job.write_text(
        "M140 S60\nM104 S200\nM190 S60\nM109 S200\nG21\nG90\nM82\nG92 E0\n"
        "G1 Z0.2 F3000\nG1 X10 Y10 E1 F1500\nM106 S255\nG1 Z0.4\nG1 X20 Y10 E2.5\n"
        "G1 Z0.6\nG1 X20 Y20 E3\nM107\nG1 X10 Y20 E4\n"
    )
    log = tmp_path / "fake.log"
    result = hyrel_send(str(job), "--from-line", "14", "--fake-log", str(log), "--no-history")
    assert result.returncode == 0, result.stderr
    assert executed(log) == [
        "M140 S60",
        "M104 S200",
        "M190 S60",
        "M109 S200",
        "G21",
        "G90",
        "G0 Z10.4 F600",
        "G28 X0 Y0",
        "M106 S255",
        "G0 X20 Y10 F3000",
        "G0 Z0.4 F600",
        "G92 E2.5",
        "M82",
        "G1 F1500",
        *job_commands(job)[13:],
    ]


@pytest.mark.parametrize("args", [["--from-line", "3", "--from-layer", "2"]])
@pytest.mark.timeout(30)
def test_from_line_and_from_layer_together_are_refused(args: list[str]) -> None:
    result = hyrel_send(str(CONE), "--dry-run", *args)
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "error: --from-line and --from-layer both say where to resume: give one"
    )


@pytest.mark.timeout(30)
def test_bad_resume_points_are_one_sentence(tmp_path: Path) -> None:
    plain = tmp_path / "plain.gcode"
    plain.write_text("G28\nG1 X1\n; the end\n")
    cases = {
        ("--from-line", "4"): "error: plain.gcode has no command on line 4 or after it "
        "(its last command is on line 2)",
        ("--from-line", "0"): "error: lines count from 1: there is no line 0",
        ("--from-layer", "2"): "error: plain.gcode has no layer marks (;LAYER_CHANGE, "
        ";LAYER:, '; layer N', M790): give the line to resume from with --from-line",
    }
    for args, expected in cases.items():
        result = hyrel_send(str(plain), "--dry-run", *args)
        assert (result.returncode, result.stderr.strip()) == (2, expected)
    result = hyrel_send(str(CONE), "--dry-run", "--from-layer", "83")
    assert (result.returncode, result.stderr.strip()) == (
        2,
        "error: cone-prusaslicer.gcode has 82 layers: there is no layer 83",
    )


def numbered_job(path: Path, moves: int) -> list[str]:
    """A job whose every move is a different line, so that runs can be pieced together."""
    lines = ["M104 S200", "M109 S200", "G90", "M82", "G92 E0", "G1 Z0.3 F1200"]
    lines += [f"G1 X{i % 50} Y{i // 50} E{i / 10:g} F1800" for i in range(1, moves + 1)]
    path.write_text("\n".join(lines) + "\n")
    return lines


def two_runs(log: Path, first_line: str) -> tuple[list[str], list[str]]:
    """The fake's log cut where the second run's preamble begins (its ``first_line``), without
    the host's own lines (M110, M115: greetings and syncs; M155, M105: the status line's
    temperatures; the job has none)."""
    host_lines = ("M110", "M115", "M155", "M105")
    commands = [c for c in log.read_text().splitlines() if not c.startswith(host_lines)]
    cut = commands.index(first_line, 1)
    return commands[:cut], commands[cut:]


@pytest.mark.parametrize(
    ("protocol", "hint"),
    [("reprap", "not acknowledged"), ("hyrel", "not known to have run")],
)
@pytest.mark.timeout(120)
@pytest.mark.slow
def test_an_interrupted_job_names_the_command_that_resumes_it(
    tmp_path: Path, protocol: str, hint: str
) -> None:
    job = tmp_path / "part.gcode"
    lines = numbered_job(job, 400)
    log = tmp_path / "slow.log"
    with BuiltInFake(log, ["--move-time", "0.01", "--protocol", protocol]) as slow:
        args = ["--no-history", "--protocol", protocol]
        process = start_streaming(job, slow.port, log, *args)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
        assert process.returncode == 130, stderr
        prefix = f"To resume from the first line {hint}: "
        hints = [line for line in stdout.splitlines() if line.startswith(prefix)]
        assert len(hints) == 1, stdout
        command = shlex.split(hints[0][len(prefix) :])
        assert command[:2] == ["hyrel-send", str(job)]
        assert command[-2] == "--from-line"
        line = int(command[-1])
        # RepRap: the line after the last ok. Hyrel's link says what ran at its answers
        # (an M115 among the lines, an M-code's notice): here at least the M109's.
        assert (7 if protocol == "reprap" else 2) < line <= len(lines)
        again = hyrel_send(*command[1:])
        assert again.returncode == 0, again.stderr
    first, second = two_runs(log, "M104 S200")
    done = next(i for i, (a, b) in enumerate(zip(first, lines, strict=False)) if a != b)
    ran = first[:done]  # a part of the job, once each and in order
    assert not [c for c in first[done:] if c in lines[6:]]  # then only the safe stop
    if protocol == "reprap":
        assert first[done:] == MARLIN_SAFE_STOP
    resumed_part = second[len(second) - (len(lines) - line + 1) :]
    assert resumed_part == lines[line - 1 :]  # exactly from the hint's line on
    assert line - 1 <= len(ran)  # nothing skipped: the union covers the whole file
    repeated = len(ran) - (line - 1)
    # What runs twice is at most what was in flight when the stop came (RepRap: 8 lines), or
    # on Hyrel's link what ran since the last answer confirmed it (at most the lines between
    # two syncs and what the controller's 8 KB held).
    shortest = min(len(c) for c in lines)
    assert repeated <= (8 if protocol == "reprap" else SYNC_EVERY + RX_BUFFER // shortest)
    preamble_part = second[: len(second) - len(resumed_part)]
    assert preamble_part[:2] == ["M104 S200", "M109 S200"]
    assert "G28 X0 Y0" in preamble_part


@pytest.mark.timeout(30)
def test_a_completed_job_gives_no_resume_hint(tmp_path: Path) -> None:
    job = tmp_path / "part.gcode"
    numbered_job(job, 20)
    result = hyrel_send(str(job), "--no-history", "--from-line", "10")
    assert result.returncode == 0, result.stderr
    assert "To resume" not in result.stdout
    assert "Resuming part.gcode at line 10 (asked: line 10)" in result.stdout


def resume_hint(stdout: str) -> list[str]:
    prefix = "To resume from the first line not acknowledged: "
    return [shlex.split(line[len(prefix) :]) for line in stdout.splitlines() if prefix in line]


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_a_controller_error_or_link_failure_gives_the_resume_hint_too(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("".join(f"G1 X{i}\n" for i in range(30)) + "!!DEBUG:reset\nG1 X99\nG1 X100\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(str(job), "--port", fake.port, "--no-history")
        hang = tmp_path / "hang.gcode"
        hang.write_text("G28\nG1 X1\n!!DEBUG:hang\nG1 X2\n")
        silent = hyrel_send(
            str(hang), "--port", fake.port, "--reply-timeout", "1", "--reconnect-wait", "1"
        )
    assert result.returncode == 4, result.stderr
    (command,) = resume_hint(result.stdout)
    assert command[1:-2] == [str(job), "--port", fake.port, "--no-history"]
    assert command[-2:] == ["--from-line", "31"]  # after G1 X29, the last acknowledged
    assert result.stderr.splitlines()[-1].startswith("controller error:")  # as before
    assert silent.returncode == 5, silent.stderr  # hung: the safe stop could not go
    (command,) = resume_hint(silent.stdout)
    assert command[-2:] == ["--from-line", "3"]  # G1 X1, line 2, is the last acknowledged


@pytest.mark.timeout(30)
@pytest.mark.slow
def test_no_hint_when_nothing_of_the_job_was_acknowledged(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("!!DEBUG:hang\nG1 X2\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(
            str(job), "--port", fake.port, "--reply-timeout", "1", "--reconnect-wait", "1"
        )
    assert result.returncode == 5, result.stderr
    assert "To resume" not in result.stdout


def test_the_hint_replaces_an_earlier_resume_point() -> None:
    arguments = ("my part.gcode", "--from-layer", "3", "--port", "/dev/ttyUSB0", "--from-line=9")
    assert recovery_command(arguments, 1234) == (
        "hyrel-send 'my part.gcode' --port /dev/ttyUSB0 --from-line 1234"
    )


@pytest.mark.timeout(90)
def test_the_hint_also_offers_the_start_of_the_layer(tmp_path: Path) -> None:
    """After a reset the controller's queue is lost with the acknowledged lines in it: the
    start of the layer the stop came in is the resume that skips nothing."""
    log = tmp_path / "slow.log"
    with BuiltInFake(log, ["--move-time", "0.002"]) as slow:
        process = start_streaming(CONE, slow.port, log, "--no-history")
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    by_line = [x for x in stdout.splitlines() if x.startswith("To resume from the first")]
    by_layer = [x for x in stdout.splitlines() if x.startswith("Or from the start of its layer")]
    assert len(by_line) == 1 and len(by_layer) == 1, stdout
    line = int(shlex.split(by_line[0])[-1])
    command = shlex.split(by_layer[0].split(": ", 1)[1])
    assert command[:2] == ["hyrel-send", str(CONE)] and command[-2] == "--from-layer"
    layers = scan_marks(CONE).layers
    layer = layers[int(command[-1]) - 1]
    following = layers[layer.number].line if layer.number < len(layers) else 1 << 30
    assert layer.line <= line < following


def test_back_to_a_paused_job_homes_x_and_y_first_when_its_motors_were_off() -> None:
    state = track(
        [(1, "G90"), (2, "M83"), (3, "G1 Z0.4 F600"), (4, "G1 X10 Y20 E1 F1500"), (5, "T1")]
    )
    assert [line.command for line in back_to_job(state, True, True)] == [
        "G90",
        "G0 Z10.4 F600",
        "G28 X0 Y0",
        "T1",
        "G0 X10 Y20 F3000",
        "G0 Z0.4 F600",
        "M83",
        "G1 F1500",
    ]
    # Only a jog: back, in the file's modes, its tool left as it is (no T was sent).
    assert [line.command for line in back_to_job(state, False)] == [
        "G90",
        "G0 X10 Y20 F3000",
        "G0 Z0.4 F600",
        "M83",
        "G1 F1500",
    ]
