"""A ``hyrel-send`` or console run killed (``kill -9``) with heaters on leaves its safe stop
owed to the next run on that port, which sends it first and says why (issue 48); a run that
ended cleanly leaves nothing owed. Read at the fake: its heater targets and executed log."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import TWO_HOTENDS, executed, hyrel_send, wait_for_log
from tests.support.helpers import heater_targets as targets

pytestmark = pytest.mark.timeout(120)
HEATING = "M140 S60\nM104 T0 S200\nM104 T1 S210\nT1\n"
MOVES = "".join(f"G1 X{i % 50} F600\n" for i in range(3000))
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}
OWED = "ended without its safe stop"


def killed_mid_job(fake: BuiltInFake, tmp_path: Path, protocol: str, console: bool) -> None:
    """hyrel-send (or its console's !print) streaming a heated job, killed with -9."""
    job = tmp_path / "two.gcode"
    job.write_text(HEATING + MOVES)
    args = ["--port", fake.port, "--protocol", protocol]
    args = ["--console", *args] if console else [str(job), *args]
    process = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert process.stdin is not None
    if console:
        process.stdin.write(f"!print {job}\n")
        process.stdin.flush()
    wait_for_log(fake.log_path, "G1 X20 F600")
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=10)
    assert targets(fake) == {"T": 200.0, "T1": 210.0, "B": 60.0}  # nobody turned them off


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("killed", ["hyrel-send", "console"])
@pytest.mark.slow
def test_the_next_run_on_the_port_sends_the_safe_stop_a_killed_run_owed(
    tmp_path: Path, protocol: str, killed: str
) -> None:
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--protocol", protocol, *TWO_HOTENDS], control=True) as fake:
        killed_mid_job(fake, tmp_path, protocol, killed == "console")
        before = len(executed(log))
        after_job = tmp_path / "after.gcode"
        after_job.write_text("G1 X77 F600\n")
        done = hyrel_send(str(after_job), "--port", fake.port, "--protocol", protocol)
        assert done.returncode == 0, done.stdout + done.stderr
        assert OWED in done.stderr and "hotend T1 at 210" in done.stderr, done.stderr
        assert targets(fake) == ALL_OFF
        ran = executed(log)[before:]
        # Its safe stop went before the new job's line, once.
        offs = [i for i, line in enumerate(ran) if line.startswith("M140") and line.endswith("S0")]
        assert len(offs) == 1 and offs[0] < ran.index("G1 X77 F600"), ran
        again = hyrel_send(str(after_job), "--port", fake.port, "--protocol", protocol)
        assert again.returncode == 0 and OWED not in again.stderr  # owed once only


def test_a_console_after_a_killed_run_turns_the_heaters_off_before_its_first_command(
    tmp_path: Path,
) -> None:
    log = tmp_path / "fake.log"
    with BuiltInFake(log, TWO_HOTENDS, control=True) as fake:
        killed_mid_job(fake, tmp_path, "reprap", console=False)
        console = hyrel_send("--console", "--port", fake.port, input="G1 X66 F600\n", timeout=60)
        assert console.returncode == 0, console.stdout + console.stderr
        assert OWED in console.stderr
        assert targets(fake) == ALL_OFF
        ran = executed(log)
        assert ran.index("M104 T1 S0") < ran.index("G1 X66 F600")


@pytest.mark.slow
def test_a_run_that_ended_cleanly_or_left_a_heater_on_by_request_owes_nothing(
    tmp_path: Path,
) -> None:
    log = tmp_path / "fake.log"
    with BuiltInFake(log, TWO_HOTENDS, control=True) as fake:
        job = tmp_path / "hot.gcode"
        job.write_text(HEATING + "G1 X5 F600\n")
        assert hyrel_send(str(job), "--port", fake.port).returncode == 0
        # A heater left on at the console, on purpose.
        console = hyrel_send("--console", "--port", fake.port, input="M104 T0 S180\n", timeout=60)
        assert console.returncode == 0, console.stderr
        assert targets(fake)["T"] == 180.0
        after = tmp_path / "after.gcode"
        after.write_text("G1 X9 F600\n")
        done = hyrel_send(str(after), "--port", fake.port)
        assert done.returncode == 0 and OWED not in done.stderr, done.stderr
        assert targets(fake)["T"] == 180.0  # left as the user left it
