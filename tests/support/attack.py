"""A printer streaming beside an attack on the server: the attack must cost it nothing."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed
from tests.support.server import Server, job_state, server_config, wait_for

# A move of 5 ms each (``--move-time 0.005`` at the fake): 4,000 of them outlast an attack.
BESIDE_MOVES = 4000
# The longest the job beside may stand still: far above a healthy server's (its progress
# is told a few times a second), far below the minute an attack used to stall it for.
# Not a speed goal (bench/attacks.py measures the delay): a stall caught in seconds.
LONGEST_STILL = 5.0


def busy_server(
    tmp_path: Path,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    protocol: str,
    settings: str = "",
    **more: dict[str, object],
) -> tuple[Server, BuiltInFake]:
    """A server with printer ``busy`` (a fake that moves for 5 ms a line, on ``protocol``'s
    link), and the TOML lines ``settings`` before its printers."""
    fake = bench("--move-time", "0.005", "--protocol", protocol)
    config = server_config(tmp_path, busy={"port": fake.port, "protocol": protocol}, **more)
    config.write_text(settings + config.read_text())
    return servers({}, "--config", str(config)), fake


@contextlib.contextmanager
def streaming_beside(
    server: Server, fake: BuiltInFake, printer: str = "busy", moves: int = BESIDE_MOVES
) -> Iterator[None]:
    """A job of ``moves`` streaming to ``printer`` (its fake ``fake``) while the block runs.

    On leaving: the job still prints, its progress never stood still for 5 s while the
    block ran (a stalled event loop starves it, and Hyrel's host watchdog kills it), the
    fake saw no link error, and every move it ran ran once, in order. The job is then
    cancelled."""
    lines = [f"G1 X{i % 200} Y{i // 200 % 200} F3000" for i in range(moves)]
    with server.client() as client:
        answer = client.post(
            f"/v1/printers/{printer}/jobs",
            files={"file": ("beside.gcode", "\n".join(lines) + "\n")},
        )
        assert answer.status_code in (200, 201), answer.text
        job = answer.json()["id"]
        wait_for(lambda: job_state(client, job)["lines"] > 20, what="the job beside streaming")
        stop = threading.Event()
        still = [0.0]  # the longest the job's line count stood still

        def watch() -> None:
            with server.client() as watcher:
                seen, since = -1, time.monotonic()
                while not stop.is_set():
                    count = watcher.get(f"/v1/jobs/{job}", timeout=120).json()["lines"]
                    now = time.monotonic()
                    if count != seen:
                        seen, since = count, now
                    still[0] = max(still[0], now - since)
                    time.sleep(0.1)

        watching = threading.Thread(target=watch, daemon=True)
        watching.start()
        try:
            yield
        finally:
            stop.set()
            watching.join(timeout=130)
        after = job_state(client, job)
        assert after["state"] == "printing", f"the job beside the attack ended: {after}"
        assert still[0] < LONGEST_STILL, f"the job beside stood still for {still[0]:.1f} s"
        assert fake.request("status")["errors"] == 0, "the link drew an error"
        client.delete(f"/v1/jobs/{job}")
        wait_for(lambda: job_state(client, job)["state"] != "printing", what="the cancel")
    assert fake.log_path is not None
    ran = [line for line in executed(fake.log_path) if line.startswith("G1 X")]
    assert ran == lines[: len(ran)], "a move ran twice or was skipped"
    assert len(ran) > 20
