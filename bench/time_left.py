"""The time left against the real remainder (issue 37), on the fake controller whose moves
take their planned time (``--time-scale``, its own process on a pty, a 2 Mbaud link).

    python bench/time_left.py               # the cone's first 4 layers at x12, 3 runs each
    python bench/time_left.py --layers 10 --scale 10 --runs 1
    python bench/time_left.py --protocol hyrel    # on Hyrel's link (its 8 KB buffer)

Two printers: one that keeps to the plan (its pace, 1/scale, known from its past jobs), and
one 10 % slower than the plan whose pace is not known (the plan's assumed), then its next
job, which starts from the pace its first one taught it (its history's record). For each
run: the pace it starts from, the time left's error against the real remainder where the
job reached 10, 25, 50 and 75 % of its file, and the pace the run measured (paces x the
scale: 1.000 is the plan's). This measures the plumbing,
not the model: the fake's moves take the time the same planner gives them.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

import repetrel_host as rh
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.session.history import paces

CONE = Path(__file__).parent.parent / "tests" / "data" / "cone-prusaslicer.gcode"
SHARES = (0.1, 0.25, 0.5, 0.75)


def first_layers(folder: Path, layers: int) -> Path:
    """The cone's first ``layers`` layers (without its slicer's settings: both sides plan
    with Marlin's defaults)."""
    lines = CONE.read_text().splitlines()
    end = scan_marks(CONE).layers[layers].line - 1
    path = folder / "cone.gcode"
    path.write_text("\n".join(lines[:end]) + "\n")
    return path


async def run(
    job_file: Path, scale: float, prior: float, history: Path, protocol: str
) -> tuple[list, float, tuple[str, str]]:
    """The errors at :data:`SHARES`, the pace measured, and the printer (its port and
    machine profile, as its history knows it)."""
    fake = ["--time-scale", str(scale), "--protocol", protocol]
    connecting = rh.connect(
        "fake", baud=2_000_000, fake_args=fake, poll_interval=None, protocol=protocol
    )
    async with connecting as printer:
        job = await printer.print(job_file, history=history)
        await job.follow_time(prior, after=0.0)  # at once: the plumbing, not the start's CPU
        samples = []
        while not job.done:
            samples.append((job.offset / job.size, time.monotonic(), job.time_left()))
            await asyncio.sleep(0.02)
        await job.wait()
        await printer.command("M400")  # answered once every move the controller held ran
        end = time.monotonic()
    errors = []
    for share in SHARES:
        _, when, left = next(s for s in samples if s[0] >= share)
        errors.append(None if left is None else (left - (end - when)) / (end - when))
    measured = job.following.measured if job.following is not None else None
    return errors, (measured or 0.0), (job.printer.port, job.plan.profile.name or "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--layers", type=int, default=4)
    parser.add_argument("--scale", type=float, default=12.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--protocol", choices=["reprap", "hyrel"], default="reprap")
    args = parser.parse_args()
    scale = args.scale
    shares = " | ".join(f"{s:.0%}" for s in SHARES)
    print(f"| printer | run | pace it starts from | {shares} | pace measured |")
    print("|---|---|---|" + "---|" * len(SHARES) + "---|")

    def row(name: str, number: int, prior: float, errors: list, measured: float) -> None:
        cells = " | ".join("-" if e is None else f"{e:+.1%}" for e in errors)
        print(
            f"| {name} | {number} | {prior * scale:.3f} | {cells} | {measured * scale:.3f} |",
            flush=True,
        )

    with tempfile.TemporaryDirectory() as folder:
        job_file = first_layers(Path(folder), args.layers)
        for number in range(1, args.runs + 1):
            history = Path(folder) / "keeps" / f"20261204-10000{number}-cone.gcode"
            history.parent.mkdir(exist_ok=True)
            errors, measured, _ = asyncio.run(
                run(job_file, scale, 1 / scale, history, args.protocol)
            )
            row("keeps to the plan", number, 1 / scale, errors, measured)
        for number in range(1, args.runs + 1):
            runs = Path(folder) / f"slower-{number}"
            runs.mkdir()
            slower = scale / 1.1
            first = runs / "20261204-100000-cone.gcode"
            errors, measured, printer = asyncio.run(
                run(job_file, slower, 1 / scale, first, args.protocol)
            )
            row("10 % slower, pace unknown", number, 1 / scale, errors, measured)
            learned = learned_pace(paces(runs, *printer))  # from the first run's record
            second = runs / "20261204-110000-cone.gcode"
            errors, measured, _ = asyncio.run(run(job_file, slower, learned, second, args.protocol))
            row("10 % slower, its next job", number, learned, errors, measured)


if __name__ == "__main__":
    main()
