"""Streaming speed against a peer: one command, one table.

    python bench/run.py             # the figures in bench/README.md (about 6 minutes)
    python bench/run.py --quick     # a small input, to check that the bench runs

For each link profile the fake controller (``hyrel-fake-controller``, a real pty)
emulates the link, and each host streams the same slicer file to it in turn:
repetrel-host buffered and unbuffered (``hyrel-send``, run in-process by
bench/peer.py), repetrel-host on Hyrel's own link (the fake speaking it too, with its
8 KB buffer) and Printrun's printcore (``pip install --no-deps printrun``).
Then ``hyrel-send`` streams a generated job of ``--big-gb`` GB for a few seconds:
when did its first job line reach the controller, and what was its peak RSS?

The columns are explained in bench/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONE = ROOT / "tests" / "data" / "cone-prusaslicer.gcode"
PEER = Path(__file__).resolve().parent / "peer.py"
OK_BYTES = 3  # "ok\n"


@dataclass(frozen=True)
class Profile:
    name: str
    bandwidth: float  # bytes/s each way
    latency: float  # seconds each way
    overflow: str  # drop (UART) or block (USB back-pressure)
    rx_buffer: int
    lines: int  # job lines streamed on this profile (the link's speed sets the run time)
    options: tuple[str, ...] = ()  # hyrel-send options for buffered mode on this link
    fake_options: tuple[str, ...] = ()
    hosts: tuple[str, ...] = ("ours-buffered",)  # with fake_options: the hosts compared


PROFILES = (
    Profile("uart", 11_520, 0.002, "drop", 128, 3_000),
    Profile("uart+advanced_ok", 11_520, 0.002, "drop", 128, 3_000, (), ("--advanced-ok",)),
    # The link pushes back, so no byte can be lost: the host may keep more in flight
    # than the controller's 128 bytes, enough to cover the round trip.
    Profile(
        "usb", 1_000_000, 0.001, "block", 128, 20_066, ("--rx-buffer", "4096", "--max-lines", "96")
    ),
    # Marlin's planner full of moves that take their planned time (a twentieth of it): a
    # controller silent for as long as its moves run, as a printer is.
    Profile(
        "uart+planner",
        11_520,
        0.002,
        "drop",
        128,
        3_000,
        (),
        ("--time-scale", "20"),
        ("ours-buffered", "ours-unbuffered", "printcore"),
    ),
)


@dataclass
class Result:
    host: str  # ours-buffered, ours-unbuffered, printcore, ideal
    profile: Profile
    lines: int
    seconds: float
    job_bytes: int  # received between the first and the last job command
    cpu_seconds: float
    peak_rss_bytes: int
    dropped: int
    starved: float
    exact: bool
    errors: int  # error lines the controller answered (a healthy link draws none)

    @property
    def rate(self) -> float:
        return self.lines / self.seconds if self.seconds > 0 else 0.0

    @property
    def wire_share(self) -> float:
        return self.job_bytes / self.seconds / self.profile.bandwidth

    def round_trip_share(self) -> float:
        """lines/s against 1 / round trip of one mean line and its ok."""
        line_bytes = self.job_bytes / max(self.lines - 1, 1)
        profile = self.profile
        round_trip = 2 * profile.latency + (line_bytes + OK_BYTES) / profile.bandwidth
        return self.rate * round_trip


def job_file(lines: int, folder: Path) -> tuple[Path, list[str]]:
    """The first ``lines`` commands of the cone file (comments kept), and those commands."""
    from repetrel_host.session.job import Job

    commands: list[str] = []
    last_line = 0
    for number, command, _, _ in Job(CONE).commands():
        if len(commands) == lines:
            break
        commands.append(command)
        last_line = number
    path = folder / f"cone-{lines}.gcode"
    path.write_text("".join(CONE.read_text().splitlines(keepends=True)[:last_line]))
    return path, commands


# Hyrel's own link: the fake speaks it, with its 8 KB buffer (ACKs while 2 KB are free).
HYREL_FAKE = ("--protocol", "hyrel", "--rx-buffer", "8192")


def start_fake(
    profile: Profile, folder: Path, tag: str, extra: tuple[str, ...] = ()
) -> tuple[subprocess.Popen[str], str]:
    stats, log = folder / f"{tag}.json", folder / f"{tag}.log"
    command = [
        sys.executable,
        "-m",
        "repetrel_host.fakes.fake_controller",
        "--bandwidth",
        str(profile.bandwidth),
        "--latency",
        str(profile.latency),
        "--overflow",
        profile.overflow,
        "--rx-buffer",
        str(profile.rx_buffer),
        "--stats",
        str(stats),
        "--log",
        str(log),
        *profile.fake_options,
        *extra,  # after the profile's: the last --rx-buffer given counts
    ]
    fake = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    assert fake.stdout is not None
    ready = fake.stdout.readline().split()
    if len(ready) != 2 or ready[0] != "ready":
        raise SystemExit("bench: the fake controller did not start")
    return fake, ready[1]


def stop_fake(fake: subprocess.Popen[str]) -> None:
    fake.send_signal(signal.SIGTERM)
    fake.wait(timeout=10)


def run_host(
    host: str,
    profile: Profile,
    job: Path,
    commands: list[str],
    folder: Path,
    history: bool = False,
    host_path: str | None = None,
) -> Result:
    tag = f"{profile.name}-{host}"
    fake, port = start_fake(profile, folder, tag, HYREL_FAKE if host == "ours-hyrel" else ())
    try:
        if host in ("printcore", "ideal"):
            argv = [sys.executable, str(PEER), host, port, str(job)]
        elif host == "ours-hyrel":  # the window: the headroom, or as buffered's on usb
            options = ["--protocol", "hyrel", *profile.options]
            argv = [sys.executable, str(PEER), "ours", port, str(job), *options]
        else:
            flow = host.removeprefix("ours-")
            options = list(profile.options) if flow == "buffered" else []
            argv = [sys.executable, str(PEER), "ours", port, str(job), "--flow", flow, *options]
        if history and host.startswith("ours"):  # the stream kept, as hyrel-send does by default
            argv += ["--history", str(folder / f"history-{tag}")]
        env = dict(os.environ)
        if host_path:  # the host from another tree; the fake stays this one's
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [host_path, env.get("PYTHONPATH")]))
        done = subprocess.run(argv, capture_output=True, text=True, timeout=3600, env=env)
    finally:
        stop_fake(fake)
    report_line = [line for line in done.stdout.splitlines() if line.startswith("PEER ")]
    if done.returncode != 0 or not report_line:
        raise SystemExit(f"bench: {tag} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    report = json.loads(report_line[-1].removeprefix("PEER "))
    stats = json.loads((folder / f"{tag}.json").read_text())
    executed = (folder / f"{tag}.log").read_text().splitlines()
    # Greetings are not the job: our M110 and M115 (and Hyrel's link's M115s, which
    # confirm what ran), the M155 asking for temperature reports (or M105 polls) for the
    # status line, printcore's M110 N-1 and the M105 it connects with.
    host_lines = ("M110", "M105", "M115", "M155")
    job_executed = [c for c in executed if not c.startswith(host_lines)]
    job_commands = [c for c in commands if not c.startswith("M105")]
    return Result(
        host=host,
        profile=profile,
        lines=len(commands),
        seconds=stats["last_command_at"] - stats["first_job_command_at"],
        job_bytes=stats["bytes_at_last_command"] - stats["bytes_at_first_job_command"],
        cpu_seconds=report["cpu_seconds"],
        peak_rss_bytes=report["peak_rss_bytes"],
        dropped=stats["bytes_dropped"],
        starved=stats["starved"],
        exact=job_executed == job_commands,
        errors=stats["errors"],
    )


def big_job(size: int, folder: Path) -> Path:
    """A job of ``size`` bytes: the cone file's text repeated."""
    path = folder / "big.gcode"
    block = CONE.read_bytes()
    with path.open("wb") as handle:
        for _ in range(size // len(block) + 1):
            handle.write(block)
    return path


def run_big(size: int, seconds: float, trials: int, folder: Path) -> dict[str, float]:
    """Start hyrel-send on a big job and stop it after ``seconds``, ``trials`` times:
    the median time to its first job line, and the highest peak RSS."""
    profile = PROFILES[-1]
    job = big_job(size, folder)
    hyrel_send = Path(sys.executable).parent / "hyrel-send"
    command = [str(hyrel_send), str(job), "--no-history", "--no-header", *profile.options]
    first_lines, greetings, peaks, streamed = [], [], [], []
    for _ in range(trials):
        fake, port = start_fake(profile, folder, "big")
        try:
            launched = time.monotonic()
            sender = subprocess.Popen(
                [*command, "--port", port],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )
            time.sleep(seconds)
            sender.send_signal(signal.SIGINT)  # Ctrl-C: the safe stop, then exit
            _, status, usage = os.wait4(sender.pid, 0)
            sender.returncode = os.waitstatus_to_exitcode(status)
        finally:
            stop_fake(fake)
        stats = json.loads((folder / "big.json").read_text())
        if stats["first_job_command_at"] is None or sender.returncode != 130:
            raise SystemExit(f"bench: the big job did not stream (exit {sender.returncode})")
        first_lines.append(stats["first_job_command_at"] - launched)
        greetings.append(stats["first_command_at"] - launched)
        peaks.append(usage.ru_maxrss * 1024)
        streamed.append(stats["commands"])
    job.unlink()
    return {
        "size": size,
        "first_line": statistics.median(first_lines),
        "first_line_max": max(first_lines),
        "greeting": statistics.median(greetings),
        "peak_rss_bytes": max(peaks),
        "lines": min(streamed),
        "seconds": seconds,
        "trials": trials,
    }


def print_table(results: list[Result]) -> None:
    peers = {r.profile.name: r for r in results if r.host == "printcore"}
    unbuffered = {r.profile.name: r for r in results if r.host == "ours-unbuffered"}
    header = (
        "| host | link | lines | lines/s | % of wire | % of 1/RTT | CPU µs/line | peak RSS MB "
        "| x printcore | x unbuffered | dropped B | starved s | errors /10k lines | exactly once |"
    )
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for r in results:
        peer = peers.get(r.profile.name)
        slow = unbuffered.get(r.profile.name)
        versus_peer = f"{r.rate / peer.rate:.1f}" if peer and r is not peer else "-"
        versus_slow = f"{r.rate / slow.rate:.1f}" if slow and r.host == "ours-buffered" else "-"
        print(
            f"| {r.host} | {r.profile.name} | {r.lines} | {r.rate:,.0f} | "
            f"{100 * r.wire_share:.1f} | {100 * r.round_trip_share():.1f} | "
            f"{1e6 * r.cpu_seconds / r.lines:.1f} | {r.peak_rss_bytes / 2**20:.0f} | "
            f"{versus_peer} | {versus_slow} | {r.dropped} | {r.starved:.2f} | "
            f"{r.errors * 10_000 / r.lines:.1f} | {'yes' if r.exact else 'NO'} |"
        )


def print_big(big: dict[str, float]) -> None:
    print(
        f"\nbig job: {big['size'] / 1e9:.2f} GB, {big['trials']:.0f} starts: first job line on "
        f"the wire {big['first_line']:.3f} s after hyrel-send started (median; at most "
        f"{big['first_line_max']:.3f} s; its greeting M110 at {big['greeting']:.3f} s); "
        f"peak RSS {big['peak_rss_bytes'] / 2**20:.0f} MB after streaming at least "
        f"{big['lines']:,} lines in {big['seconds']:.0f} s, then Ctrl-C"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small inputs: checks the bench runs")
    parser.add_argument("--big-gb", type=float, default=1.0, help="size of the generated job")
    parser.add_argument("--big-seconds", type=float, default=3.0, help="how long it streams")
    parser.add_argument("--profile", action="append", help="only these link profiles")
    parser.add_argument("--host", action="append", help="only these hosts")
    parser.add_argument("--no-big", action="store_true", help="skip the big job")
    parser.add_argument(
        "--history",
        action="store_true",
        help="our hosts keep the print history (the stream and its records), as hyrel-send "
        "does by default; without it they run with --no-history",
    )
    parser.add_argument(
        "--host-path",
        metavar="DIR",
        help="run our hosts from the package in DIR (another tree's src/), against this "
        "tree's fake: a before-and-after on the same controller",
    )
    args = parser.parse_args()
    try:
        import printrun.printcore  # noqa: F401
    except ImportError:
        raise SystemExit("bench: printcore is missing: pip install --no-deps printrun") from None
    print(
        f"# {platform.node()}: {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M')}"
    )
    results: list[Result] = []
    with tempfile.TemporaryDirectory(prefix="repetrel-bench-") as name:
        folder = Path(name)
        for profile in PROFILES:
            if args.profile and profile.name not in args.profile:
                continue
            lines = min(profile.lines, 300 if args.quick else profile.lines)
            job, commands = job_file(lines, folder)
            hosts = list(profile.hosts)
            if not profile.fake_options:
                hosts += ["ours-unbuffered", "ours-hyrel", "printcore", "ideal"]
            for host in hosts:
                if args.host and host not in args.host:
                    continue
                results.append(
                    run_host(host, profile, job, commands, folder, args.history, args.host_path)
                )
                print(
                    f"  {results[-1].host} on {profile.name}: {results[-1].rate:,.0f} lines/s",
                    file=sys.stderr,
                )
        print_table(results)
        if not args.no_big:
            size = int((0.02 if args.quick else args.big_gb) * 1e9)
            seconds = 3.0 if args.quick else args.big_seconds  # quick: room for a busy machine
            print_big(run_big(size, seconds, 1 if args.quick else 5, folder))
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"# bench CPU (all children): {usage.ru_utime + usage.ru_stime:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
