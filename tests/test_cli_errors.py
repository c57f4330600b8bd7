"""Bad input gets one clear sentence and a distinct exit code, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from repetrel_host.link import BuiltInFake
from tests.helpers import executed, hyrel_send

pytestmark = pytest.mark.timeout(60)


def assert_one_clear_line(stderr: str, *words: str) -> None:
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
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


def test_bad_flow_mode(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(str(job), "--flow", "sideways")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr


def test_non_ascii_line_stops_after_what_was_accepted(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_bytes(b"G28\nG1 X1\nG1 X2\nM117 caf\xe9\nG1 X3\n")
    log = tmp_path / "fake.log"
    with BuiltInFake(log) as fake:
        result = hyrel_send(str(job), "--port", fake.port)
    assert result.returncode == 2
    assert_one_clear_line(result.stderr, "job.gcode:4", "not ASCII")
    assert executed(log) == ["G28", "G1 X1", "G1 X2"]
