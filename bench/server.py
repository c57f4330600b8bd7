"""Several printers, one small PC: the print server streams to N fake printers at once.

A ``hyrel-server`` process serves four fake controllers (``bench/run.py``'s links, each
fake its own process and pty), each printer sent the same slicer job; then one printer
alone, the same way. ``uart`` is what a printer on a 115200-baud serial link asks;
``usb`` a link as fast as the fake goes, where the fakes' own CPU competes with the
server's on this 2-core machine. It prints each printer's lines/s beside the single-printer figure
(target: each at >= 90 % of it) and the server's CPU per streamed line (its own
process's user + system time while the jobs stream, over all their lines).

    .venv/bin/python bench/server.py [--profile uart|usb] [--printers 4] [--quick]
    .venv/bin/python bench/server.py --socket-clients 10 [--repeat 5] [--job-times 5]
    .venv/bin/python bench/server.py --socket-clients 10 --moonraker [--repeat 5] [--job-times 5]

Jobs are queued while the printers are held, then released together, so the CPU counted
is the streaming's (the uploads' checks come before).

``--socket-clients N``: the printers' runs with N push socket clients on each printer
(``bench/socket_clients.py``: each logged in and reading every message) against runs
without any, alternated ``--repeat`` times; it prints each run and the medians' ratio.
``--job-times K`` makes each job the profile's K times over: a run that is mostly
streaming, not a job's start and end (each sends every client its state changes and events).
``--moonraker``: the clients are Moonraker's websockets instead, each subscribed to every
printer object as Mainsail subscribes.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent.parent))

from bench.run import PROFILES, Profile, job_file, start_fake, stop_fake

from repetrel_host.cli.server_client import ServerClient

KEY = "bench"


@dataclass
class Run:
    printers: int
    rates: list[float]  # lines/s of each printer
    lines: int  # per printer
    cpu_seconds: float  # the server's, while the jobs streamed
    fake_cpu_seconds: float  # the fakes' together, the same time
    sockets: dict[str, int] = field(default_factory=dict)  # what the socket clients got
    socket_cpu_seconds: float = 0.0  # the socket clients' process, the same time

    @property
    def cpu_per_line(self) -> float:
        return self.cpu_seconds / (self.lines * self.printers)

    @property
    def fake_cpu_per_line(self) -> float:
        return self.fake_cpu_seconds / (self.lines * self.printers)


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def run(
    profile: Profile,
    count: int,
    job: Path,
    lines: int,
    folder: Path,
    socket_clients: int = 0,
    moonraker: bool = False,
) -> Run:
    fakes = [start_fake(profile, folder, f"{profile.name}-{count}-{i}") for i in range(count)]
    window = dict(zip(profile.options[::2], profile.options[1::2], strict=True))
    port = free_port()
    data = folder / f"data-{count}"
    config = folder / f"server-{count}.toml"
    link = "".join(
        f"{option[2:].replace('-', '_')} = {value}\n" for option, value in window.items()
    )
    printers = "".join(
        f'[printers.p{i}]\nport = "{tty}"\n{link}' for i, (_, tty) in enumerate(fakes)
    )
    config.write_text(
        f'data_dir = "{data}"\nbind = "127.0.0.1:{port}"\napi_key = "{KEY}"\n{printers}'
    )
    server = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.server.main", "--config", str(config)],
        stdout=subprocess.DEVNULL,
        stderr=(folder / f"server-{count}.log").open("w"),
    )
    client = ServerClient(f"127.0.0.1:{port}", KEY)
    readers: subprocess.Popen[str] | None = None
    try:
        names = [f"p{i}" for i in range(count)]
        deadline = time.monotonic() + 30
        while True:
            try:
                states = [p["state"] for p in client.request("GET", "/v1/printers")]
                if states == ["ready"] * count:
                    break
            except Exception:  # not listening yet
                pass
            if time.monotonic() > deadline:
                raise SystemExit("bench: the server's printers did not get ready")
            time.sleep(0.1)
        for name in names:
            client.request("POST", f"/v1/printers/{name}/hold")
        jobs = [client.submit(name, job)["id"] for name in names]
        if socket_clients:
            script = Path(__file__).parent / "socket_clients.py"
            readers = subprocess.Popen(
                [
                    sys.executable,
                    str(script),
                    *(["--moonraker"] if moonraker else []),
                    f"127.0.0.1:{port}",
                    KEY,
                    str(socket_clients),
                    *names,
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
            assert readers.stdout is not None
            if readers.stdout.readline().strip() != "ready":
                raise SystemExit("bench: the socket clients did not get ready")
            time.sleep(1.0)  # past their histories: the streaming's cost is counted
        before = cpu_seconds(server.pid)
        fakes_before = sum(cpu_seconds(fake.pid) for fake, _ in fakes)
        readers_before = cpu_seconds(readers.pid) if readers is not None else 0.0
        for name in names:
            client.request("POST", f"/v1/printers/{name}/release")
        records = []
        for job_id in jobs:
            while (record := client.request("GET", f"/v1/jobs/{job_id}"))["state"] in (
                "queued",
                "printing",
            ):
                time.sleep(0.2)
            if record["state"] != "completed" or record["lines"] != lines:
                raise SystemExit(f"bench: job {job_id} ended {record}")
            records.append(record)
        cpu = cpu_seconds(server.pid) - before
        fake_cpu = sum(cpu_seconds(fake.pid) for fake, _ in fakes) - fakes_before
        rates = [lines / (r["ended"] - r["started"]) for r in records]
        result = Run(count, rates, lines, cpu, fake_cpu)
        if readers is not None:
            result.socket_cpu_seconds = cpu_seconds(readers.pid) - readers_before
            readers.send_signal(signal.SIGTERM)
            out, _ = readers.communicate(timeout=30)
            result.sockets = json.loads(out.strip().splitlines()[-1])
        return result
    finally:
        if readers is not None and readers.poll() is None:
            readers.kill()
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)
        for fake, _ in fakes:
            stop_fake(fake)


def with_sockets(
    profiles: list[str],
    printers: int,
    clients: int,
    repeat: int,
    quick: bool,
    times: int,
    moonraker: bool = False,
) -> None:
    """Runs without socket clients and with ``clients`` on each printer, alternated; each
    printer's job is the profile's ``times`` over (a longer run: the streaming's cost,
    less the start's and end's)."""
    # The kinds of message counted: OctoPrint's currents and events, or Moonraker's status
    # updates and process statistics.
    kinds = (
        ("notify_status_update", "notify_proc_stat_update") if moonraker else ("current", "event")
    )
    print(
        "| link | printers | socket clients | run | lines/s (mean of printers) "
        f"| server CPU µs/line | messages | {kinds[0]} | {kinds[1]} | clients' CPU µs/line |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for profile in (p for p in PROFILES if p.name in profiles):
        lines = 300 if quick else profile.lines
        runs: dict[int, list[Run]] = {0: [], clients: []}
        with tempfile.TemporaryDirectory(prefix="hyrel-bench-server-") as name:
            folder = Path(name)
            job, _ = job_file(lines, folder)
            if times > 1:
                longer = folder / f"{job.stem}-x{times}.gcode"
                longer.write_text(job.read_text() * times)
                job, lines = longer, lines * times
            for number in range(repeat):
                for count in (0, clients):
                    result = run(profile, printers, job, lines, folder, count, moonraker)
                    runs[count].append(result)
                    got = result.sockets
                    rate = statistics.mean(result.rates)
                    readers = result.socket_cpu_seconds / (lines * printers) * 1e6
                    print(
                        f"| {profile.name} | {printers} | {count} | {number + 1} | {rate:,.0f} "
                        f"| {result.cpu_per_line * 1e6:.2f} | {got.get('messages', 0)} "
                        f"| {got.get(kinds[0], 0)} | {got.get(kinds[1], 0)} "
                        f"| {readers:.2f} |",
                        flush=True,
                    )
        rate = {
            n: statistics.median(statistics.mean(r.rates) for r in rs) for n, rs in runs.items()
        }
        cpu = {n: statistics.median(r.cpu_per_line for r in rs) for n, rs in runs.items()}
        print(
            f"\n{profile.name}, medians of {repeat}: without socket clients {rate[0]:,.0f} lines/s "
            f"and {cpu[0] * 1e6:.2f} µs of server CPU a line; with {clients} on each printer "
            f"{rate[clients]:,.0f} lines/s ({100 * rate[clients] / rate[0] - 100:+.1f} %) and "
            f"{cpu[clients] * 1e6:.2f} µs ({100 * cpu[clients] / cpu[0] - 100:+.1f} %)\n"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", action="append", choices=["uart", "usb"])
    parser.add_argument("--printers", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="small inputs: checks that it runs")
    parser.add_argument(
        "--socket-clients", type=int, default=0, help="push socket clients on each printer"
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs of each (--socket-clients)")
    parser.add_argument(
        "--moonraker", action="store_true", help="the clients on Moonraker's websocket"
    )
    parser.add_argument(
        "--job-times", type=int, default=1, help="each job the profile's this many times over"
    )
    args = parser.parse_args()
    if args.socket_clients:
        profiles = args.profile or ["uart", "usb"]
        with_sockets(
            profiles,
            args.printers,
            args.socket_clients,
            args.repeat,
            args.quick,
            args.job_times,
            args.moonraker,
        )
        return 0
    print(
        "| link | printers | printer | lines | lines/s | % of alone | server CPU µs/line "
        "| a fake's CPU µs/line |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for profile in (p for p in PROFILES if p.name in (args.profile or ["uart", "usb"])):
        lines = 300 if args.quick else profile.lines
        with tempfile.TemporaryDirectory(prefix="hyrel-bench-server-") as name:
            folder = Path(name)
            job, _ = job_file(lines, folder)
            single = run(profile, 1, job, lines, folder)
            several = run(profile, args.printers, job, lines, folder)
        alone = single.rates[0]
        cpu = f"{single.cpu_per_line * 1e6:.1f} | {single.fake_cpu_per_line * 1e6:.1f}"
        print(f"| {profile.name} | 1 | p0 | {lines} | {alone:,.0f} | 100 | {cpu} |")
        for i, rate in enumerate(several.rates):
            cpu = f"{several.cpu_per_line * 1e6:.1f} | {several.fake_cpu_per_line * 1e6:.1f}"
            row = f"| {profile.name} | {several.printers} | p{i} | {lines} | {rate:,.0f}"
            print(f"{row} | {100 * rate / alone:.0f} | {cpu if i == 0 else ' | '} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
