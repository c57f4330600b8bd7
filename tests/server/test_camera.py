"""Camera snapshots (M791, M790): a real camera command run as a process."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

from repetrel_host.config import HostSettings
from repetrel_host.session.camera import (
    MAX_WAITING,
    Camera,
    SnapshotFailed,
    snapshot,
)
from tests.support.fake_camera import png
from tests.support.paths import SUPPORT

CAMERA = f"{sys.executable} {SUPPORT / 'fake_camera.py'}"

pytestmark = pytest.mark.timeout(30)


def files(folder: Path) -> list[str]:
    """What a folder of snapshots holds, the images being taken included."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def test_an_image_written_to_the_path_or_to_standard_output_is_kept(tmp_path: Path) -> None:
    to_path = asyncio.run(snapshot(f"{CAMERA} {{path}}", tmp_path / "a"))
    to_stdout = asyncio.run(snapshot(CAMERA, tmp_path / "b"))
    assert to_path == tmp_path / "a.png" and to_stdout == tmp_path / "b.png"
    assert to_path.read_bytes() == png() == to_stdout.read_bytes()
    assert files(tmp_path) == ["a.png", "b.png"]  # nothing half written left


@pytest.mark.parametrize(
    ("arguments", "timeout", "said"),
    [
        ("--fail", 10.0, "failed (exit 3): /dev/video0: No such device"),
        ("--text", 10.0, "gave no JPEG, PNG, GIF or WebP image"),
        ("--sleep 5", 0.5, "took over 0.5 s"),
    ],
)
def test_a_camera_that_fails_says_why_in_one_sentence_and_leaves_nothing(
    tmp_path: Path, arguments: str, timeout: float, said: str
) -> None:
    with pytest.raises(SnapshotFailed, match=said.replace("(", r"\(").replace(")", r"\)")):
        asyncio.run(snapshot(f"{CAMERA} {arguments} {{path}}", tmp_path / "x", timeout))
    assert files(tmp_path) == []


def test_a_missing_program_or_a_bad_command_line_is_said(tmp_path: Path) -> None:
    with pytest.raises(SnapshotFailed, match="no-such-camera cannot run"):
        asyncio.run(snapshot("no-such-camera {path}", tmp_path / "x"))
    for command, said in (('fswebcam "unclosed', "cannot be split"), ("  ", "empty")):
        with pytest.raises(ValidationError, match=said):
            HostSettings(camera=command)


def test_the_camera_takes_one_at_a_time_in_the_background_and_keeps_the_newest(
    tmp_path: Path,
) -> None:
    taken: list[str] = []
    failed: list[str] = []

    async def scenario() -> None:
        camera = Camera(
            f"{CAMERA} --sleep 0.3 {{path}}",
            tmp_path / "shots",
            keep=2,
            on_taken=lambda path: taken.append(path.name),
            on_failed=failed.append,
        )
        for number in range(3):
            assert camera.take(f"{number}-first")
            assert camera.busy and not camera.take(f"{number}-skipped")  # still taking
            await camera.close()
        assert not camera.busy
        await camera.take_now("3-now")

    asyncio.run(scenario())
    assert taken == ["0-first.png", "1-first.png", "2-first.png", "3-now.png"] and not failed
    kept = [p.name for p in Camera(CAMERA, tmp_path / "shots").images()]
    assert kept == ["3-now.png", "2-first.png"]  # newest first, two kept


def test_snapshots_asked_for_wait_their_turn_and_close_gives_up_all_the_rest(
    tmp_path: Path,
) -> None:
    async def scenario() -> list[str]:
        camera = Camera(f"{CAMERA} --sleep 0.4 {{path}}", tmp_path)
        assert camera.take("0")
        assert all(camera.take(f"{n}", wait_turn=True) for n in range(1, 1 + MAX_WAITING))
        assert not camera.take("late", wait_turn=True)  # enough are waiting
        await camera.close(0.6)
        assert not camera.busy
        return files(tmp_path)

    after_close = asyncio.run(scenario())
    time.sleep(1.0)  # a camera process left running would write its image meanwhile
    assert files(tmp_path) == after_close and len(after_close) <= 2
    assert all(name.endswith(".png") for name in after_close)  # nothing half written
