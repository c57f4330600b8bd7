"""No input holds the server up: its worst answer delay while a big file and a long line are
uploaded and analysed, with another printer streaming the while.

A ``hyrel-server`` process serves two fake printers. ``busy`` streams a job of moves that
take 5 ms each (a printer's pace, not the link's); meanwhile a client process polls
``GET /v1/printers/busy`` every 10 ms and keeps each answer's time, and another uploads to
the file store a file of ``--size-mb`` MB of ordinary G-code and one with a 500 KB line
(``/v1/files``: stored, then analysed in the background), then asks each one's check
(``/v1/files/NAME/check``: the whole file linted). It prints the answers' worst and 99th
percentile times while that goes on (the event loop's delay, seen from outside: an
answer's own time is about 1 ms), and ``busy``'s lines/s before and during (a line late
would show as a lower rate), the same for each step (each upload, each check), and that
each of ``busy``'s lines ran once, in order, up to the cancel that ends its job.

    .venv/bin/python bench/loop_delay.py [--size-mb 1024]
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).parent.parent))

from tests.support.helpers import executed
from tests.support.server import KEY, Server

from repetrel_host.fakes.fake_controller import BuiltInFake

MOVES = 100_000  # 500 s at 200 lines/s: longer than the uploads and checks


def big_file(path: Path, megabytes: int) -> None:
    line = b"G1 X112.345 Y98.765 E0.04321 ; a perimeter\n"
    block = line * (1 << 20 // len(line) + 1)
    with path.open("wb") as out:
        written = 0
        while written < megabytes << 20:
            out.write(block)
            written += len(block)


def lines(client: httpx.Client, job: int) -> int:
    return int(client.get(f"/v1/jobs/{job}").json()["lines"])


def rate(client: httpx.Client, job: int, seconds: float) -> float:
    first = lines(client, job)
    time.sleep(seconds)
    return (lines(client, job) - first) / seconds


def step(
    name: str, started: float, first: int, client: httpx.Client, job: int
) -> tuple[str, float, float, float]:
    """A step's name, when it began and ended, and the busy printer's lines/s through it."""
    ended = time.monotonic()
    return name, started, ended, (lines(client, job) - first) / (ended - started)


def poll(url: str, stop: Any, results: Any) -> None:
    """``GET /v1/printers/busy`` every 10 ms until ``stop``; sends back (when, seconds) each."""
    answers = []
    with httpx.Client(base_url=url, headers={"X-Api-Key": KEY}, timeout=30) as client:
        while not stop.is_set():
            at = time.monotonic()  # the system's clock: the same in every process
            started = time.perf_counter()
            client.get("/v1/printers/busy").raise_for_status()
            answers.append((at, time.perf_counter() - started))
            if len(answers) == 1:
                results.send("polling")
            time.sleep(0.01)
    results.send(answers)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size-mb", type=int, default=1024, help="the big file's size")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        big, long = folder / "big.gcode", folder / "long.gcode"
        big_file(big, args.size_mb)
        long.write_bytes(b"G28\n;" + b"c" * 500_000 + b"\nG1 X1\n")
        moves = [f"G1 X{i % 200} F3000" for i in range(MOVES)]
        with (
            BuiltInFake(folder / "busy.log", ["--move-time", "0.005"]) as busy,
            BuiltInFake(folder / "idle.log") as idle,
        ):
            printers = {"busy": busy.port, "idle": idle.port}
            limit = str(args.size_mb + 64)
            server = Server(folder / "data", printers, "--api-key", KEY, "--max-upload-mb", limit)
            server.start()
            try:
                with server.client() as client:
                    job = client.post(
                        "/v1/printers/busy/jobs",
                        files={"file": ("moves.gcode", "\n".join(moves) + "\n")},
                    ).json()["id"]
                    time.sleep(2)
                    before = rate(client, job, 3)
                    # The poller is a process of its own: a thread here would share this
                    # process's lock with the upload's sending, and count its own waits.
                    spawn = multiprocessing.get_context("spawn")
                    stop = spawn.Event()
                    receiving, sending = spawn.Pipe(duplex=False)
                    poller = spawn.Process(target=poll, args=(server.url, stop, sending))
                    poller.start()
                    assert receiving.recv() == "polling"
                    steps: list[tuple[str, float, float, float]] = []  # name, from, to, lines/s
                    started = time.monotonic()
                    first = lines(client, job)
                    for path in (long, big):
                        step_start, step_lines = time.monotonic(), lines(client, job)
                        with path.open("rb") as handle:
                            stored = client.post(
                                "/v1/files", files={"file": (path.name, handle)}, timeout=600
                            )
                        assert stored.status_code == 201, stored.text
                        steps.append(
                            step(f"upload {path.name}", step_start, step_lines, client, job)
                        )
                        step_start, step_lines = time.monotonic(), lines(client, job)
                        checked = client.get(f"/v1/files/{path.name}/check", timeout=600)
                        assert checked.status_code == 200, checked.text
                        steps.append(
                            step(f"check {path.name}", step_start, step_lines, client, job)
                        )
                    during_seconds = time.monotonic() - started
                    during = (lines(client, job) - first) / during_seconds
                    stop.set()
                    answers: list[tuple[float, float]] = receiving.recv()
                    poller.join()
                    # A job that ended before the measurement would make its rate a lie.
                    assert client.get(f"/v1/jobs/{job}").json()["state"] == "printing"
                    client.post("/v1/printers/busy/cancel")
                    while client.get(f"/v1/jobs/{job}").json()["state"] == "printing":
                        time.sleep(0.5)
            finally:
                server.stop()
            ran = [line for line in executed(busy.log_path) if line.endswith(" F3000")]
            once = ran == moves[: len(ran)]  # each line once, in order, up to the cancel
    for name, begun, ended, per_second in steps:
        shown = f"{per_second:.0f} lines/s" if ended - begun >= 1 else "-"  # too short to tell
        worst = max((took for at, took in answers if begun <= at < ended), default=0.0)
        print(
            f"  {name}: {ended - begun:.1f} s, busy printer {shown}, "
            f"worst answer {worst * 1000:.1f} ms"
        )
    times = sorted(took for at, took in answers if started <= at)
    print(
        f"a file of {args.size_mb} MB and a 500 KB line, uploaded and checked in "
        f"{during_seconds:.1f} s"
    )
    print(
        f"answers meanwhile: {len(times)}, median {statistics.median(times) * 1000:.1f} ms, "
        f"p99 {times[int(len(times) * 0.99)] * 1000:.1f} ms, worst {times[-1] * 1000:.1f} ms"
    )
    print(
        f"busy printer: {before:.0f} lines/s before, {during:.0f} lines/s during; "
        f"every line sent once, in order: {once}"
    )


if __name__ == "__main__":
    main()
