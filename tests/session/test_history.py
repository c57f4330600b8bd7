"""The print history folder: each run's outcome record, ``hyrel-send --history-list``, and
the pruning to ``[host] history_max_mb``; through real hyrel-send processes on the
built-in fake, and the history module's pure parts on their own."""

from __future__ import annotations

import dataclasses
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from repetrel_host.errors import ControllerError, JobError, LinkError
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session import history
from repetrel_host.session.job import Job
from tests.support.helpers import CONE, EXAMPLE, hyrel_send, start_streaming

pytestmark = pytest.mark.timeout(60)


def record(**changes: object) -> history.Record:
    values: dict[str, object] = {
        "job": "cube.gcode",
        "outcome": history.COMPLETED,
        "lines": 12,
        "seconds": 3.25,
        "where": "the last line the controller acknowledged is cube.gcode:14 (command 12 "
        "of the job, M84)",
        "port": "/dev/ttyACM0",
        "started": "2025-03-04T10:11:12",
        "ended": "2025-03-04T10:11:15",
    }
    values.update(changes)
    return history.Record(**values)  # type: ignore[arg-type]


def progress(**changes: object) -> history.RunProgress:
    values: dict[str, object] = {
        "job": "cube.gcode",
        "path": "/jobs/cube.gcode",
        "command": ("cube.gcode", "--port", "/dev/ttyACM0", "--from-line", "5"),
        "cwd": "/jobs",
        "pid": os.getpid(),
        "process": history.process_identity(os.getpid()),
        "host": history.this_host(),
        "port": "/dev/ttyACM0",
        "started": "2025-03-04T10:11:12",
        "updated": "2025-03-04T10:11:15",
        "seconds": 3.25,
        "lines": 12,
        "where": "the last line the controller acknowledged is cube.gcode:14 (command 12 "
        "of the job, G1 X5)",
        "acknowledged": 14,
        "resume_line": 15,
        "known_to_run": False,
        "all_sent": False,
        "sent": 20,
        "stream_bytes": 0,
    }
    values.update(changes)
    return history.RunProgress(**values)  # type: ignore[arg-type]


def a_dead_process() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def make_run(folder: Path, stamp: str, job: str, size: int, with_record: bool = True) -> Path:
    """A run as the session leaves it: the stream, its record, a report and snapshots."""
    folder.mkdir(parents=True, exist_ok=True)
    stream = folder / f"{stamp}-{job}.gcode"
    stream.write_bytes(b"G1 X1\n" * (size // 6))
    if with_record:
        history.write_record(stream, record(job=f"{job}.gcode"))
    (folder / f"{stamp}-{job}-report.txt").write_text("Print time: 1 s\n")
    snapshots = folder / f"{stamp}-{job}-snapshots"
    snapshots.mkdir()
    (snapshots / "0001.jpg").write_bytes(b"\xff" * 100)
    old = time.time() - 2 * history.STILL_RUNNING
    os.utime(stream, (old, old))
    return stream


# --- the pure parts -----------------------------------------------------------------


def test_a_record_reads_back_and_garbage_is_no_record(tmp_path: Path) -> None:
    stream = tmp_path / "20250304-101112-cube.gcode"
    written = record(outcome=history.FAILED, error="the serial link was lost", error_kind="x")
    history.write_record(stream, written)
    assert history.record_path(stream) == tmp_path / "20250304-101112-cube.json"
    assert history.read_record(stream) == written
    assert [p.name for p in tmp_path.iterdir()] == ["20250304-101112-cube.json"]  # no .part
    for text in ("{", "[]", '{"job": "x"}', ""):
        assert history.Record.from_json(text) is None
    assert history.read_record(tmp_path / "20250304-101113-none.gcode") is None


def test_a_printers_paces_are_its_runs_on_that_port_and_machine_newest_first(
    tmp_path: Path,
) -> None:
    runs = [
        ("20250304-101112", "/dev/ttyACM0", "hydra-16a", 1.10),
        ("20250305-101112", "/dev/ttyACM1", "hydra-16a", 2.00),  # another printer
        ("20250306-101112", "/dev/ttyACM0", "esr", 3.00),  # another machine profile
        ("20250307-101112", "/dev/ttyACM0", "hydra-16a", None),  # too short to tell
        ("20250308-101112", "/dev/ttyACM0", "hydra-16a", 1.20),
    ]
    for stamp, port, machine, pace in runs:
        stream = tmp_path / f"{stamp}-cube.gcode"
        stream.write_text("G1 X1\n")
        history.write_record(stream, record(port=port, machine=machine, pace=pace))
    assert list(history.paces(tmp_path, "/dev/ttyACM0", "hydra-16a")) == [1.20, 1.10]
    assert list(history.paces(tmp_path / "none", "/dev/ttyACM0", "hydra-16a")) == []


def test_a_progress_reads_back_in_the_records_place_until_the_record_replaces_it(
    tmp_path: Path,
) -> None:
    stream = tmp_path / "20250304-101112-cube.gcode"
    kept = progress()
    assert history.write_progress(stream, kept)
    assert history.read_state(stream) == kept
    assert history.read_record(stream) is None  # no outcome yet
    assert [p.name for p in tmp_path.iterdir()] == ["20250304-101112-cube.json"]
    written = record()
    history.write_record(stream, written)
    assert history.read_state(stream) == written == history.read_record(stream)
    for text in ("{", '{"outcome": "streaming"}', '{"outcome": "streaming", "command": 1}'):
        assert history.RunProgress.from_json(text) is None
    # A record that says "streaming" is no record.
    assert history.Record.from_json(dataclasses.replace(written, outcome="streaming").to_json())
    history.write_record(stream, dataclasses.replace(written, outcome="streaming"))
    assert history.read_state(stream) is None
    assert not history.write_progress(tmp_path / "none" / "20250304-101112-x.gcode", kept)


def test_a_progress_process_is_alive_gone_or_another_machines() -> None:
    assert history.is_alive(progress()) is True
    assert history.is_alive(progress(pid=a_dead_process())) is False
    if history.process_identity(os.getpid()):  # Linux: a number given to a later process
        assert history.is_alive(progress(process="another boot:1")) is False
    assert history.is_alive(progress(host="elsewhere")) is None


def test_a_streaming_and_a_killed_run_in_one_line() -> None:
    run = history.parse_run(Path("20250304-101112-cube.gcode"))
    assert run is not None
    where = progress().where
    assert history.describe(run, None, progress(), alive=True) == (
        f"2025-03-04 10:11:12  cube.gcode  streaming (process {os.getpid()}): 12 lines "
        f"acknowledged in 3.2 s so far; {where}"
    )
    assert history.describe(run, None, progress(), alive=False) == (
        "2025-03-04 10:11:12  cube.gcode  killed (its host stopped while it streamed: no safe "
        f"stop went): 12 lines acknowledged in 3.2 s; {where}"
    )
    elsewhere = history.describe(run, None, progress(host="lab2"), alive=None)
    assert f"  cube.gcode  streaming on lab2 (process {os.getpid()}), or its host " in elsewhere
    entry = history.Entry(run, None, progress(), alive=False)
    assert entry.killed and not history.Entry(run, None, progress(), alive=None).killed


def test_the_stream_after_a_progress_record(tmp_path: Path) -> None:
    stream = tmp_path / "s.gcode"
    stream.write_bytes(b"N1 G28*18\nN2 G1 X1*99\nN3 G1 X2*98\n")
    assert history.lines_after(stream, 0) == 3
    assert history.lines_after(stream, 10) == 2
    assert history.lines_after(stream, stream.stat().st_size) == 0
    assert history.lines_after(tmp_path / "none", 0) is None


def test_error_kinds_are_hyrel_sends() -> None:
    assert history.error_kind(LinkError("x")) == "link failure"
    assert history.error_kind(ControllerError("x")) == "controller error"
    assert history.error_kind(JobError("x")) == "error"


def test_run_names() -> None:
    run = history.parse_run(Path("h/20250304-101112-my-part.v2.gcode"))
    assert run is not None and run.job == "my-part.v2"
    assert f"{run.started:%Y-%m-%d %H:%M:%S}" == "2025-03-04 10:11:12"
    for name in ("notes.gcode", "20250304-101112-x-reports.log", "20251304-101112-x.gcode"):
        assert history.parse_run(Path(name)) is None


def test_each_outcome_in_one_line() -> None:
    run = history.parse_run(Path("20250304-101112-cube.gcode"))
    assert run is not None
    assert history.describe(run, record()) == (
        "2025-03-04 10:11:12  cube.gcode  completed: 12 lines acknowledged in 3.2 s; the "
        "last line the controller acknowledged is cube.gcode:14 (command 12 of the job, M84)"
    )
    cancelled = history.describe(run, record(outcome=history.CANCELLED))
    assert "  cube.gcode  cancelled: 12 lines acknowledged in 3.2 s; the last line" in cancelled
    error = "no answer from the controller for 2 s; " + record().where
    failed = history.describe(
        run, record(outcome=history.FAILED, error=error, error_kind="link failure")
    )
    assert failed == (
        f"2025-03-04 10:11:12  cube.gcode  failed: link failure: {error}; 12 lines "
        "acknowledged in 3.2 s"
    )  # the last line once, in the error's sentence
    assert history.describe(run, None) == (
        "2025-03-04 10:11:12  cube  unknown (no record: the host stopped before the job ended)"
    )


def test_the_oldest_runs_go_first_never_the_kept_ones() -> None:
    a, b, c, d = (Path(n) for n in "abcd")
    sizes = [(a, 10), (b, 20), (c, 30), (d, 40)]
    assert history.to_remove(sizes, 100, 100, []) == []
    assert history.to_remove(sizes, 100, 75, []) == [a, b]
    assert history.to_remove(sizes, 100, 75, [a]) == [b, c]
    assert history.to_remove(sizes, 100, 0, [d]) == [a, b, c]  # d is never removed


def test_prune_removes_whole_runs_and_nothing_else(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    first = make_run(folder, "20250101-080000", "a", 6000)
    second = make_run(folder, "20250102-080000", "b", 6000)
    killed = make_run(folder, "20250103-080000", "c", 6000, with_record=False)
    running = make_run(folder, "20250104-080000", "d", 6000, with_record=False)
    os.utime(running)  # written to just now: another process may be streaming it
    current = make_run(folder, "20250105-080000", "e", 6000)
    (folder / "notes.txt").write_text("mine\n")
    assert history.prune(folder, 0, current) == []  # 0: no limit
    removed = history.prune(folder, 0.02, current)
    assert removed == [first, second]
    left = sorted(p.name for p in folder.iterdir())
    assert not [name for name in left if name.startswith(("20250101", "20250102"))]
    assert killed.exists() and running.exists() and current.exists()
    assert "notes.txt" in left and "20250103-080000-c-snapshots" in left
    # Below its limit, a folder is left alone; past it, only the kept ones stay.
    assert history.prune(folder, 1, current) == []
    assert history.prune(folder, 0.000001, current) == [killed]
    assert running.exists() and current.exists()


def test_prune_keeps_a_run_whose_process_still_streams_however_old(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    killed = make_run(folder, "20250101-080000", "a", 6000, with_record=False)
    history.write_progress(killed, progress(pid=a_dead_process()))
    paused = make_run(folder, "20250102-080000", "b", 6000, with_record=False)
    history.write_progress(paused, progress())  # this process: alive
    current = make_run(folder, "20250105-080000", "e", 6000)
    assert history.prune(folder, 0.000001, current) == [killed]
    assert paused.exists()


def test_history_list_is_newest_first_and_short(tmp_path: Path) -> None:
    for day in range(1, 24):
        make_run(tmp_path, f"202501{day:02d}-080000", f"part{day}", 6)
    lines = history.history_list(tmp_path)
    assert len(lines) == history.LIST_LENGTH == 20
    assert lines[0].startswith("2025-01-23 08:00:00  part23.gcode  completed")
    assert lines[-1].startswith("2025-01-04 08:00:00  part4.gcode")
    assert history.history_list(tmp_path / "none") == []


# --- hyrel-send on the built-in fake, as real processes -------------------------------


def history_list(folder: Path, *args: str) -> list[str]:
    result = hyrel_send("--history-list", "--history", str(folder), *args)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == f"Print history in {folder} (newest first):"
    return lines[1:]


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_history_list_after_a_completed_and_a_failed_run(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    result = hyrel_send("--history-list", "--history", str(folder))
    assert result.returncode == 0
    assert result.stdout.strip() == f"no prints in {folder} yet"
    done = hyrel_send(str(EXAMPLE), "--history", str(folder))
    assert done.returncode == 0, done.stderr
    hang = tmp_path / "hang.gcode"
    hang.write_text("G28\nG1 X1\n!!DEBUG:hang\nG1 X2\n")
    failed = hyrel_send(
        str(hang), "--history", str(folder), "--reply-timeout", "1", "--reconnect-wait", "1"
    )
    assert failed.returncode == 5
    newest, oldest = history_list(folder)
    error = failed.stderr.strip().splitlines()[-1].removeprefix("not safe: ")
    assert newest.endswith(
        f"  hang.gcode  failed: not safe: {error}; 2 lines acknowledged in "
        f"{newest.rsplit(' in ', 1)[1]}"
    )
    assert "the last line the controller acknowledged is hang.gcode:2" in newest
    assert " square-tube.gcode  completed: 334 lines acknowledged in " in oldest
    assert oldest.endswith("the last line the controller acknowledged is square-tube.gcode:353 "
                           "(command 334 of the job, M84)")  # fmt: skip
    # The record names the port and the times too.
    (stream,) = folder.glob("*-square-tube.gcode")
    saved = history.read_record(stream)
    assert saved is not None and saved.port == "fake" and saved.started <= saved.ended


@pytest.mark.timeout(60)
def test_history_list_offers_a_killed_runs_resume(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    folder.mkdir()
    gone = a_dead_process()
    hyrel = folder / "20250304-101112-cube.gcode"
    hyrel.write_bytes(b"N1 G28\n" * 10)
    history.write_progress(
        hyrel,
        progress(pid=gone, stream_bytes=35, cwd=os.getcwd(), resume_line=9, known_to_run=True),
    )
    library = folder / "20250305-101112-cube.gcode"
    library.write_bytes(b"")
    history.write_progress(library, progress(pid=gone, command=(), cwd=os.getcwd()))
    unsent = folder / "20250306-101112-cube.gcode"
    unsent.write_bytes(b"N1 G28\n")
    history.write_progress(unsent, progress(pid=gone, resume_line=None, sent=0, lines=0))
    done = folder / "20250307-101112-cube.gcode"
    done.write_bytes(b"")
    history.write_progress(done, progress(pid=gone, resume_line=None, all_sent=True))
    streaming = folder / "20250308-101112-cube.gcode"
    streaming.write_bytes(b"")
    history.write_progress(streaming, progress())
    lines = history_list(folder)
    assert lines[0].startswith("2025-03-08 10:11:12  cube.gcode  streaming (process ")
    assert lines[1].startswith("2025-03-07 10:11:12  cube.gcode  killed (its host stopped")
    assert lines[2] == "  nothing to resume: every line of the job was acknowledged"
    assert lines[4] == (
        "  no line is known to have run: to start again (uncertain: no line of the job was "
        "sent when last recorded; the stream has 1 lines after that, sent later): cd /jobs && "
        "hyrel-send cube.gcode --port /dev/ttyACM0 --from-line 5"
    )
    assert lines[6] == (
        "  to resume (uncertain: lines up to 20 were sent and may have run): "
        "print('/jobs/cube.gcode', from_line=15)"
    )  # a library user's run: no command line
    assert lines[8] == (
        "  to resume (uncertain: lines up to 20 were sent and may have run; the stream has 5 "
        "lines after that, sent later): hyrel-send cube.gcode --port /dev/ttyACM0 --from-line 9"
    )
    assert len(lines) == 9


def start_on_the_builtin_fake(job: Path, folder: Path, log: Path) -> subprocess.Popen[str]:
    """hyrel-send on the built-in fake (logging to ``log``), once lines are executing."""
    environment = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    environment["TMPDIR"] = str(log.parent)  # the fake's pty folder, should the host be killed
    process = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", str(job), "--history", str(folder),
         "--fake-log", str(log)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        env=environment,
    )  # fmt: skip
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 2000):
        time.sleep(0.05)
    return process


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_history_list_after_ctrl_c_and_after_a_killed_host(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    process = start_on_the_builtin_fake(CONE, folder, tmp_path / "cancelled.log")
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 130, stderr
    assert f"The fake controller's log of executed commands: {tmp_path / 'cancelled.log'}" in (
        stdout
    )
    (cancelled,) = history_list(folder)
    assert f"  {CONE.name}  cancelled: " in cancelled
    assert f"the last line the controller acknowledged is {CONE.name}:" in cancelled

    process = start_on_the_builtin_fake(CONE, folder, tmp_path / "killed.log")
    process.kill()  # no Ctrl-C, no safe stop: the host is gone
    process.communicate(timeout=30)
    killed, resume, _ = history_list(folder)
    assert f"  {CONE.name}  killed (its host stopped while it streamed: no safe stop went): " in (
        killed
    )
    # Killed at once: the record may still say no line ran (then it starts again).
    assert resume.startswith(("  to resume (uncertain: ", "  no line is known to have run: "))
    assert f"): hyrel-send {CONE} --history {folder} --fake-log " in resume


def stream_commands(stream: Path) -> list[str]:
    """The commands of a kept stream, without their framing (N<n>, *checksum, Hyrel's
    control bytes)."""
    text = stream.read_bytes().decode("ascii")
    lines = (re.sub(r"[\x00-\x1f]", "", line) for line in text.split("\n"))
    return [re.sub(r"^N\d+ |\*\d+$", "", line) for line in lines if line]


def drained(fake: BuiltInFake) -> None:
    """Wait until the fake ran what it holds (the host is gone: nothing more comes)."""
    done = -1
    for _ in range(60):
        commands = fake.request("status")["commands"]
        if commands == done:
            return
        done = commands
        time.sleep(0.5)


@pytest.mark.timeout(90)
@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_a_killed_host_left_all_it_sent_in_the_stream_and_a_resume_that_skips_nothing(
    tmp_path: Path, protocol: str
) -> None:
    folder, log = tmp_path / "history", tmp_path / "fake.log"
    fake_args = ["--move-time", "0.005"]
    link = ["--protocol", "hyrel"] if protocol == "hyrel" else []
    with BuiltInFake(log, [*fake_args, *link], control=True) as fake:
        args = ["--history", str(folder), *link]
        process = start_streaming(CONE, fake.port, log, *args)
        try:
            time.sleep(1.2)  # the progress record rewritten since the start
            (streaming,) = history_list(folder)
            assert f"  {CONE.name}  streaming (process {process.pid}): " in streaming
        finally:
            process.kill()  # kill -9: no safe stop, no record
            process.communicate(timeout=30)
        drained(fake)
    (stream,) = folder.glob("*.gcode")
    executed = log.read_text().splitlines()
    kept = stream_commands(stream)
    # The greeting (M110, M115...) came before the job's stream began.
    start = next(i for i, command in enumerate(executed) if command == kept[0])
    assert start <= 5, executed[:10]
    # Every command the controller executed is in the stream, in order (with what went
    # again after a resend request, and what was sent but not yet run, besides).
    position = 0
    for number, command in enumerate(executed[start:]):
        while position < len(kept) and kept[position] != command:
            position += 1
        assert position < len(kept), (
            f"executed command {number} ({command}) is not in the kept stream, which ends "
            f"{kept[-3:]}, {len(executed) - start - number} commands before the controller"
        )
        position += 1
    # The first job line the controller did not run...
    job = list(Job(CONE).lines())
    ran = 0
    for command in executed[start:]:
        if ran < len(job) and job[ran].command == command:
            ran += 1
    assert 0 < ran < len(job)
    not_run = job[ran].source_line
    killed, resume = history_list(folder)
    assert f"  {CONE.name}  killed (its host stopped while it streamed: no safe stop went): " in (
        killed
    )
    # ... is not skipped by the resume offered: what may have run is said to be uncertain.
    match = re.fullmatch(
        r"  to resume \(uncertain: lines up to (\d+) were sent and may have run(; .*)?\): (.*)",
        resume,
    )
    assert match is not None, resume
    command = shlex.split(match[3])
    expected = [str(CONE), "--port", fake.port, "--history", str(folder), *link]
    assert command[:-2] == ["hyrel-send", *expected] and command[-2] == "--from-line"
    from_line = int(command[-1])
    assert 1 < from_line <= not_run
    assert int(match[1]) >= from_line - 1


@pytest.mark.timeout(90)
@pytest.mark.slow
def test_the_oldest_runs_are_pruned_to_the_configured_size(tmp_path: Path) -> None:
    folder = tmp_path / "history"
    config = tmp_path / "config.toml"
    # Two square-tube runs (11.5 KB each) are more than 18 KB; one and a small run are not
    # (nor one and the first lines of the next, when that one starts).
    config.write_text(f'[host]\nhistory_dir = "{folder}"\nhistory_max_mb = 0.018\n')
    jobs = []
    for name, text in (
        ("1-first", EXAMPLE.read_text()),
        ("2-second", EXAMPLE.read_text()),
        ("3-small", "G28\nG1 X1\n"),
    ):
        job = tmp_path / f"{name}.gcode"
        job.write_text(text)
        jobs.append(job)
        result = hyrel_send(str(job), "--config", str(config))
        assert result.returncode == 0, result.stderr
        assert history_list(folder, "--config", str(config))[0].split("  ")[1] == job.name
    names = [line.split("  ")[1] for line in history_list(folder, "--config", str(config))]
    assert names == ["3-small.gcode", "2-second.gcode"]
    assert not list(folder.glob("*-1-first*"))  # its stream and its record


def test_a_bad_limit_is_a_configuration_error(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text("[host]\nhistory_max_mb = -1\n")
    result = hyrel_send("--history-list", "--config", str(config))
    assert result.returncode == 2
    assert result.stderr.startswith(f"error: {config}: host.history_max_mb: ")
