"""The bad-input corpus: each case gets one clear sentence and its exit code, never a
traceback, and nothing is sent from a file that cannot be sent whole."""

from __future__ import annotations

import os
import pty
import shutil
import subprocess
import sys
import tempfile
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed, hyrel_send

pytestmark = pytest.mark.timeout(60)
BAD_INPUT, LINK_FAILURE = 2, 3


def one_sentence(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = [
        line
        for line in stderr.splitlines()
        if line.strip() and ": warning: " not in line and not line.startswith("connecting to ")
    ]
    assert len(lines) == 1, stderr
    return lines[0]


def send_file(tmp_path: Path, content: bytes) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    job = tmp_path / "job.gcode"
    job.write_bytes(content)
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port)
    return result, executed(log)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"G28\nM117 \xff\xfe hello\nG1 X1\n", ["job.gcode:2", "not ASCII"]),
        (b"G28\nG1 X1\x00\n", ["job.gcode:2", "control characters"]),
        (b"G28\nM117 " + b"x" * 10_000 + b"\n", ["job.gcode:2", "10005 characters", "at most 96"]),
        (b"G28\nG1 X1 * 2\n", ["job.gcode:2", "'*'"]),
        (b"", ["holds no G-code command"]),
        (b"; only comments\n\n", ["holds no G-code command"]),
    ],
    ids=["non-utf8", "nul", "10kB-line", "star", "empty", "comments-only"],
)
def test_a_file_that_cannot_be_sent_whole_sends_nothing(
    tmp_path: Path, content: bytes, words: list[str]
) -> None:
    result, done = send_file(tmp_path, content)
    assert result.returncode == BAD_INPUT
    sentence = one_sentence(result.stderr)
    for word in words:
        assert word in sentence
    assert done == []


def test_a_file_framed_by_another_host_is_renumbered(tmp_path: Path) -> None:
    content = b"N14 ; set line numbers for error logging\nN1 G28*18\nN2 G1 X1*99\nN3 M110 N0*12\n"
    result, done = send_file(tmp_path, content)
    assert result.returncode == 0, result.stderr
    assert done == ["G28", "G1 X1"]


@pytest.mark.parametrize("ending", [b"\r\n", b"\r"], ids=["crlf", "lone-cr"])
def test_line_endings(tmp_path: Path, ending: bytes) -> None:
    content = ending.join([b"G28", b"G1 X1 ; move", b"", b"G1 X2"]) + ending
    result, done = send_file(tmp_path, content)
    assert result.returncode == 0, result.stderr
    assert done == ["G28", "G1 X1", "G1 X2"]


def test_missing_file(tmp_path: Path) -> None:
    result = hyrel_send(str(tmp_path / "nope.gcode"))
    assert result.returncode == BAD_INPUT
    assert "no such file" in one_sentence(result.stderr)


def test_directory(tmp_path: Path) -> None:
    result = hyrel_send(str(tmp_path))
    assert result.returncode == BAD_INPUT
    assert "directory" in one_sentence(result.stderr)


def as_nobody(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run hyrel-send without root's right to read anything (tests run as root in CI)."""
    command = [sys.executable, "-m", "repetrel_host.cli", *args, "--no-history"]
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("needs setpriv to drop root's rights")
        command = [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups", *command]
    env = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    env |= {"HOME": str(cwd), "XDG_CONFIG_HOME": str(cwd), "XDG_DATA_HOME": str(cwd)}
    return subprocess.run(command, capture_output=True, text=True, timeout=30, cwd=cwd, env=env)


@pytest.fixture
def open_dir() -> Iterator[Path]:
    """A folder anyone may enter (pytest's own are root's alone)."""
    folder = Path(tempfile.mkdtemp(prefix="hyrel-test-"))
    folder.chmod(0o755)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_unreadable_file(open_dir: Path) -> None:
    job = open_dir / "secret.gcode"
    job.write_text("G28\n")
    job.chmod(0o000)
    result = as_nobody(str(job), "--dry-run", cwd=open_dir)
    assert result.returncode == BAD_INPUT
    assert "permission denied" in one_sentence(result.stderr)


def test_port_without_permission(open_dir: Path) -> None:
    job = open_dir / "job.gcode"
    job.write_text("G28\n")
    job.chmod(0o644)
    master, slave = pty.openpty()
    try:
        tty.setraw(slave)
        port = os.ttyname(slave)
        os.chmod(port, 0o600)
        result = as_nobody(str(job), "--port", port, cwd=open_dir)
    finally:
        os.close(master)
        os.close(slave)
    assert result.returncode == LINK_FAILURE
    assert "permission denied" in one_sentence(result.stderr)
