"""The print history folder: each run's files, its outcome record, the list, the pruning.

A *run* is a stream as transmitted, ``<date>-<time>-<job>.gcode`` (see
``planning.history_file``), and its siblings under the same stem: ``-reports.log``
(M719), ``-report.txt`` (the M773 job report), ``-snapshots/`` (M791, M790) and the
outcome record ``.json`` the session writes when the job ends. A run without a record
is one whose host stopped before the job ended (killed, or a power cut).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from datetime import datetime
from pathlib import Path

from repetrel_host.errors import ControllerError, HostError, LinkError, ProtocolError, SafeStopError

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
    try:
        text = record_path(stream).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    return Record.from_json(text)


@dataclass(frozen=True, slots=True)
class Run:
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


def parse_run(path: Path) -> Run | None:
    """The run a file name stands for; None for any other file."""
    match = RUN_NAME.match(path.name)
    if match is None:
        return None
    try:
        started = datetime.strptime(match["date"] + match["time"], "%Y%m%d%H%M%S")
    except ValueError:
        return None
    return Run(path, started, match["job"])


def runs(folder: Path) -> list[Run]:
    """The runs in ``folder``, oldest first (by their names' date and time)."""
    try:
        entries = list(folder.iterdir())
    except OSError:
        return []
    found = [run for path in entries if (run := parse_run(path)) is not None]
    return sorted(found, key=lambda run: (run.started, run.stream.name))


# --- the list -------------------------------------------------------------------


def describe(run: Run, record: Record | None) -> str:
    """One line of ``hyrel-send --history-list``."""
    when = f"{run.started:%Y-%m-%d %H:%M:%S}"
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
    newest = list(reversed(runs(folder)))[:length]
    return [describe(run, read_record(run.stream)) for run in newest]


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


def _may_be_running(run: Run, now: float) -> bool:
    if record_path(run.stream).exists():
        return False
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
