"""The built-in fake as users meet it: how fast it runs and how to get a slower one (in
hyrel-send's --help), every setting's default in hyrel-fake-controller's --help, and no
temporary log left behind unless one was asked for, nor its pty's folder."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.helpers import EXAMPLE, executed, hyrel_send, job_commands
from tests.support.server import wait_for

pytestmark = pytest.mark.timeout(60)


def test_hyrel_send_help_says_how_fast_the_fake_is_and_how_to_slow_it() -> None:
    result = hyrel_send("--help")
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    assert "built-in fake controller, which runs every command at once" in text
    assert "as fast as --baud (115200: 11.5 KB/s each way) with 1 ms latency" in text
    assert (
        'hyrel-fake-controller --move-time 0.01 --faults "drop_ok=0.01" --link /tmp/printer &'
        in result.stdout  # on one line, to copy
    )
    assert "hyrel-send JOB --port /tmp/printer" in result.stdout
    assert "'auto' for the only port that looks like a Hyrel or Marlin board" in text
    assert "--list-ports List the serial ports" in text
    assert "--history-list Show the newest 20 prints" in text
    assert "--fake-log FILE Where the built-in fake writes the commands it executed " in text


def test_fake_controller_help_shows_every_default() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "repetrel_host.fakes.fake_controller", "--help"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    options = result.stdout.split("options:", 1)[1]
    blocks: dict[str, str] = {}
    for line in options.splitlines():
        if line.startswith("  -"):
            name = line.split()[0].rstrip(",")
            blocks[name] = " ".join(line.split())
        elif line.strip():
            blocks[name] += " " + line.strip()
    del blocks["-h"]
    assert len(blocks) == 28  # every option of build_parser
    missing = [name for name, block in blocks.items() if "(default" not in block]
    assert missing == []
    assert "--move-time SECONDS time a move takes (default: 0, at once)" in blocks["--move-time"]
    assert "(default: 4)" in blocks["--slots"] and "(default: off)" in blocks["--advanced-ok"]
    assert "(default: reprap)" in blocks["--protocol"]


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_builtin_fake_leaves_no_temporary_log(tmp_path: Path) -> None:
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    env = {"TMPDIR": str(temporary)}
    result = hyrel_send(str(EXAMPLE), "--no-history", env=env)
    assert result.returncode == 0, result.stderr
    assert "streaming to the built-in fake controller" in result.stdout
    assert "The fake controller's log" not in result.stdout
    assert list(temporary.iterdir()) == []  # neither a hyrel-fake-*.log nor its pty folder
    # Asked for, the log is the user's: kept, and said.
    log = tmp_path / "executed.log"
    result = hyrel_send(str(EXAMPLE), "--no-history", "--fake-log", str(log), env=env)
    assert result.returncode == 0, result.stderr
    assert f"The fake controller's log of executed commands: {log}" in result.stdout
    assert executed(log) == job_commands(EXAMPLE)
    assert list(temporary.iterdir()) == []


def test_the_builtin_fakes_pty_folder_goes_when_whoever_started_it_is_killed(
    tmp_path: Path,
) -> None:
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    starter = (
        "import time\n"
        "from repetrel_host.fakes.fake_controller import BuiltInFake\n"
        "print(BuiltInFake(control=True).start(), flush=True)\n"
        "time.sleep(60)\n"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", starter],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "TMPDIR": str(temporary)},
    )
    assert process.stdout is not None
    port = Path(process.stdout.readline().strip())
    assert port.parent.parent == temporary and port.is_symlink()
    process.kill()  # a server or hyrel-send killed with kill -9 never stops its fake
    process.wait()
    process.stdout.close()
    wait_for(lambda: not any(temporary.iterdir()), timeout=10, what="the fake's folder gone")


def test_a_fake_whose_starter_is_gone_before_it_is_ready_leaves_nothing(tmp_path: Path) -> None:
    folder = tmp_path / "own"
    folder.mkdir()
    command = [sys.executable, "-m", "repetrel_host.fakes.fake_controller", "--control"]
    process = subprocess.Popen(
        [*command, "--link", str(folder / "tty"), "--own-link-folder"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None and process.stdin is not None
    process.stdout.close()  # killed while the fake started: nobody reads its 'ready'
    process.stdin.close()
    assert process.wait(timeout=30) == 0
    assert process.stderr is not None and process.stderr.read() == ""
    assert not folder.exists()
