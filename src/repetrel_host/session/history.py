"""The print history folder: each run's files, its outcome record, the list, the pruning.

A *run* is a stream as transmitted, ``<date>-<time>-<job>.gcode`` (see
``planning.history_file``), and its siblings under the same stem: ``-reports.log``
(M719), ``-report.txt`` (the M773 job report), ``-snapshots/`` (M791, M790) and the
outcome record ``.json`` the session writes when the job ends. While the job streams,
that file holds its progress instead (:class:`RunProgress`: the process, the command line,
the last lines acknowledged and sent), rewritten at most every :data:`PROGRESS_INTERVAL`
and replaced by the record at the end: a run left with its progress, its process gone,
was killed (``kill -9``, a power cut) and can be recovered from there, uncertainly. A run
with neither is one whose host stopped before its first line went.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import socket
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, fields
from datetime import datetime
from pathlib import Path
from typing import Any

from repetrel_host.errors import ControllerError, HostError, LinkError, ProtocolError, SafeStopError
from repetrel_host.session.job import JobLine

log = logging.getLogger(__name__)

STREAM_SUFFIX = ".gcode"
RECORD_SUFFIX = ".json"
# What else a run leaves beside its stream, under its stem (the console's, the session's).
SIBLING_SUFFIXES = ("-reports.log", "-report.txt", "-snapshots", RECORD_SUFFIX)
RUN_NAME = re.compile(r"^(?P<date>\d{8})-(?P<time>\d{6})-(?P<job>.*)\.gcode$")
LIST_LENGTH = 20  # hyrel-send --history-list: the newest runs
# A run without a record written to this recently may still be streaming (another
# printer or process sharing the folder): never pruned.
STILL_RUNNING = 3600.0
NO_RECORD = "unknown (no record: the host stopped before the job ended)"
COMPLETED, CANCELLED, FAILED = "completed", "cancelled", "failed"
STREAMING = "streaming"  # the outcome of a progress record: the job had not ended
# A streaming run's progress record is rewritten this often while lines are acknowledged.
PROGRESS_INTERVAL = 0.5
# --history-list counts the stream's lines after the last progress record up to this far.
TAIL_LIMIT = 8_000_000


@dataclass(frozen=True, slots=True)
class Record:
    """How a run ended, as the session writes it beside the stream (``<run>.json``)."""

    job: str  # the job's file name
    outcome: str  # completed, cancelled, failed
    lines: int  # job lines acknowledged
    seconds: float
    where: str  # the last line the controller acknowledged (PrintJob.where())
    port: str
    started: str  # ISO 8601, local time
    ended: str
    error: str = ""  # the failure's sentence
    error_kind: str = ""  # link failure, controller error, error
    machine: str = ""  # the machine profile's name
    # Actual over planned moving time (gcode.timeline's TimeLeft.measured): what the next
    # job on this printer expects; None when too little of the run was watched.
    pace: float | None = None
    # Its heaters' climbs, degrees a second by kind (gcode.heat_rates): the next job's heat
    # waits are planned at them.
    heat_rates: dict[str, float] | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1) + "\n"

    @classmethod
    def from_json(cls, text: str) -> Record | None:
        """The record in ``text``; None when it is not one (cut short, another program's)."""
        try:
            data = json.loads(text)
        except ValueError:
            return None
        if not isinstance(data, dict):
            return None
        names = {f.name for f in fields(cls)}
        try:
            return cls(**{k: v for k, v in data.items() if k in names})
        except TypeError:  # a field missing
            return None


def records(folder: Path, port: str, machine: str | None = None) -> Iterator[Record]:
    """The records of the runs in ``folder`` on ``port`` (with ``machine``, when given),
    newest first, read as they are asked for."""
    for run in reversed(runs(folder)):
        record = read_record(run.stream)
        if record is not None and record.port == port and machine in (None, record.machine):
            yield record


def paces(folder: Path, port: str, machine: str) -> Iterable[float]:
    """The paces of the runs in ``folder`` on ``port`` with ``machine``, newest first."""
    return (r.pace for r in records(folder, port, machine) if r.pace is not None)


def last_machine(folder: Path, port: str) -> str | None:
    """The machine profile the newest run in ``folder`` on ``port`` ran with (None: none)."""
    return next((r.machine for r in records(folder, port) if r.machine), None)


def heat_rates(folder: Path, port: str, machine: str) -> Iterable[dict[str, float]]:
    """The heat rates the runs in ``folder`` on ``port`` with ``machine`` timed, newest first."""
    return (r.heat_rates for r in records(folder, port, machine) if r.heat_rates)


def error_kind(error: HostError) -> str:
    """The failure's kind as hyrel-send names it (and its exit code tells)."""
    if isinstance(error, SafeStopError):
        return "not safe"
    if isinstance(error, LinkError):
        return "link failure"
    if isinstance(error, ControllerError | ProtocolError):
        return "controller error"
    return "error"


def record_path(stream: Path) -> Path:
    """Where a run's outcome record goes: beside its stream, ``<run>.json``."""
    return stream.with_name(stream.stem + RECORD_SUFFIX)


def write_record(stream: Path, record: Record) -> None:
    """Write the record whole or not at all (a reader never sees half of one)."""
    path = record_path(stream)
    partial = path.with_name(path.name + ".part")
    try:
        partial.write_text(record.to_json(), encoding="utf-8")
        os.replace(partial, path)
    except OSError as exc:
        log.warning("cannot write the run's record %s: %s", path, exc.strerror)
        with contextlib.suppress(OSError):
            partial.unlink()


def read_record(stream: Path) -> Record | None:
    """How the run ended; None while it streams, or when its host stopped first."""
    found = read_state(stream)
    return found if isinstance(found, Record) else None


def read_state(stream: Path) -> Record | RunProgress | None:
    """The run's record, or its progress (a job that had not ended), or None."""
    try:
        text = record_path(stream).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    progress = RunProgress.from_json(text)
    if progress is not None:
        return progress
    record = Record.from_json(text)
    return record if record is not None and record.outcome != STREAMING else None


# --- a streaming run's progress ----------------------------------------------------


@dataclass(frozen=True, slots=True)
class RunProgress:
    """Where a job stood as it streamed, in ``<run>.json`` until its record replaces it."""

    job: str  # the job's file name
    path: str  # the job's path, absolute
    command: tuple[str, ...]  # hyrel-send's arguments; () for a library user's run
    cwd: str  # where they were given
    pid: int  # the host's process
    process: str  # that process's identity (boot and start time), "" where unknown
    host: str  # the machine it runs on
    port: str
    started: str  # ISO 8601, local time
    updated: str
    seconds: float  # since the start, when this was written
    lines: int  # job lines acknowledged
    where: str  # the last line the controller acknowledged (PrintJob.where())
    acknowledged: int  # the source line of the last job line acknowledged; 0: none
    # PrintJob.recovery_line: where a recovery starts (the stored key keeps the user's word)
    resume_line: int | None
    known_to_run: bool  # resume_line follows a line known to have run (Hyrel's link)
    all_sent: bool  # the job was read to its end (PrintJob.all_sent)
    sent: int  # the source line of the last job line transmitted; 0: none
    stream_bytes: int  # the kept stream's size when this was written
    outcome: str = STREAMING

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1) + "\n"

    @classmethod
    def from_json(cls, text: str) -> RunProgress | None:
        """The progress in ``text``; None when it is none (a record, cut short...)."""
        try:
            data = json.loads(text)
        except ValueError:
            return None
        if not isinstance(data, dict) or data.get("outcome") != STREAMING:
            return None
        command = data.get("command")
        if not isinstance(command, list) or not all(isinstance(a, str) for a in command):
            return None
        values: dict[str, Any] = {f.name: data[f.name] for f in fields(cls) if f.name in data}
        values["command"] = tuple(command)
        try:
            return cls(**values)
        except TypeError:  # a field missing
            return None


def write_progress(stream: Path, progress: RunProgress) -> bool:
    """Write the progress whole or not at all, as :func:`write_record`; False on failure
    (not logged: the caller says so once, not every time)."""
    path = record_path(stream)
    partial = path.with_name(path.name + ".part")
    try:
        partial.write_text(progress.to_json(), encoding="utf-8")
        os.replace(partial, path)
    except OSError:
        with contextlib.suppress(OSError):
            partial.unlink()
        return False
    return True


def process_identity(pid: int) -> str:
    """What tells process ``pid`` from a later one given the same number: the boot's id
    and the process's start time (Linux's /proc); "" where that cannot be read."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    after_name = stat.rsplit(")", 1)[-1].split()
    return f"{boot}:{after_name[19]}" if len(after_name) > 19 else ""  # field 22: starttime


def this_host() -> str:
    return socket.gethostname()


def is_alive(progress: RunProgress) -> bool | None:
    """Whether the process streaming the run is still there; None when that cannot be
    told from here (another machine's)."""
    return process_alive(progress.host, progress.pid, progress.process)


def process_alive(host: str, pid: int, process: str) -> bool | None:
    """Whether process ``pid`` of ``host`` (its :func:`process_identity` ``process``) is
    still there; None when that cannot be told from here (another machine's)."""
    if host != this_host():
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: there
    except OSError:
        return None
    identity = process_identity(pid)
    return not (process and identity and identity != process)


class ProgressKeeper:
    """A streaming run's progress, written to its record's place (``<run>.json``) when it
    moved; the session calls :meth:`update` every :data:`PROGRESS_INTERVAL`, and the
    outcome record replaces it at the end."""

    def __init__(
        self,
        stream: Path,
        job: Path,
        command: Iterable[str],
        port: str,
        started: datetime,
        sent_before: object = None,
    ) -> None:
        self.stream = stream
        self.started = started
        self.sent: JobLine | None = None  # the job's last line transmitted
        self._sent_before = sent_before  # the dialect's last_sent as the job began
        pid = os.getpid()
        self._fixed: dict[str, Any] = {
            "job": job.name,
            "path": str(job.absolute()),
            "command": tuple(command),
            "cwd": os.getcwd(),
            "pid": pid,
            "process": process_identity(pid),
            "host": this_host(),
            "port": port,
            "started": started.isoformat(timespec="seconds"),
        }
        self._written: tuple[object, ...] | None = None
        self._warned = False

    def update(
        self,
        lines: int,
        where: str,
        acknowledged: int,
        recovery_line: int | None,
        known_to_run: bool,
        all_sent: bool,
        last_sent: object,
    ) -> None:
        """Write the progress if it moved since it was last written (``last_sent``: the
        dialect's, the last line transmitted: a job line of this job is kept)."""
        if (
            isinstance(last_sent, JobLine)
            and last_sent.index
            and last_sent is not self._sent_before
        ):
            self.sent = last_sent
        sent = self.sent
        key = (lines, acknowledged, recovery_line, sent.index if sent else 0, all_sent)
        if key == self._written:
            return
        now = datetime.now()
        try:
            stream_bytes = self.stream.stat().st_size
        except OSError:
            stream_bytes = 0
        progress = RunProgress(
            **self._fixed,
            updated=now.isoformat(timespec="seconds"),
            seconds=round((now - self.started).total_seconds(), 3),
            lines=lines,
            where=where,
            acknowledged=acknowledged,
            resume_line=recovery_line,
            known_to_run=known_to_run,
            all_sent=all_sent,
            sent=sent.source_line if sent is not None else 0,
            stream_bytes=stream_bytes,
        )
        if write_progress(self.stream, progress):
            self._written = key
        elif not self._warned:
            self._warned = True
            log.warning("cannot write the run's progress %s", record_path(self.stream))


def lines_after(stream: Path, offset: int) -> int | None:
    """Lines in ``stream`` past byte ``offset`` (what went after a progress record was
    written); None when that is more than :data:`TAIL_LIMIT` bytes, or unreadable."""
    try:
        with stream.open("rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            if size - offset > TAIL_LIMIT:
                return None
            handle.seek(max(offset, 0))
            return handle.read().count(b"\n")
    except OSError:
        return None


@dataclass(frozen=True, slots=True)
class RecordedRun:
    """One run in the history folder."""

    stream: Path
    started: datetime  # from its name
    job: str  # from its name (the job's stem)

    @property
    def files(self) -> list[Path]:
        """The stream and the siblings it left (that exist)."""
        candidates = [self.stream] + [
            self.stream.with_name(self.stream.stem + suffix) for suffix in SIBLING_SUFFIXES
        ]
        return [path for path in candidates if path.exists()]


def parse_run(path: Path) -> RecordedRun | None:
    """The run a file name stands for; None for any other file."""
    match = RUN_NAME.match(path.name)
    if match is None:
        return None
    try:
        started = datetime.strptime(match["date"] + match["time"], "%Y%m%d%H%M%S")
    except ValueError:
        return None
    return RecordedRun(path, started, match["job"])


def runs(folder: Path) -> list[RecordedRun]:
    """The runs in ``folder``, oldest first (by their names' date and time)."""
    try:
        entries = list(folder.iterdir())
    except OSError:
        return []
    found = [run for path in entries if (run := parse_run(path)) is not None]
    return sorted(found, key=lambda run: (run.started, run.stream.name))


# --- the list -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Entry:
    """One run as ``--history-list`` shows it: its record, or its progress and whether
    its process is alive (None: on another machine)."""

    run: RecordedRun
    record: Record | None
    progress: RunProgress | None
    alive: bool | None = None

    @property
    def killed(self) -> bool:
        """Its host stopped while the job streamed (no record, its process gone)."""
        return self.progress is not None and self.alive is False


def entry(run: RecordedRun) -> Entry:
    found = read_state(run.stream)
    if isinstance(found, RunProgress):
        return Entry(run, None, found, is_alive(found))
    return Entry(run, found, None)


def describe(
    run: RecordedRun,
    record: Record | None,
    progress: RunProgress | None = None,
    alive: bool | None = None,
) -> str:
    """One line of ``hyrel-send --history-list``."""
    when = f"{run.started:%Y-%m-%d %H:%M:%S}"
    if progress is not None and record is None:
        counts = f"{progress.lines} lines acknowledged in {progress.seconds:.1f} s"
        if alive:
            state = f"streaming (process {progress.pid}): {counts} so far"
        elif alive is None:
            state = (
                f"streaming on {progress.host} (process {progress.pid}), or its host was "
                f"stopped: {counts} when last told"
            )
        else:
            state = f"killed (its host stopped while it streamed: no safe stop went): {counts}"
        return f"{when}  {progress.job}  {state}; {progress.where}"
    if record is None:
        return f"{when}  {run.job}  {NO_RECORD}"
    counts = f"{record.lines} lines acknowledged in {record.seconds:.1f} s"
    if record.outcome == FAILED:
        kind = f"{record.error_kind}: " if record.error_kind else ""
        where = "" if record.where in record.error else f"; {record.where}"
        outcome = f"failed: {kind}{record.error}{where}; {counts}"
    else:
        outcome = f"{record.outcome}: {counts}; {record.where}"
    return f"{when}  {record.job}  {outcome}"


def history_list(folder: Path, length: int = LIST_LENGTH) -> list[str]:
    """The newest ``length`` runs in ``folder``, newest first, one line each."""
    return [describe(e.run, e.record, e.progress, e.alive) for e in entries(folder, length)]


def entries(folder: Path, length: int = LIST_LENGTH) -> list[Entry]:
    """The newest ``length`` runs in ``folder``, newest first, with what they left."""
    return [entry(run) for run in list(reversed(runs(folder)))[:length]]


# --- pruning --------------------------------------------------------------------


def size_of(path: Path) -> int:
    """Bytes in a file, or in everything under a folder."""
    try:
        if path.is_dir() and not path.is_symlink():
            return sum(size_of(child) for child in path.iterdir())
        return path.lstat().st_size
    except OSError:
        return 0


def to_remove(
    sizes: Sequence[tuple[Path, int]], total: int, limit: int, keep: Iterable[Path]
) -> list[Path]:
    """The oldest runs (``sizes``: each run's stream and its bytes, oldest first) to
    remove so that ``total`` bytes fit in ``limit``; never one in ``keep``."""
    kept = set(keep)
    chosen: list[Path] = []
    for stream, size in sizes:
        if total <= limit:
            break
        if stream in kept:
            continue
        chosen.append(stream)
        total -= size
    return chosen


def prune(folder: Path, limit_mb: float, current: Path, now: float | None = None) -> list[Path]:
    """Remove the oldest runs until ``folder`` holds at most ``limit_mb`` megabytes
    (0: no limit); never ``current`` (the run just started), nor a run that may still
    be streaming. Returns the streams of the runs removed."""
    if limit_mb <= 0:
        return []
    now = time.time() if now is None else now
    found = runs(folder)
    keep = [folder / current.name]  # as the folder lists it, however it was spelt
    keep += [run.stream for run in found if _may_be_running(run, now)]
    sizes = [(run.stream, sum(size_of(path) for path in run.files)) for run in found]
    try:
        total = sum(size_of(path) for path in folder.iterdir())
    except OSError:
        return []
    chosen = to_remove(sizes, total, int(limit_mb * 1e6), keep)
    by_stream = {run.stream: run for run in found}
    for stream in chosen:
        for path in by_stream[stream].files:
            _remove(path)
    if chosen:
        log.info("print history: removed %d oldest runs to stay under %s MB", len(chosen), limit_mb)
    return chosen


def _may_be_running(run: RecordedRun, now: float) -> bool:
    found = read_state(run.stream)
    if isinstance(found, Record):
        return False
    if isinstance(found, RunProgress) and is_alive(found):
        return True  # streaming (paused for hours, perhaps); on another machine: its mtime
    try:
        return now - run.stream.stat().st_mtime < STILL_RUNNING
    except OSError:
        return False


def _remove(path: Path) -> None:
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    except OSError as exc:
        log.warning("print history: cannot remove %s: %s", path, exc.strerror)
