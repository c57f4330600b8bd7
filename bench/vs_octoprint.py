"""hyrel-send against OctoPrint itself, on OctoPrint's own virtual printer.

    python3 -m venv /tmp/octo-venv && /tmp/octo-venv/bin/pip install octoprint==1.11.8
    .venv/bin/python bench/vs_octoprint.py                  # three rounds, about 13 minutes
    .venv/bin/python bench/vs_octoprint.py --runs 1 --lines 300 --keep /tmp/wires

Each run starts a fresh ``bench/octoprint_virtual.py`` (OctoPrint 1.11.8's
VirtualPrinter with its default settings behind a pty that pushes back like USB: cold
heaters, its simulated errors at lines 100, 105, 110 and 115) and prints the first
``--lines`` lines of the cone file through it with one host: OctoPrint's own serial layer
(``bench/octoprint_host.py``: ``MachineCom``, as OctoPrint's server drives it), then
``hyrel-send --flow unbuffered``, then ``hyrel-send --flow buffered`` (machine profile
marlin, its default window), in turn, ``--runs`` rounds. It prints each run's seconds and
the medians: for OctoPrint from the start of the print to its "print job done", for
hyrel-send the whole command, from the process's start to its exit.

Each run is checked: the host succeeded, and the commands VirtualPrinter executed are the
job's, in order, each once, besides the hosts' own (M105, M110, M115, M155...). One job
line may be missing, and only this one: line 105. VirtualPrinter's ``resend_with_timeout``
error asks for line 105 again but counts it as received without running it, and drops the
next line it gets without running or answering it: it then takes line 106 next, so no host
can tell, and every host loses that line.
"""

from __future__ import annotations

import argparse
import ast
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONE = ROOT / "tests" / "data" / "cone-prusaslicer.gcode"
BRIDGE = Path(__file__).resolve().parent / "octoprint_virtual.py"
OCTOPRINT_HOST = Path(__file__).resolve().parent / "octoprint_host.py"
HOSTS = ("octoprint", "unbuffered", "buffered")
# What the hosts send of their own: greetings, temperature polls and reports, SD card.
HOST_WORDS = frozenset({"M105", "M110", "M115", "M155", "M20", "M21", "M27", "M114", "M400"})
SWALLOWED = "N105 "  # the simulated error that makes VirtualPrinter lose a line


def job_file(lines: int, folder: Path) -> tuple[Path, list[str]]:
    """The first ``lines`` lines of the cone file, and its commands as a host sends them."""
    from repetrel_host.session.job import Job

    path = folder / f"cone-{lines}.gcode"
    path.write_text("".join(CONE.read_text().splitlines(keepends=True)[:lines]))
    return path, [command for _, command, _, _ in Job(path).commands()]


def start_bridge(python: str, folder: Path, tag: str) -> tuple[subprocess.Popen[str], Path]:
    link = folder / f"{tag}.pty"
    argv = [python, str(BRIDGE), "--link", str(link)]
    argv += ["--log", str(folder / f"{tag}.log"), "--wire", str(folder / f"{tag}.wire")]
    bridge = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
    assert bridge.stdout is not None
    if not bridge.stdout.readline().startswith("ready"):
        raise SystemExit("bench: the VirtualPrinter bridge did not start")
    return bridge, link


def host_argv(host: str, python: str, job: Path, port: Path) -> list[str]:
    if host == "octoprint":
        return [python, str(OCTOPRINT_HOST), str(job), "--port", str(port)]
    send = str(Path(sys.executable).parent / "hyrel-send")
    return [
        send,
        str(job),
        "--port",
        str(port),
        "--flow",
        host,
        "--machine",
        "marlin",
        "--no-history",
    ]


def swallowed(wire: Path) -> str | None:
    """The command VirtualPrinter took for run but never ran: its first N105's."""
    for line in wire.read_text().splitlines():
        _, direction, data = line.split(" ", 2)
        if direction == ">" and data.startswith("b'" + SWALLOWED):
            body = ast.literal_eval(data).split(b" ", 1)[1].rsplit(b"*", 1)[0]
            return str(body.decode("ascii").strip())
    return None


def check(executed: list[str], commands: list[str], dropped: str | None) -> str | None:
    """None when ``executed`` is ``commands`` once each, in order (see the docstring)."""
    normal = [" ".join(command.split()) for command in commands]
    at, skipped = 0, False
    for command in executed:
        if at < len(normal) and command == normal[at]:
            at += 1
        elif (
            not skipped
            and at + 1 < len(normal)
            and normal[at] == dropped
            and command == normal[at + 1]
        ):
            at, skipped = at + 2, True
        elif command.split(" ", 1)[0] not in HOST_WORDS:
            return f"executed {command!r} where the job's line {at} is {normal[at : at + 1]}"
    if at != len(normal):
        return f"only {at} of the job's {len(normal)} commands ran"
    return None


def run(host: str, python: str, job: Path, commands: list[str], folder: Path, tag: str) -> float:
    bridge, port = start_bridge(python, folder, tag)
    try:
        start = time.monotonic()
        done = subprocess.run(
            host_argv(host, python, job, port), capture_output=True, text=True, timeout=900
        )
        seconds = time.monotonic() - start
    finally:
        bridge.send_signal(signal.SIGTERM)
        bridge.wait(timeout=10)
    if done.returncode != 0:
        raise SystemExit(f"bench: {tag} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    if host == "octoprint":  # from the start of the print: its connection is not counted
        seconds = float(done.stdout.split("seconds ", 1)[1].split()[0])
    executed = [line.split(" ", 1)[1] for line in (folder / f"{tag}.log").read_text().splitlines()]
    problem = check(executed, commands, swallowed(folder / f"{tag}.wire"))
    if problem is not None:
        raise SystemExit(f"bench: {tag} did not run the job exactly once: {problem}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--octoprint-python", default="/tmp/octo-venv/bin/python")
    parser.add_argument("--lines", type=int, default=4528, help="lines of the cone file")
    parser.add_argument("--runs", type=int, default=3, help="rounds of the three hosts")
    parser.add_argument("--hosts", nargs="+", choices=HOSTS, default=list(HOSTS))
    parser.add_argument("--keep", type=Path, help="keep the wire and executed logs here")
    args = parser.parse_args()
    if not os.access(args.octoprint_python, os.X_OK):
        raise SystemExit(f"bench: no OctoPrint Python at {args.octoprint_python}: see --help")

    folder = args.keep or Path(tempfile.mkdtemp(prefix="bench-octoprint-"))
    folder.mkdir(parents=True, exist_ok=True)
    job, commands = job_file(args.lines, folder)
    print(f"{job.name}: {args.lines} lines, {len(commands)} commands; logs in {folder}")
    times: dict[str, list[float]] = {host: [] for host in args.hosts}
    for round_ in range(args.runs):
        for host in args.hosts:
            seconds = run(host, args.octoprint_python, job, commands, folder, f"{host}-{round_}")
            times[host].append(seconds)
            print(f"round {round_ + 1} {host}: {seconds:.2f} s, exactly once", flush=True)
    print("\n| host | runs (s) | median (s) |\n|---|---|---|")
    for host, runs in times.items():
        listed = ", ".join(f"{t:.2f}" for t in runs)
        print(f"| {host} | {listed} | {statistics.median(runs):.2f} |")


if __name__ == "__main__":
    main()
