"""Hyrel jobs end to end: header, history, lint refusal, host codes, safe stop."""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from repetrel_host.config import shipped_config_dir
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.gcode.heaters import safe_stop_commands
from repetrel_host.session.planning import PRECHECK_LIMIT
from tests.support.helpers import EXAMPLE, executed, hyrel_send, job_commands, start_streaming
from tests.support.paths import SUPPORT

pytestmark = pytest.mark.timeout(60)

LOADOUTS = shipped_config_dir() / "loadouts"
TWO_HEADS = LOADOUTS / "wiki-two-heads.toml"


def dry_run(job: Path, loadout: Path) -> list[str]:
    result = hyrel_send(str(job), "--loadout", str(loadout), "--dry-run")
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


def test_loadout_job_runs_header_then_job_and_history_is_the_wire(tmp_path: Path) -> None:
    log, received, history = tmp_path / "fake.log", tmp_path / "wire.bin", tmp_path / "history"
    with BuiltInFake(log, ["--received", str(received)]) as fake:
        result = hyrel_send(
            str(EXAMPLE),
            "--port",
            fake.port,
            "--loadout",
            str(TWO_HEADS),
            "--history",
            str(history),
        )
    assert result.returncode == 0, result.stderr
    assert executed(log) == dry_run(EXAMPLE, TWO_HEADS)
    (history_file,) = history.glob("*-square-tube.gcode")
    # The job's stream, from its first line to the probes that confirmed its last, as the
    # fake received it after the session's greeting (M110 and a probe), M115 and M155.
    assert received.read_bytes().endswith(history_file.read_bytes())
    assert history_file.read_bytes().startswith(b"N4 M6 T1 O2 X0 Y0 Z0*114\n")
    assert str(history_file) in result.stdout


def test_a_tool_change_to_an_empty_slot_is_refused_unless_forced(tmp_path: Path) -> None:
    job = tmp_path / "two-tools.gcode"
    job.write_text("G28\nT1\nG1 X5\nT3 ; slot 4 is empty\nG1 X6\n")
    check = hyrel_send(str(job), "--check", "--loadout", str(TWO_HEADS))
    assert check.returncode == 2
    assert "two-tools.gcode:4: error: T3 selects yoke 1, slot 4" in check.stderr
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        refused = hyrel_send(str(job), "--port", fake.port, "--loadout", str(TWO_HEADS))
        assert refused.returncode == 2
        assert "two-tools.gcode:4" in refused.stderr and "--force" in refused.stderr
        assert executed(log) == []
        forced = hyrel_send(
            str(job), "--port", fake.port, "--loadout", str(TWO_HEADS), "--force", "--no-header"
        )
    assert forced.returncode == 0, forced.stderr
    assert executed(log) == ["G28", "T1", "G1 X5", "T3", "G1 X6"]
    ok = hyrel_send(str(EXAMPLE), "--check", "--loadout", str(LOADOUTS / "wiki-one-head.toml"))
    assert ok.returncode == 0
    assert "ok (0 findings)" in ok.stdout


def test_m0_pauses_with_its_message_and_resumes_on_enter(tmp_path: Path) -> None:
    job = tmp_path / "pause.gcode"
    job.write_text("G28\nG1 X1\nM0 ;Remove the part\nG1 X2\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        process = subprocess.Popen(
            [sys.executable, "-m", "repetrel_host.cli", str(job), "--port", fake.port],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert process.stdout is not None and process.stdin is not None
        seen = ""
        while "Paused" not in seen:
            line = process.stdout.readline()
            assert line, "hyrel-send ended without pausing"
            seen += line
        assert "Paused at pause.gcode:3: Remove the part" in seen
        time.sleep(0.3)
        # Paused after the machine finished what came before, and nothing after it sent.
        assert executed(log) == ["G28", "G1 X1", "M400"]
        process.stdin.write("\n")
        process.stdin.flush()
        stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 0, stderr
    assert "resumed" in stdout
    assert executed(log) == ["G28", "G1 X1", "M400", "G1 X2"]


def test_m0_without_an_operator_stops_safely(tmp_path: Path) -> None:
    job = tmp_path / "pause.gcode"
    job.write_text("G1 X1\nM0 ;Remove the part\nG1 X2\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port, "--machine", "hydra-16a")
    assert result.returncode == 2
    assert "pause.gcode:2: M0 waits for the operator, but standard input is closed" in result.stderr
    assert executed(log) == ["G1 X1", "G4 P1", *safe_stop_commands("v5")]


def test_m792_shell_is_refused_unless_allowed(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    job = tmp_path / "act.gcode"
    job.write_text(f"G1 X1\nM792 ; SHELL touch {marker} ; BEEP ; SAY done\nG1 X2\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        refused = hyrel_send(str(job), "--port", fake.port)
        assert refused.returncode == 0, refused.stderr
        assert "refused" in refused.stdout and "allow_shell = true under [host]" in refused.stdout
        assert "say (act.gcode:2): done" in refused.stdout
        assert not marker.exists()
        config = tmp_path / "config.toml"
        config.write_text("[host]\nallow_shell = true\n")
        allowed = hyrel_send(str(job), "--port", fake.port, "--config", str(config))
    assert allowed.returncode == 0, allowed.stderr
    assert marker.exists()
    assert executed(log) == ["G1 X1", "G1 X2", "G1 X1", "G1 X2"]


def test_m791_and_m790_take_snapshots_beside_the_stream(tmp_path: Path) -> None:
    camera = f"{sys.executable} {SUPPORT / 'fake_camera.py'}"
    job = tmp_path / "shots.gcode"
    layers = "".join(f"M790\nG1 Z{z}\nG1 X{z}\n" for z in range(1, 4))
    job.write_text(f"G28\n{layers}M791\nG1 X9\n")
    history = tmp_path / "history"
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        without = hyrel_send(str(job), "--port", fake.port, "--history", str(history))
        assert without.returncode == 0, without.stderr
        assert "no snapshot (shots.gcode:11): no camera is set" in without.stdout
        assert not list(history.glob("*-snapshots"))  # M790 alone takes none
        config = tmp_path / "config.toml"
        config.write_text(f'[host]\ncamera = "{camera} {{path}}"\nlayer_snapshots = true\n')
        taken = hyrel_send(
            str(job), "--port", fake.port, "--history", str(history), "--config", str(config)
        )
    assert taken.returncode == 0, taken.stderr
    (folder,) = history.glob("*-snapshots")
    images = sorted(p.name for p in folder.glob("*.png"))
    # A layer's unless the last was still being taken; M791's waits its turn.
    assert "0000002-layer1.png" in images and "0000011-layer3.png" in images
    assert all(f"snapshot: {folder / name}" in taken.stdout for name in images)
    # Neither code goes to the controller.
    assert executed(log) == 2 * [
        "G28",
        "G1 Z1",
        "G1 X1",
        "G1 Z2",
        "G1 X2",
        "G1 Z3",
        "G1 X3",
        "G1 X9",
    ]


def test_m719_logs_the_controllers_reports_until_m718(tmp_path: Path) -> None:
    job = tmp_path / "logged.gcode"
    job.write_text("M115\nM719 P10 S1\nM115\nM718\nM115\n")
    history = tmp_path / "history"
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(str(job), "--port", fake.port, "--history", str(history))
    assert result.returncode == 0, result.stderr
    (reports,) = history.glob("*-logged-reports.log")
    # One M115's answer: its name, then its capabilities.
    lines = reports.read_text().splitlines()
    assert len(lines) == 3 and lines[0].startswith("FIRMWARE_NAME:")
    assert lines[1:] == ["Cap:AUTOREPORT_TEMP:1", "Cap:EMERGENCY_PARSER:1"]


def test_ctrl_c_sends_the_machines_safe_stop(tmp_path: Path) -> None:
    job = tmp_path / "long.gcode"
    job.write_text("".join(f"G1 X{i % 100} Y{i % 7}\n" for i in range(20000)))
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--move-time", "0.002"]) as fake:
        process = start_streaming(job, fake.port, log, "--machine", "hydra-16a-v4")
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=30)
    assert process.returncode == 130, stderr
    done = executed(log)
    safe_stop = safe_stop_commands("v4")
    assert done[-len(safe_stop) :] == safe_stop
    assert done[: -len(safe_stop)] == job_commands(job)[: len(done) - len(safe_stop)]


def test_bad_config_is_one_sentence(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text("[host]\nallow_shel = true\n")
    result = hyrel_send(str(EXAMPLE), "--config", str(config), "--dry-run")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "host.allow_shel: unknown field" in result.stderr
    assert str(config) in result.stderr


def test_a_big_job_starts_at_once_and_is_checked_as_it_streams(tmp_path: Path) -> None:
    # Over the pre-check limit: the refused tool change at line 5 is found only when the
    # stream reaches it, so the lines before it run and nothing after it does.
    job = tmp_path / "big.gcode"
    filler = ("; " + "x" * 98 + "\n") * (PRECHECK_LIMIT // 100 + 10)
    job.write_text("G28\nT1\nG1 X5\nG1 X6\nT3 ; slot 4 is empty\nG1 X7\n" + filler)
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(
            str(job), "--port", fake.port, "--loadout", str(TWO_HEADS), "--no-header"
        )
    assert result.returncode == 2
    assert "checked as it streams" in result.stdout
    assert "big.gcode:5: error: T3 selects yoke 1, slot 4" in result.stderr
    assert executed(log)[:4] == ["G28", "T1", "G1 X5", "G1 X6"]
    assert "G1 X7" not in executed(log) and "T3" not in executed(log)


# Moves, a dwell, moves: the controller answers each M115 twice (its identity said again
# at once); a controller that did so once called such a job done during the dwell and
# resumed 48 lines past it.
DWELL_JOB = (
    [f"G1 X{i} F6000" for i in range(40)] + ["G4 P4000"] + [f"G1 Y{i} F6000" for i in range(48)]
)
SAYS_IT_TWICE = ["--protocol", "hyrel", "--move-time", "0.01", "--faults", "identity_twice=1"]


def job_lines(log: Path) -> list[str]:
    """What the fake ran of the job: its log without the host's M115s."""
    return [c for c in log.read_text().splitlines() if c != "M115"]


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_an_identity_said_twice_does_not_end_a_job_before_its_last_line_ran(
    tmp_path: Path,
) -> None:
    job = tmp_path / "dwell.gcode"
    job.write_text("".join(f"{line}\n" for line in DWELL_JOB))
    log = tmp_path / "fake.log"
    with BuiltInFake(log, SAYS_IT_TWICE) as fake:
        result = hyrel_send(
            str(job), "--port", fake.port, "--protocol", "hyrel", "--no-history", "--no-header"
        )
        ran = job_lines(log)  # when hyrel-send said done
    assert result.returncode == 0, result.stderr
    assert ran == DWELL_JOB  # every line, once, in order, before the job was called done


@pytest.mark.timeout(90)
@pytest.mark.slow
def test_a_link_cut_during_a_dwell_resumes_at_no_line_past_what_ran(tmp_path: Path) -> None:
    job = tmp_path / "dwell.gcode"
    job.write_text("".join(f"{line}\n" for line in DWELL_JOB))
    log = tmp_path / "fake.log"
    with BuiltInFake(log, SAYS_IT_TWICE, control=True) as fake:
        process = subprocess.Popen(
            [sys.executable, "-m", "repetrel_host.cli", str(job), "--port", fake.port,
             "--protocol", "hyrel", "--no-history", "--no-header"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 30
        while "G1 X39 F6000" not in job_lines(log) and time.monotonic() < deadline:
            time.sleep(0.02)
        ran = job_lines(log)  # the dwell began: what follows it has not run
        assert fake.request("link_drop 2")["ok"]
        stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 3, stderr
    assert ran == DWELL_JOB[: len(ran)] and len(ran) == 40
    prefix = "To resume from the first line not known to have run: "
    (hint,) = [line[len(prefix) :] for line in stdout.splitlines() if line.startswith(prefix)]
    line = int(shlex.split(hint)[-1])
    # Not past the dwell, the first line the controller had not run when the link went.
    assert line <= len(ran) + 1
    # The job's lines ran once each, in order; then only the safe stop.
    done = job_lines(log)
    run = next(i for i, (a, b) in enumerate(zip(done, DWELL_JOB, strict=False)) if a != b)
    assert run >= len(ran) and not [c for c in done[run:] if c in DWELL_JOB]
