"""Time-lapse videos of a job's layer snapshots, made by ffmpeg where it is installed."""

from __future__ import annotations

import asyncio
import shutil
import tempfile
from pathlib import Path

from repetrel_host.session.camera import IMAGE_SUFFIXES

FRAME_RATE = 10  # images a second
MAKE_TIMEOUT = 300.0  # s: a video of thousands of layers takes a while on a small PC
NO_FFMPEG = (
    "ffmpeg is not installed on the server (apt install ffmpeg): the layer snapshots are "
    "kept, and a time-lapse video can be made of them once it is"
)


class CannotMake(Exception):
    """No video: why, and the HTTP status that says so."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


def ffmpeg() -> str | None:
    """ffmpeg's path, None when it is not installed."""
    return shutil.which("ffmpeg")


def videos(folder: Path) -> list[Path]:
    """The videos made, newest first."""
    if not folder.is_dir():
        return []
    return sorted(folder.glob("timelapse-job*.mp4"), key=lambda p: p.stat().st_mtime, reverse=True)


def layer_images(folder: Path, job: int) -> list[Path]:
    """Job ``job``'s layer snapshots, in the order they were taken (their names say)."""
    if not folder.is_dir():
        return []
    tag = f"-job{job}-layer"
    return sorted(p for p in folder.iterdir() if tag in p.name and p.suffix in IMAGE_SUFFIXES)


async def make(folder: Path, job: int) -> Path:
    """``folder/timelapse-job<job>.mp4`` made of the job's layer snapshots (H.264, even
    sizes, yuv420p: what every browser plays). :class:`CannotMake` without ffmpeg, without
    two snapshots, or when ffmpeg fails."""
    program = ffmpeg()
    if program is None:
        raise CannotMake(NO_FFMPEG, 501)
    images = layer_images(folder, job)
    if len(images) < 2:
        raise CannotMake(f"job {job} has {len(images)} layer snapshots: a video needs two", 409)
    target = folder / f"timelapse-job{job}.mp4"
    with tempfile.TemporaryDirectory() as work:
        listing = Path(work) / "images.txt"
        duration = 1 / FRAME_RATE
        listing.write_text(
            "".join(f"file '{p.as_posix()}'\nduration {duration}\n" for p in images)
            + f"file '{images[-1].as_posix()}'\n"  # the concat demuxer's last image
        )
        partial = Path(work) / target.name
        process = await asyncio.create_subprocess_exec(
            program,
            *("-y", "-loglevel", "error", "-f", "concat", "-safe", "0", "-i", str(listing)),
            *("-vf", "scale=trunc(iw/2)*2:trunc(ih/2)*2,format=yuv420p", "-r", str(FRAME_RATE)),
            *("-c:v", "libx264", "-movflags", "+faststart", str(partial)),
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        try:
            _, errors = await asyncio.wait_for(process.communicate(), MAKE_TIMEOUT)
        except TimeoutError:
            process.kill()
            await process.wait()
            raise CannotMake(f"ffmpeg took over {MAKE_TIMEOUT:.0f} s", 504) from None
        if process.returncode != 0 or not partial.is_file():
            said = errors.decode(errors="replace").strip().splitlines()
            raise CannotMake(f"ffmpeg failed: {said[-1] if said else process.returncode}", 502)
        shutil.move(partial, target)
    return target
