"""No input holds the host up (issue 35): a file of long lines is read in time linear in
its size, a command longer than a controller takes is refused with its line number and
never sent, and the server goes on answering (another printer streaming on) while such a
file is uploaded and analysed."""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session.job import MAX_KEPT_LINE, _raw_lines
from repetrel_host.session.planning import PRECHECK_LIMIT
from repetrel_host.session.workers import in_worker, stop_workers
from tests.support.helpers import executed
from tests.support.server import Server, job_state, wait_for

pytestmark = pytest.mark.timeout(60)
# The bug report's file: 300 KB of NUL bytes without a line end, then a 200 KB line.
NULS_THEN_A_LONG_LINE = b"G28\n" + b"\0" * 300_000 + b"G1 X1 " + b"Y2 " * 66_000 + b"\nG1 X2\n"
LONG_COMMAND = b"G28\nG1 X1 " + b"Y2 " * 170_000 + b"\nG1 X2\n"


def test_lines_of_any_length_are_read_whole_or_bounded_with_their_offsets() -> None:
    data = b"G28\r\n;" + b"c" * 300_000 + b"\rG1 X1\nG1 X2"
    handle = io.BytesIO(data)
    lines = list(_raw_lines(handle))
    assert [line[:4] for line, _ in lines] == [b"G28", b";ccc", b"G1 X", b"G1 X"]
    assert len(lines[1][0]) == MAX_KEPT_LINE  # only its start is kept
    assert [offset for _, offset in lines] == [5, 300_007, 300_013, len(data)]


@pytest.mark.parametrize("content", [NULS_THEN_A_LONG_LINE, LONG_COMMAND], ids=["nuls", "long"])
def test_check_refuses_a_file_of_long_lines_at_once_naming_the_line(
    tmp_path: Path, content: bytes
) -> None:
    job = tmp_path / "long.gcode"
    job.write_bytes(content)
    result = subprocess.run(
        [sys.executable, "-m", "repetrel_host.cli", str(job), "--check"],
        capture_output=True,
        text=True,
        timeout=20,  # it took minutes: the reading was quadratic in a line's length
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert "error: long.gcode:2: the command" in result.stderr


def test_a_command_too_long_is_never_sent_and_the_job_stops_before_it(tmp_path: Path) -> None:
    job = tmp_path / "long.gcode"
    job.write_bytes(b"".join(b"G1 X%d\n" % i for i in range(50)) + LONG_COMMAND)
    log = tmp_path / "fake.log"

    async def scenario(port: str) -> None:
        async with rh.connect(port, poll_interval=None) as printer:
            plan = printer.plan(job)  # a plan is not checked first: it streams as it reads
            streaming = await printer.print(plan, history=False)
            with pytest.raises(rh.JobError, match=r"long\.gcode:52: the command is over"):
                await streaming.wait()

    with BuiltInFake(log) as fake:
        asyncio.run(scenario(fake.port))
        done = executed(log)
    assert done[:51] == [f"G1 X{i}" for i in range(50)] + ["G28"]
    assert not any(command.startswith("G1 X1 Y2") for command in done)
    assert done[-1] == "M84"  # then the safe stop


@pytest.mark.slow
def test_the_server_answers_and_another_printer_streams_on_while_long_lines_are_uploaded(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    busy, idle = bench("--move-time", "0.005"), bench()
    server = servers({"busy": busy.port, "idle": idle.port})
    moves = [f"G1 X{i % 200} F3000" for i in range(1500)]
    with server.client() as client:
        printing = client.post(
            "/v1/printers/busy/jobs", files={"file": ("moves.gcode", "\n".join(moves) + "\n")}
        ).json()["id"]
        wait_for(lambda: job_state(client, printing)["lines"] > 50, what="the job streaming")
        answers: list[float] = []
        stop = threading.Event()

        def poll() -> None:  # the API while the uploads are analysed: it answers
            with server.client() as poller:
                while not stop.is_set():
                    started = time.monotonic()
                    assert poller.get("/v1/printers/busy", timeout=10).status_code == 200
                    answers.append(time.monotonic() - started)
                    time.sleep(0.05)

        polling = threading.Thread(target=poll)
        polling.start()
        wait_for(lambda: answers, what="the API's first answer")
        try:
            for name, content in (
                ("nuls.gcode", NULS_THEN_A_LONG_LINE),
                ("cmd.gcode", LONG_COMMAND),
            ):
                upload = client.post(
                    "/v1/printers/idle/jobs", files={"file": (name, content)}, timeout=20
                )
                assert upload.status_code in (400, 422), upload.text
                assert "refused" in upload.json()["error"], upload.text
                assert "2: the command" in upload.text, upload.text
            before = len(answers)
            wait_for(lambda: len(answers) > before, what="the API answering after the uploads")
        finally:
            stop.set()
            polling.join(timeout=20)
        wait_for(lambda: job_state(client, printing)["state"] == "completed", what="the job")
    assert executed(busy.log_path)[-len(moves) :] == moves  # each line once, in order
    assert "G1 X1 Y2" not in " ".join(executed(idle.log_path))


def test_a_job_is_planned_and_checked_off_the_event_loop(tmp_path: Path) -> None:
    # Up to 4 MB a job is checked whole before its first line: the loop (every other
    # printer's stream, the server's answers) runs on meanwhile.
    job = tmp_path / "moves.gcode"
    job.write_bytes(b"".join(b"G1 X%d Y%d F3000\n" % (i % 200, i % 150) for i in range(150_000)))
    assert job.stat().st_size < PRECHECK_LIMIT

    async def scenario(port: str) -> int:
        async with rh.connect(port, poll_interval=None) as printer:
            ticks = 0
            done = asyncio.Event()

            async def tick() -> None:
                nonlocal ticks
                while not done.is_set():
                    ticks += 1
                    await asyncio.sleep(0)

            ticker = asyncio.ensure_future(tick())
            await asyncio.sleep(0)
            before = ticks
            streaming = await printer.print(job, history=False)
            done.set()
            await ticker
            streaming.stop()
            with contextlib.suppress(rh.HostError):
                await streaming.wait()
            return ticks - before

    with BuiltInFake(tmp_path / "fake.log") as fake:
        assert asyncio.run(scenario(fake.port)) > 0  # it was 0: print() held the loop


def test_file_work_runs_in_another_process_and_a_dead_worker_is_replaced() -> None:
    # The server's checks and analyses run here: a thread would share the interpreter's
    # lock with the event loop (every printer's stream) for as long as a big file takes.
    try:
        assert in_worker(os.getpid) != os.getpid()
        with pytest.raises(rh.JobError, match="the process reading the file ended"):
            in_worker(os._exit, 3)  # a worker killed (out of memory, kill -9) mid-work
        assert in_worker(os.getpid) != os.getpid()  # new workers for the next file
    finally:
        stop_workers()


def _workers_of(pid: int) -> list[int]:
    """The server's file workers (its children started by multiprocessing's spawn)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            command_line = (stat.parent / "cmdline").read_bytes()
            if parent == pid and b"spawn_main" in command_line:
                found.append(int(stat.parent.name))
    return found


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.slow
def test_the_servers_file_workers_are_replaced_when_killed_and_end_with_it(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"idle": bench().port})
    assert server.process is not None
    with server.client() as client:
        first = client.post("/v1/files", files={"file": ("a.gcode", "G28\nG1 X1\n")})
        assert first.status_code == 201, first.text
        workers = wait_for(lambda: _workers_of(server.process.pid), what="a file worker")
        for pid in workers:
            os.kill(pid, signal.SIGKILL)
        second = client.post("/v1/files", files={"file": ("b.gcode", "G28\nG1 X1\nG1 X2\n")})
        assert second.status_code == 201, second.text
        checked = client.get("/v1/files/b.gcode/check").json()
        assert (checked["errors"], checked["lines"]) == (0, 3)
        workers = wait_for(lambda: _workers_of(server.process.pid), what="new file workers")
    server.stop(signal.SIGKILL)  # no shutdown of its own: the workers see it gone
    wait_for(lambda: all(_gone(pid) for pid in workers), timeout=10, what="the workers ending")
