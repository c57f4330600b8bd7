"""No input holds the server up: its worst answer delay while a big file and a long line are
uploaded and analysed, with another printer streaming the while.

A ``hyrel-server`` process serves two fake printers. ``busy`` streams a job of moves that
take 5 ms each (a printer's pace, not the link's); meanwhile a client polls
``GET /v1/printers/busy`` every 10 ms and keeps each answer's time, and another uploads to
the file store a file of ``--size-mb`` MB of ordinary G-code and one with a 500 KB line
(``/v1/files``: stored, then analysed in the background), then asks each one's check
(``/v1/files/NAME/check``: the whole file linted). It prints the answers' worst and 99th
percentile times while that goes on (the event loop's delay, seen from outside: an
answer's own time is about 1 ms), and ``busy``'s lines/s before and during (a line late
would show as a lower rate), and that each of its lines ran once.

    .venv/bin/python bench/loop_delay.py [--size-mb 1024]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).parent.parent))

from tests.helpers import executed
from tests.test_server import KEY, Server

from repetrel_host.fakes.fake_controller import BuiltInFake

MOVES = 20_000


def big_file(path: Path, megabytes: int) -> None:
    line = b"G1 X112.345 Y98.765 E0.04321 ; a perimeter\n"
    block = line * (1 << 20 // len(line) + 1)
    with path.open("wb") as out:
        written = 0
        while written < megabytes << 20:
            out.write(block)
            written += len(block)


def rate(client: httpx.Client, job: int, seconds: float) -> float:
    first = client.get(f"/v1/jobs/{job}").json()["lines"]
    time.sleep(seconds)
    return (client.get(f"/v1/jobs/{job}").json()["lines"] - first) / seconds


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
                    times: list[float] = []
                    done = threading.Event()

                    def poll() -> None:
                        with server.client() as poller:
                            while not done.is_set():
                                started = time.perf_counter()
                                poller.get("/v1/printers/busy")
                                times.append(time.perf_counter() - started)
                                time.sleep(0.01)

                    polling = threading.Thread(target=poll)
                    started = time.monotonic()
                    first = client.get(f"/v1/jobs/{job}").json()["lines"]
                    polling.start()
                    for path in (long, big):
                        with path.open("rb") as handle:
                            stored = client.post(
                                "/v1/files", files={"file": (path.name, handle)}, timeout=600
                            )
                        assert stored.status_code == 201, stored.text
                        checked = client.get(f"/v1/files/{path.name}/check", timeout=600)
                        assert checked.status_code == 200, checked.text
                    during_seconds = time.monotonic() - started
                    during = (
                        client.get(f"/v1/jobs/{job}").json()["lines"] - first
                    ) / during_seconds
                    done.set()
                    polling.join()
                    while client.get(f"/v1/jobs/{job}").json()["state"] == "printing":
                        time.sleep(0.5)
            finally:
                server.stop()
            once = executed(busy.log_path)[-MOVES:] == moves
    times.sort()
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
        f"every line once: {once}"
    )


if __name__ == "__main__":
    main()
