"""A farm on one PostgreSQL: how fast a job reaches a printer, how many jobs a second six
printers get through, and how many claims a second one database gives 200 printers.

    .venv/bin/python bench/farm.py            # the figures in bench/README.md
    .venv/bin/python bench/farm.py --quick    # small counts: checks that it runs (a test does)

It starts its own PostgreSQL cluster (Debian's binaries, as the tests do) and:

1. **latency**: two ``hyrel-server`` nodes of three fake printers each (real processes,
   ptys); a job submitted to the farm (``POST /v1/farm/jobs``) at a time, timed from the
   request to the job's first command in the executed log of the fake that printed it
   (the claim woken by NOTIFY, the file fetched from the database, checked, streamed).
2. **throughput**: the same six printers, a thousand one-line jobs queued at once
   (``copies``), timed from the submit to the farm counting every one completed.
3. **claims**: 200 simulated printers on 20 simulated nodes in this process (no streams),
   each claiming, starting and reporting the completion of a job in a loop, against a
   queue of jobs queued beforehand; claims a second, and the database's CPU (every
   PostgreSQL process's user + system time / the wall time: the cores it kept busy).
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import json
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
from tests.support.pg import PASSWORD, Postgres  # noqa: E402

from repetrel_host.fakes.fake_controller import BuiltInFake  # noqa: E402
from repetrel_host.server.farm import needs  # noqa: E402
from repetrel_host.server.farm.db import FarmDB  # noqa: E402

KEY = "bench"


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def postgres_cpu(cluster: Postgres) -> float:
    """CPU seconds of the cluster's processes: the postmaster (with its ended children)
    and every process it started that still runs."""
    tick = os.sysconf("SC_CLK_TCK")
    master = int((cluster.data / "postmaster.pid").read_text().split()[0])
    total = 0.0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        pid, parent = int(entry.name), int(fields[1])
        if pid == master:
            total += sum(int(value) for value in fields[11:15]) / tick  # with its children's
        elif parent == master:
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


class Nodes:
    """``count`` hyrel-server nodes of ``printers`` fake printers each, on one farm."""

    def __init__(self, url: str, folder: Path, count: int, printers: int) -> None:
        self.folder = folder
        self.fakes: list[BuiltInFake] = []
        self.processes: list[subprocess.Popen[bytes]] = []
        self.urls: list[str] = []
        for number in range(count):
            name = f"node{number}"
            lines = [f'farm = "{url}"', f'node_name = "{name}"', "automatic_transition = true"]
            for index in range(printers):
                fake = BuiltInFake(folder / f"{name}-p{index}.log", (), control=True)
                fake.start()
                self.fakes.append(fake)
                lines += [f"[printers.p{number}{index}]", f'port = "{fake.port}"']
            config = folder / f"{name}.toml"
            config.write_text("\n".join(lines) + "\n")
            port = free_port()
            self.urls.append(f"http://127.0.0.1:{port}")
            command = [
                sys.executable, "-m", "repetrel_host.server.main", "--config", str(config),
                "--data-dir", str(folder / name), "--bind", f"127.0.0.1:{port}", "--api-key", KEY,
            ]  # fmt: skip
            log = (folder / f"{name}.log").open("w")
            self.processes.append(subprocess.Popen(command, stdout=log, stderr=log))
        for url in self.urls:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                try:
                    if httpx.get(f"{url}/v1/farm", headers={"X-Api-Key": KEY}).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.1)

    def client(self, number: int = 0) -> httpx.Client:
        return httpx.Client(base_url=self.urls[number], headers={"X-Api-Key": KEY}, timeout=60)

    def stop(self) -> None:
        for process in self.processes:
            process.send_signal(signal.SIGTERM)
        for process in self.processes:
            try:
                process.wait(20)
            except subprocess.TimeoutExpired:
                process.kill()
        for fake in self.fakes:
            fake.stop()

    def first_command(self, mark: str) -> float | None:
        """When a fake's log first showed ``mark`` (None: not yet)."""
        for fake in self.fakes:
            assert fake.log_path is not None
            if fake.log_path.exists() and mark in fake.log_path.read_text():
                return time.monotonic()
        return None


def latency(nodes: Nodes, count: int) -> list[float]:
    """Seconds from submitting a job to its first command run on a fake, ``count`` jobs."""
    seconds = []
    with nodes.client() as client:
        for number in range(count):
            mark = f"G1 X1 Y{number + 1}.5"
            body = f"{mark} F6000\nG1 X2 F6000\n".encode()
            start = time.monotonic()
            answer = client.post(
                "/v1/farm/jobs", files={"file": (f"l{number}.gcode", body, "text/plain")}
            )
            answer.raise_for_status()
            while (seen := nodes.first_command(mark)) is None:
                time.sleep(0.002)
                if time.monotonic() - start > 30:
                    raise SystemExit(f"job {number} did not start in 30 s")
            seconds.append(seen - start)
    return seconds


def throughput(nodes: Nodes, count: int) -> float:
    """Jobs a second: ``count`` one-line jobs queued at once, until all completed."""
    with nodes.client() as client:
        before = client.get("/v1/farm").json()["counts"].get("completed", 0)
        start = time.monotonic()
        left = count
        while left:
            copies = min(left, 100)
            answer = client.post(
                "/v1/farm/jobs",
                data={"copies": str(copies)},
                files={"file": ("one.gcode", b"G1 X5 F6000\n", "text/plain")},
            )
            answer.raise_for_status()
            left -= copies
        while True:
            done = client.get("/v1/farm").json()["counts"].get("completed", 0)
            if done - before >= count or time.monotonic() - start > 600:
                break
            time.sleep(0.2)
        return count / (time.monotonic() - start)


async def claims(
    url: str, cluster: Postgres, printers: int, jobs: int
) -> tuple[float, float, float]:
    """Claims a second, the database's cores and the claimers' (this process), with
    ``printers`` claim loops on one pool each node (20 nodes), ``jobs`` queued beforehand."""
    nodes = 20
    pools = [FarmDB(url, size=max(2, printers // nodes)) for _ in range(nodes)]
    for pool in pools:
        await pool.open()
    folder = Path(tempfile.mkdtemp())
    path = folder / "one.gcode"
    path.write_text("G1 X5\n")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    await pools[0].store_file(path, digest, 30)
    for start in range(0, jobs, 1000):
        await pools[0].submit("one.gcode", digest, {}, 0, min(1000, jobs - start), 1, None, 60)
    loops = []
    taken = [0]
    for number, pool in enumerate(pools):
        node = str(uuid.uuid4())
        names = [f"n{number}p{i}" for i in range(printers // nodes)]
        has = {name: needs.capabilities(name, f"n{number}", None, "reprap", []) for name in names}
        await pool.register(node, f"n{number}", "", "bench", 600, [
            (name, has[name], None) for name in names
        ], 30)  # fmt: skip
        for name in names:
            loops.append(_claim_loop(pool, node, name, has[name], taken))
    cpu, start, own = postgres_cpu(cluster), time.monotonic(), _own_cpu()
    await asyncio.gather(*loops)
    wall = time.monotonic() - start
    used, claimers = postgres_cpu(cluster) - cpu, _own_cpu() - own
    for pool in pools:
        await pool.close()
    return taken[0] / wall, used / wall, claimers / wall


def _own_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def _claim_loop(db: FarmDB, node: str, printer: str, has: dict, taken: list[int]) -> None:
    done = {
        "state": "completed", "lines": 1, "last_line": 1, "started": time.time(),
        "ended": time.time(), "error": None, "report": None, "filament": None,
        "safe_stop": None, "local_id": 1,
    }  # fmt: skip
    while (job := await db.claim(node, printer, has, 60)) is not None:
        await db.start(job["id"], job["fence"], 60)
        await db.report(job["id"], job["fence"], done, 60)
        taken[0] += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small counts: checks it runs")
    options = parser.parse_args()
    samples, one_line_jobs, simulated, queued = (
        (10, 60, 40, 400) if options.quick else (100, 1000, 200, 20000)
    )
    os.environ["PGPASSWORD"] = PASSWORD
    cluster = Postgres(fsync=True)  # commits as durable as a production database's
    results: dict[str, float | int] = {}
    try:
        with tempfile.TemporaryDirectory() as folder:
            nodes = Nodes(cluster.new_database(), Path(folder), 2, 3)
            try:
                seconds = sorted(latency(nodes, samples))
                results["submit_to_first_line_median_ms"] = statistics.median(seconds) * 1000
                results["submit_to_first_line_p99_ms"] = (
                    seconds[min(len(seconds) - 1, int(len(seconds) * 0.99))] * 1000
                )
                results["one_line_jobs"] = one_line_jobs
                results["jobs_per_second_six_printers"] = throughput(nodes, one_line_jobs)
            finally:
                nodes.stop()
        rate, cores, own = asyncio.run(claims(cluster.new_database(), cluster, simulated, queued))
        results["simulated_printers"] = simulated
        results["claims_per_second"] = rate
        results["database_cores"] = cores
        results["claimers_cores"] = own
    finally:
        cluster.close()
    median, p99 = results["submit_to_first_line_median_ms"], results["submit_to_first_line_p99_ms"]
    print(f"submit to first line, six printers: median {median:.0f} ms, "
          f"99th percentile {p99:.0f} ms ({samples} jobs)")  # fmt: skip
    print(f"{one_line_jobs} one-line jobs through six printers: "
          f"{results['jobs_per_second_six_printers']:.1f} jobs/s")  # fmt: skip
    print(f"{simulated} simulated printers, claim + start + report a job each loop: "
          f"{results['claims_per_second']:.0f} claims/s, the database kept "
          f"{results['database_cores']:.2f} cores busy, the claimers "
          f"{results['claimers_cores']:.2f} ({os.cpu_count()} cores here)")  # fmt: skip
    print(json.dumps({key: round(value, 2) for key, value in results.items()}))


if __name__ == "__main__":
    main()
