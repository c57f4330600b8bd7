"""Camera snapshots for ``M790`` (new layer) and ``M791`` (snap image), as Repetrel takes them.

The camera is a command line from the configuration, run without a shell. ``{path}`` in it
is replaced by the file to write (``fswebcam --no-banner -r 1280x720 {path}``); without
it, the image is read from the command's standard output
(``ffmpeg -loglevel error -f v4l2 -i /dev/video0 -frames:v 1 -f image2 -``). The image is
kept as .jpg, .png, .gif or .webp, by what it holds.

A snapshot never holds the job up: it runs beside the stream, one at a time per camera (a
layer that comes while the last snapshot is still being taken gets none).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shlex
import signal
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger("repetrel_host.session.camera")

SNAPSHOT_TIMEOUT = 20.0
MAX_WAITING = 4  # snapshots asked for (M791) waiting behind the one being taken
IMAGE_SUFFIXES = (".jpg", ".png", ".gif", ".webp")
_MAGIC = (
    (b"\xff\xd8\xff", ".jpg"),
    (b"\x89PNG\r\n\x1a\n", ".png"),
    (b"GIF8", ".gif"),
)


class SnapshotFailed(Exception):
    """The camera command did not give an image; the message says why, in one sentence."""


def image_suffix(data: bytes) -> str | None:
    """.jpg, .png, .gif or .webp by the image's first bytes; None for anything else."""
    for magic, suffix in _MAGIC:
        if data.startswith(magic):
            return suffix
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return ".webp"
    return None


async def snapshot(command: str, target: Path, timeout: float = SNAPSHOT_TIMEOUT) -> Path:
    """Run the camera command for ``target`` (a name without its suffix); the image's path."""
    # Written aside under an image's name (ffmpeg picks its format by the name), then
    # moved into place: a folder of snapshots never holds half an image.
    partial = target.parent / ".taking" / f"{target.name}.jpg"
    argv = [word.replace("{path}", str(partial)) for word in shlex.split(command)]
    to_stdout = "{path}" not in command
    try:
        partial.parent.mkdir(parents=True, exist_ok=True)
        with partial.open("wb") if to_stdout else contextlib.nullcontext() as out:
            try:
                process = await asyncio.create_subprocess_exec(
                    *argv,
                    stdin=asyncio.subprocess.DEVNULL,
                    stdout=out if out is not None else asyncio.subprocess.DEVNULL,
                    stderr=asyncio.subprocess.PIPE,
                    start_new_session=True,  # a wrapper script's children are stopped too
                )
            except OSError as exc:
                raise SnapshotFailed(f"the camera command {argv[0]} cannot run: {exc}") from None
            try:
                _, errors = await asyncio.wait_for(process.communicate(), timeout)
            except (TimeoutError, asyncio.CancelledError) as exc:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                await process.wait()
                if isinstance(exc, asyncio.CancelledError):
                    raise
                raise SnapshotFailed(f"the camera command took over {timeout:g} s") from None
        if process.returncode != 0:
            said = errors.decode(errors="replace").strip().splitlines()
            why = f": {said[-1]}" if said else ""
            raise SnapshotFailed(f"the camera command failed (exit {process.returncode}){why}")
        try:
            with partial.open("rb") as image:
                head = image.read(16)
        except FileNotFoundError:
            raise SnapshotFailed("the camera command wrote no image at {path}") from None
        suffix = image_suffix(head)
        if suffix is None:
            what = "nothing" if not head else "no JPEG, PNG, GIF or WebP image"
            raise SnapshotFailed(f"the camera command gave {what}")
        final = target.with_name(target.name + suffix)
        partial.replace(final)
        return final
    except OSError as exc:  # a full disk, a folder that cannot be made
        raise SnapshotFailed(f"the snapshot cannot be kept in {target.parent}: {exc}") from None
    finally:
        partial.unlink(missing_ok=True)


class Camera:
    """A printer's camera: snapshots in the background, one at a time, the newest kept."""

    def __init__(
        self,
        command: str,
        folder: Path,
        keep: int = 500,
        on_taken: Callable[[Path], None] = lambda path: None,
        on_failed: Callable[[str], None] = lambda message: None,
    ) -> None:
        self.command = command
        self.folder = folder
        self.keep = keep
        self.on_taken = on_taken
        self.on_failed = on_failed
        self._tasks: list[asyncio.Task[Path | None]] = []  # taking, then those waiting

    @property
    def busy(self) -> bool:
        self._tasks = [task for task in self._tasks if not task.done()]
        return bool(self._tasks)

    def take(self, name: str, wait_turn: bool = False) -> bool:
        """Start a snapshot named ``name`` (no suffix) in the background. While one is being
        taken: False (none taken), unless ``wait_turn``: then it is taken after those before
        it (up to :data:`MAX_WAITING` of them; False beyond)."""
        if self.busy and (not wait_turn or len(self._tasks) > MAX_WAITING):
            return False
        self._queue(name, report=True)
        return True

    async def take_now(self, name: str) -> Path:
        """A snapshot, awaited (after those being taken); :class:`SnapshotFailed` says why not."""
        path = await self._queue(name, report=False)
        assert path is not None  # failures raise when not reported
        return path

    async def close(self, timeout: float = SNAPSHOT_TIMEOUT) -> None:
        """Wait up to ``timeout`` for the snapshots being taken and waiting, then give up."""
        if self.busy:
            await asyncio.wait(self._tasks, timeout=timeout)
            for task in self._tasks:
                task.cancel()
            await asyncio.wait(self._tasks)

    def _queue(self, name: str, report: bool) -> asyncio.Task[Path | None]:
        before = self._tasks[-1] if self._tasks else None
        task = asyncio.get_running_loop().create_task(self._take(name, before, report))
        self._tasks.append(task)
        return task

    async def _take(
        self, name: str, before: asyncio.Task[Path | None] | None, report: bool
    ) -> Path | None:
        if before is not None:
            await asyncio.wait([before])  # neither raises its error nor cancels it
        try:
            path = await snapshot(self.command, self.folder / name)
        except SnapshotFailed as exc:
            if not report:
                raise
            log.warning("%s", exc)
            self.on_failed(str(exc))
            return None
        self._taken(path)
        return path

    def _taken(self, path: Path) -> None:
        self._prune()
        self.on_taken(path)

    def images(self) -> list[Path]:
        """The snapshots kept, newest first (their names begin with the time they were taken)."""
        if not self.folder.is_dir():
            return []
        found = [p for p in self.folder.iterdir() if p.suffix in IMAGE_SUFFIXES]
        return sorted(found, key=lambda p: p.name, reverse=True)

    def _prune(self) -> None:
        for old in self.images()[self.keep :]:
            old.unlink(missing_ok=True)
