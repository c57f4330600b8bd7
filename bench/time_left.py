"""The time left against the real remainder (issues 37 and 51), from a job's first second, on
the fake controller whose moves take their planned time (``--time-scale``, its own process on
a pty, a 2 Mbaud link) and whose hotend heats at the rate the plan gives it (scaled alike).

    python bench/time_left.py                     # both links, 4 layers at x4, 1 run each
    python bench/time_left.py --protocol hyrel --runs 3
    python bench/time_left.py --slower 1.0 --heater 0.8   # a hotend 20 % slower than planned
    python bench/time_left.py --quick             # 2 layers at x16, about a minute (a test)

The job: the cone's first layers (its M104/M109 heat-up to 200 degrees at the start) and the
slicer's closing comments (its estimate and settings; without its ``machine_max_*`` lines,
which the fake cannot be given, so both sides plan with Marlin's defaults). One printer whose
moves are ``--slower`` than the plan (1.1: 10 % slower): its first job, never seen (the plan's
pace, 1.0), then its next, which starts from the pace its first taught it (``learned_pace``
over its history's records, as hyrel-send reads them). Each job starts as hyrel-send starts
one on a terminal (``follow_time`` at once), with hyrel-send's temperature polls, and
``time_left()`` is read every 0.1 s while it runs.

Columns: the error of the time left against the real remainder (until the controller's last
move ended) at 1 s into the job and at shares of its real duration (by time: what a person
watching sees); a None at one of them is a failure there. The largest rise (the most the time
left went up from any earlier figure, in seconds; 0: it never rose), the largest gap to the
real countdown (seconds), the figures that were None while the job ran, and the paces
(actual over planned moving time, times the scale: 1.000 is the plan's).
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import repetrel_host as rh
from repetrel_host.config import UserConfig, shipped_config_dir
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.gcode.estimate import DEFAULT_LIMITS
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.session.history import paces
from repetrel_host.session.workers import in_worker, stop_workers

CONE = Path(__file__).parent.parent / "tests" / "data" / "cone-prusaslicer.gcode"
FIRST = 1.0  # seconds into the job: the first figure a person reads
SHARES = (0.05, 0.1, 0.25, 0.5, 0.75, 0.9)  # of the job's real duration
SAMPLE = 0.1  # seconds between readings of the time left
TEMPERATURE_POLL = 2.0  # hyrel-send's (cli/send.py)
HEATERS = ("hotend", "bed", "chamber")


def cone_job(folder: Path, layers: int) -> Path:
    """The cone's first ``layers`` layers, then its slicer's closing comments (without the
    machine limits the fake cannot take)."""
    lines = CONE.read_text().splitlines()
    end = scan_marks(CONE).layers[layers].line - 1
    closing = next(i for i, line in enumerate(lines) if line.startswith("; filament used"))
    comments = [line for line in lines[closing:] if not line.startswith("; machine_max_")]
    path = folder / "cone.gcode"
    path.write_text("\n".join(lines[:end] + comments) + "\n")
    return path


def scaled_heaters(scale: float) -> UserConfig:
    """The shipped Marlin and Hyrel profiles, their heaters ``scale`` times as fast as the
    plan's defaults (so that a heat wait takes its planned time over ``scale``, as a move)."""
    shipped = tomllib.loads((shipped_config_dir() / "machines.toml").read_text())
    rates = {kind: DEFAULT_LIMITS.heat_rates[kind] * scale for kind in HEATERS}
    limits = {"source": f"the bench: heaters x{scale:g}", "heat_rates": rates}
    machines = {name: {**shipped[name], "limits": limits} for name in ("marlin", "hyrel")}
    return UserConfig(machines=machines)


@dataclass
class Reading:
    """What the job said ``seconds`` into it: its time left (None: not known), the share
    of its file acknowledged, the pace its time left took (None: not planned yet)."""

    seconds: float
    left: float | None
    share: float
    pace: float | None


@dataclass
class Run:
    """One job's readings, its real duration, the pace it started from and the one it
    measured, and its printer as its history knows it (port, machine)."""

    readings: list[Reading]
    duration: float
    prior: float
    measured: float
    printer: tuple[str, str]

    def error(self, at: float) -> float | None:
        """The time left's error at ``at`` seconds in (the first reading there or after),
        over the real remainder; None when the time left was."""
        reading = next(r for r in self.readings if r.seconds >= at)
        remainder = self.duration - reading.seconds
        return None if reading.left is None else (reading.left - remainder) / remainder

    @property
    def rise(self) -> float:
        """The most the time left rose over any earlier figure (seconds)."""
        lowest, rise = float("inf"), 0.0
        for reading in self.readings:
            if reading.left is not None:
                rise = max(rise, reading.left - lowest)
                lowest = min(lowest, reading.left)
        return rise

    @property
    def gap(self) -> float:
        """The largest gap between the time left and the real remainder (seconds)."""
        gaps = [
            abs(r.left - (self.duration - r.seconds)) for r in self.readings if r.left is not None
        ]
        return max(gaps, default=0.0)

    @property
    def missing(self) -> list[float]:
        """When the time left was None while the job ran (seconds in)."""
        return [r.seconds for r in self.readings if r.left is None]

    def write(self, path: Path, scale: float) -> None:
        """The readings as CSV: seconds in, the time left, the real remainder, the file's
        share acknowledged, the pace (x scale)."""
        rows = ["seconds,time_left,remainder,file_share,pace"]
        for r in self.readings:
            left = "" if r.left is None else f"{r.left:.2f}"
            pace = "" if r.pace is None else f"{r.pace * scale:.3f}"
            rows.append(
                f"{r.seconds:.2f},{left},{self.duration - r.seconds:.2f},{r.share:.4f},{pace}"
            )
        path.write_text("\n".join(rows) + "\n")


async def run(
    job_file: Path, fake: list[str], config: UserConfig, prior: float, history: Path, link: str
) -> Run:
    connecting = rh.connect(
        "fake",
        baud=2_000_000,
        fake_args=[*fake, "--protocol", link],
        protocol=link,
        config=config,
        poll_interval=TEMPERATURE_POLL,
        poll_while_printing=True,
    )
    async with connecting as printer:
        job = await printer.print(job_file, history=history)
        start = time.monotonic()
        # As hyrel-send starts it when its status line shows: planned at once.
        following = asyncio.ensure_future(job.follow_time(prior, in_worker, after=0.0))
        readings: list[Reading] = []
        while not job.done:
            left = job.time_left()
            pace = job.following.pace if job.following is not None else None
            seconds = time.monotonic() - start
            readings.append(Reading(seconds, left, job.offset / job.size, pace))
            await asyncio.sleep(SAMPLE)
        await job.wait()
        await printer.command("M400")  # answered once every move the controller held ran
        duration = time.monotonic() - start
        await following
    printed_on = (job.printer.port, job.plan.profile.name or "")
    return Run(readings, duration, prior, job.pace or 0.0, printed_on)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--layers", type=int, default=4)
    parser.add_argument("--scale", type=float, default=4.0, help="the fake's speed-up")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--protocol", choices=["reprap", "hyrel"], action="append")
    parser.add_argument(
        "--slower", type=float, default=1.1, help="the printer's moves against the plan's"
    )
    parser.add_argument(
        "--heater", type=float, default=1.0, help="its hotend's rate against the plan's"
    )
    parser.add_argument("--trace", type=Path, help="each job's readings as CSV in this folder")
    parser.add_argument("--quick", action="store_true", help="2 layers at x16, 1 run")
    args = parser.parse_args()
    if args.quick:
        args.layers, args.scale, args.runs = 2, 16.0, 1
    scale, links = args.scale, args.protocol or ["reprap", "hyrel"]
    config = scaled_heaters(scale)
    heat_rate = DEFAULT_LIMITS.heat_rates["hotend"] * scale * args.heater
    fake = ["--time-scale", str(scale / args.slower), "--heat-rate", str(heat_rate)]
    points = ["1 s", *(f"{share:.0%}" for share in SHARES)]
    print(
        f"| link | job | pace it starts from | {' | '.join(points)} | largest rise s "
        "| largest gap s | None | pace measured |"
    )
    print("|---|---|---|" + "---|" * len(points) + "---|---|---|---|")

    def row(link: str, name: str, number: int, job: Run) -> None:
        at = [FIRST, *(share * job.duration for share in SHARES)]
        errors = [job.error(when) for when in at]
        cells = " | ".join("None" if e is None else f"{e:+.1%}" for e in errors)
        print(
            f"| {link} | {name} | {job.prior * scale:.3f} | {cells} | {job.rise:.1f} "
            f"| {job.gap:.1f} | {len(job.missing)} | {job.measured * scale:.3f} |",
            flush=True,
        )
        if args.trace is not None:
            args.trace.mkdir(parents=True, exist_ok=True)
            job.write(args.trace / f"{link}-{name.split(':')[0]}-{number}.csv", scale)
        if job.missing:
            print(f"  None at {', '.join(f'{when:.1f} s' for when in job.missing)}")

    with tempfile.TemporaryDirectory() as folder:
        job_file = cone_job(Path(folder), args.layers)
        for link in links:
            for number in range(1, args.runs + 1):
                runs = Path(folder) / f"{link}-{number}"
                runs.mkdir()
                first = runs / "20261210-100000-cone.gcode"
                never_seen = asyncio.run(run(job_file, fake, config, 1 / scale, first, link))
                row(link, "first: never seen", number, never_seen)
                # Its first's record, as hyrel-send reads it (in the plan's paces: x scale).
                known = paces(runs, *never_seen.printer)
                learned = learned_pace(pace * scale for pace in known) / scale
                second = runs / "20261210-110000-cone.gcode"
                with_history = asyncio.run(run(job_file, fake, config, learned, second, link))
                row(link, "next: its history", number, with_history)
    stop_workers()


if __name__ == "__main__":
    main()
