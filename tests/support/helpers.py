"""Shared helpers: the sample files, the job's commands, running hyrel-send for real."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine, Iterable
from pathlib import Path
from typing import Any

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session.job import Job
from tests.support.paths import DATA, ROOT

CONE = DATA / "cone-prusaslicer.gcode"
EXAMPLE = ROOT / "examples" / "square-tube.gcode"
# The safe stops a job ends with: Marlin's, and a Hyrel controller's (the reference's
# standard footer without its moves home, with v5's group addresses: every head T47, every
# bed T46).
MARLIN_SAFE_STOP = ["M107", "M104 S0", "M140 S0", "G91", "G0 Z10", "G90", "M84"]
HYREL_SAFE_STOP = [
    "M107 T47", "M620 T47 E0", "M104 T47 S0", "M140 T46 S0", "M5", "G91", "G0 Z10", "G90", "M84"
]  # fmt: skip


def job_commands(path: Path) -> list[str]:
    return [line.command for line in Job(path).lines()]


def executed(log: Path) -> list[str]:
    """The fake controller's log without the host's own lines (see :func:`without_greetings`)."""
    return without_greetings(log.read_text().splitlines())


def without_greetings(executed: Iterable[str]) -> list[str]:
    """Executed commands without the host's own lines: M110, the M115 a session asks right
    after it (who are you?) and the M155 that may follow (report temperatures), and M105:
    the host's probes are numbered M105 lines that run (a test that sends M105 itself
    reads the log whole)."""
    commands: list[str] = []
    after = ""  # the host's greeting line just before
    for command in executed:
        if command == "M105":
            continue
        if command.startswith("M110"):
            after = "M110"
        elif after == "M110" and command == "M115":
            after = "M115"
        elif after == "M115" and command.startswith("M155 S"):
            after = ""
        else:
            after = ""
            commands.append(command)
    return commands


def hyrel_send(
    *args: str, env: dict[str, str] | None = None, timeout: float = 90, input: str | None = None
) -> subprocess.CompletedProcess[str]:
    """Run hyrel-send as a real process, without a HYREL_PORT unless ``env`` gives one;
    ``input``: what its standard input reads (the console's lines), else nothing."""
    environment = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    environment.update(env or {})
    return subprocess.run(
        [sys.executable, "-m", "repetrel_host.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=environment,
        input=input,
        stdin=subprocess.DEVNULL if input is None else None,
    )


def start_streaming(job: Path, port: str, log: Path, *args: str) -> subprocess.Popen[str]:
    """Start hyrel-send in the background; return once the fake ``log`` shows progress."""
    process = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", str(job), "--port", port, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 2000):
        time.sleep(0.05)
    return process


def run_server_cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """hyrel-server as a real process that is expected to stop by itself (a refusal)."""
    return subprocess.run(
        [sys.executable, "-m", "repetrel_host.server.main", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


# Two hotends and a bed, as issue 35's reports heated them (with no EXTRUDER_COUNT said,
# so that the host learns T1 from the job alone).
TWO_HOTENDS = ["--extruders", "2", "--no-extruder-count"]


def heater_targets(fake: BuiltInFake) -> dict[str, float]:
    """Each heater's target on the fake, as it reports them itself (not the host's account)."""
    readings = fake.request("status")["temperatures"]
    return {name: float(target) for name, (_, target) in readings.items()}


def wait_for_log(log: Path, command: str, timeout: float = 20) -> None:
    """Until the fake has executed ``command`` (its log is flushed as it goes)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists() and command in log.read_text().splitlines():
            return
        time.sleep(0.02)
    raise AssertionError(f"{command} never ran: {log.read_text()[-2000:] if log.exists() else ''}")


def run(scenario: Callable[[], Coroutine[Any, Any, None]]) -> None:
    asyncio.run(scenario())


def job_file(tmp_path: Path, commands: list[str], name: str = "job.gcode") -> Path:
    path = tmp_path / name
    path.write_text("".join(f"{c}\n" for c in commands))
    return path
