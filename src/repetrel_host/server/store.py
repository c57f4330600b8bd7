"""The print server's queue and history: one SQLite file in the data folder.

Written so that a ``kill -9`` at any moment loses nothing a client was told: WAL
journal, one transaction per change, committed before the answer goes out (WAL with
``synchronous=NORMAL`` survives a crash of the process; ``FULL`` also a power cut, and
is used here: a queue changes a few times a minute). Progress is written every
:data:`PROGRESS_INTERVAL` seconds while a job streams, so after a crash a job knows it
was acknowledged through at least its recorded line.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol

from repetrel_host.gcode.heaters import Heater
from repetrel_host.gcode.timeline import PACE_JOBS
from repetrel_host.protocol.reports import JobReport

PROGRESS_INTERVAL = 0.5  # seconds between progress records of a streaming job
CRASHED = "the server ended while the job was streaming (its safe stop was not sent)"
# The same job's error once its owed safe stop went: the record says what is true now.
CRASHED_SENT = (
    "the server ended while the job was streaming (its safe stop went once the printer "
    "answered again)"
)
REPORT_END = "End M773"  # the report's last line but its stars: it came whole

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    printer TEXT NOT NULL,
    name TEXT NOT NULL,           -- as uploaded
    file TEXT NOT NULL,           -- stored file, relative to the data folder
    state TEXT NOT NULL,
    position REAL NOT NULL,       -- queue order among queued jobs
    submitted REAL NOT NULL,
    started REAL,
    ended REAL,
    lines INTEGER NOT NULL DEFAULT 0,      -- job lines acknowledged (at least)
    last_line INTEGER NOT NULL DEFAULT 0,  -- file line of the last acknowledged one
    total_lines INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    report TEXT,                  -- the controller's M773 report (Hyrel), as it came
    safe_stop TEXT                -- 'owed': not confirmed (goes at the next contact); 'sent'
);
CREATE INDEX IF NOT EXISTS jobs_by_printer ON jobs (printer, state, position);
-- The heaters each printer's session turned on and not yet off, as far as the controller
-- confirmed: JSON [[kind, index, target, command]...]. Written as they change, before the
-- line goes, so that the safe stop owed after a kill -9 turns every one of them off.
-- The name each stored upload was given (before it was cleaned and shortened), by its
-- path: two names that clean alike stay two files; the same name replaces.
CREATE TABLE IF NOT EXISTS uploads (
    path TEXT PRIMARY KEY,
    original TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS heaters (
    printer TEXT PRIMARY KEY,
    heaters TEXT NOT NULL
);
-- Printers whose queue waits for a release (a part may be on the bed), with why and since
-- when: kept across restarts and a kill -9, as the owed safe stop is.
CREATE TABLE IF NOT EXISTS holds (
    printer TEXT PRIMARY KEY,
    reason TEXT NOT NULL,
    since REAL NOT NULL
);
-- (Moonraker's database was kept here, as client_data: moonraker/database_store.py moves it
-- to a file of its own.)
"""
# Columns added since the first schema, added to an older data folder's table as it opens.
_ADDED_COLUMNS = {
    "report": "TEXT",
    "safe_stop": "TEXT",
    "user": "TEXT",
    "filament": "TEXT",
    "from_line": "INTEGER",
    # A farm's job (hyrel-server --farm), claimed for one of this server's printers: its
    # number in the farm and the claim's fencing token. ``version`` counts the record's
    # changes; the farm has been told them up to ``synced_version`` (the outbox: a node
    # cut from the farm's database reports what its printers did once it is back).
    "farm_id": "INTEGER",
    "fence": "INTEGER",
    "version": "INTEGER NOT NULL DEFAULT 0",
    "synced_version": "INTEGER NOT NULL DEFAULT 0",
    # Actual over planned moving time as the job ran (gcode.timeline: TimeLeft.measured):
    # the printer's next jobs expect its pace.
    "pace": "REAL",
    # Its heaters' climbs (gcode.heat_rates), JSON: degrees a second by kind.
    "heat_rates": "TEXT",
}
OWED, SENT = "owed", "sent"


class JobState(StrEnum):
    QUEUED = "queued"
    PRINTING = "printing"
    PAUSED = "paused"
    COMPLETED = "completed"
    CANCELLED = "cancelled"
    FAILED = "failed"
    INTERRUPTED = "interrupted"  # the server stopped (a crash, a kill) while it streamed


ACTIVE = (JobState.PRINTING, JobState.PAUSED)
ENDED = (JobState.COMPLETED, JobState.CANCELLED, JobState.FAILED, JobState.INTERRUPTED)


@dataclass(frozen=True)
class JobRecord:
    id: int
    printer: str
    name: str
    file: str
    state: JobState
    position: float
    submitted: float
    started: float | None
    ended: float | None
    lines: int
    last_line: int
    total_lines: int
    error: str | None
    report: str | None = None  # the M773 report's text
    safe_stop: str | None = None  # OWED: its safe stop was not confirmed; SENT: went later
    user: str | None = None  # who submitted it (the API key's user or app)
    # The filament it used, by tool: JSON {"tool0": {"length": mm, "volume": cm3}}; the
    # file's figures times the share of it acknowledged (an estimate for a stopped job).
    filament: str | None = None
    from_line: int | None = None  # a recovered job: the file's line it starts from
    farm_id: int | None = None  # the farm's job this is (hyrel-server --farm)
    fence: int | None = None  # the farm claim's fencing token
    version: int = 0  # changes made to the record
    synced_version: int = 0  # changes the farm was told
    pace: float | None = None  # actual over planned moving time, as it ran
    heat_rates: str | None = None  # JSON: its heaters' climbs, degrees a second by kind

    @property
    def location(self) -> str:
        """Its file below the uploads, as ``/v1/files`` (and Moonraker's ``gcodes``) name it."""
        return self.file.removeprefix("files/")

    def as_json(self) -> dict[str, object]:
        return {
            "id": self.id,
            "printer": self.printer,
            "name": self.name,
            "path": self.location,
            "state": self.state.value,
            "submitted": self.submitted,
            "started": self.started,
            "ended": self.ended,
            "lines": self.lines,
            "last_line": self.last_line,
            "total_lines": self.total_lines,
            "error": self.error,
            "report": _report_json(self.report),
            "safe_stop": self.safe_stop,
            "user": self.user,
            "filament": json.loads(self.filament) if self.filament else None,
            "from_line": self.from_line,
            "farm_job": self.farm_id,
            "pace": self.pace,
            "heat_rates": json.loads(self.heat_rates) if self.heat_rates else None,
        }


def _report_json(text: str | None) -> dict[str, object] | None:
    """The report as the API shows it: its text, its figures, whether its end came."""
    if text is None:
        return None
    report = JobReport(tuple(text.split("\n")), complete=REPORT_END in text)
    return {"text": report.text, "fields": report.fields, "complete": report.complete}


class JobQueue(Protocol):
    """Where a printer's next job comes from: this server's queue (:class:`Store`), or a
    farm's shared one (``server.farm.FarmNode``). The printer services do not know which."""

    async def take(self, printer: str) -> JobRecord | None:
        """The printer's next job, claimed (printing from now on); None when there is none."""


class Store:
    """The jobs of every printer. Each method is one transaction."""

    def __init__(self, path: Path) -> None:
        self.path = path
        # One connection, used from the server's event loop only.
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)
        with self._transaction() as db:
            have = {row["name"] for row in db.execute("PRAGMA table_info(jobs)")}
            for column, kind in _ADDED_COLUMNS.items():
                if column not in have:
                    db.execute(f"ALTER TABLE jobs ADD COLUMN {column} {kind}")

    def close(self) -> None:
        self._db.close()

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    # --- reading ----------------------------------------------------------------

    def job(self, job_id: int) -> JobRecord | None:
        row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _record(row) if row is not None else None

    def jobs(self, printer: str | None = None) -> list[JobRecord]:
        """Queued jobs in queue order first, then the others, newest first."""
        where, args = ("WHERE printer = ?", (printer,)) if printer is not None else ("", ())
        rows = self._db.execute(
            f"SELECT * FROM jobs {where} ORDER BY state != 'queued', "
            "CASE state WHEN 'queued' THEN position ELSE -id END",
            args,
        ).fetchall()
        return [_record(row) for row in rows]

    def jobs_using(self, file: str) -> list[int]:
        """Jobs queued, printing or paused that print ``file`` (relative to the data folder)."""
        rows = self._db.execute(
            "SELECT id FROM jobs WHERE file = ? AND state IN ('queued', 'printing', 'paused') "
            "ORDER BY id",
            (file,),
        ).fetchall()
        return [row[0] for row in rows]

    def prints(self, file: str) -> dict[str, Any]:
        """OctoPrint's ``prints`` of a file (relative to the data folder): how often it
        ended completed or not, and when and how it last ended."""
        rows = self._db.execute(
            "SELECT printer, state, started, ended FROM jobs WHERE file = ? AND ended IS NOT NULL"
            " AND started IS NOT NULL ORDER BY ended",
            (file,),
        ).fetchall()
        done = [row for row in rows if row["state"] == JobState.COMPLETED]
        answer: dict[str, Any] = {"success": len(done), "failure": len(rows) - len(done)}
        if rows:
            last = rows[-1]
            answer["last"] = {
                "date": last["ended"],
                "success": last["state"] == JobState.COMPLETED,
                "printerProfile": last["printer"],
            }
            if last["state"] == JobState.COMPLETED:
                answer["last"]["printTime"] = last["ended"] - last["started"]
        return answer

    def next_queued(self, printer: str) -> JobRecord | None:
        row = self._db.execute(
            "SELECT * FROM jobs WHERE printer = ? AND state = 'queued' ORDER BY position LIMIT 1",
            (printer,),
        ).fetchone()
        return _record(row) if row is not None else None

    def queued(self, printer: str) -> list[JobRecord]:
        """The printer's queued jobs, in queue order."""
        rows = self._db.execute(
            "SELECT * FROM jobs WHERE printer = ? AND state = 'queued' ORDER BY position",
            (printer,),
        ).fetchall()
        return [_record(row) for row in rows]

    def unsynced(self) -> list[JobRecord]:
        """Farm jobs with changes the farm was not told (a queued one has nothing to tell)."""
        rows = self._db.execute(
            "SELECT * FROM jobs WHERE farm_id IS NOT NULL AND version > synced_version"
            " AND state != 'queued' ORDER BY id"
        ).fetchall()
        return [_record(row) for row in rows]

    def farm_job(self, farm_id: int) -> JobRecord | None:
        """The record of the farm's job ``farm_id`` here (its latest claim)."""
        row = self._db.execute(
            "SELECT * FROM jobs WHERE farm_id = ? ORDER BY id DESC LIMIT 1", (farm_id,)
        ).fetchone()
        return _record(row) if row is not None else None

    # --- changing -----------------------------------------------------------------

    async def take(self, printer: str) -> JobRecord | None:
        record = self.next_queued(printer)
        return self.claim(record.id) if record is not None else None

    def submit(
        self,
        printer: str,
        name: str,
        file: str,
        total_lines: int,
        user: str | None = None,
        from_line: int | None = None,
        farm: tuple[int, int] | None = None,
    ) -> JobRecord:
        """Queue a job at the end of its printer's queue (``from_line``: recovered there;
        ``farm``: the farm's job and the claim's fencing token, claimed for this printer)."""
        farm_id, fence = farm if farm is not None else (None, None)
        with self._transaction() as db:
            (last,) = db.execute(
                "SELECT COALESCE(MAX(position), 0) FROM jobs WHERE printer = ?", (printer,)
            ).fetchone()
            cursor = db.execute(
                "INSERT INTO jobs (printer, name, file, state, position, submitted, total_lines,"
                " user, from_line, farm_id, fence) VALUES (?, ?, ?, 'queued', ?, ?, ?, ?, ?, ?, ?)",
                (
                    printer,
                    name,
                    file,
                    last + 1,
                    time.time(),
                    total_lines,
                    user,
                    from_line,
                    farm_id,
                    fence,
                ),
            )
            job_id = cursor.lastrowid
        assert job_id is not None
        record = self.job(job_id)
        assert record is not None
        return record

    def move(self, job_id: int, before: int | None) -> bool:
        """Move a queued job before another queued job of its printer (None: to the end)."""
        with self._transaction() as db:
            job = db.execute(
                "SELECT printer FROM jobs WHERE id = ? AND state = 'queued'", (job_id,)
            ).fetchone()
            if job is None:
                return False
            queue = [
                row[0]
                for row in db.execute(
                    "SELECT id FROM jobs WHERE printer = ? AND state = 'queued' AND id != ?"
                    " ORDER BY position",
                    (job["printer"], job_id),
                )
            ]
            if before is not None and before not in queue:
                return False
            index = queue.index(before) if before is not None else len(queue)
            queue.insert(index, job_id)
            db.executemany(
                "UPDATE jobs SET position = ? WHERE id = ?",
                [(number, queued) for number, queued in enumerate(queue, start=1)],
            )
        return True

    def claim(self, job_id: int) -> JobRecord | None:
        """A queued job starts printing; None if it is no longer queued (cancelled)."""
        with self._transaction() as db:
            cursor = db.execute(
                "UPDATE jobs SET state = 'printing', started = ?, version = version + 1"
                " WHERE id = ? AND state = 'queued'",
                (time.time(), job_id),
            )
            if cursor.rowcount != 1:
                return None
        return self.job(job_id)

    def set_state(
        self,
        job_id: int,
        state: JobState,
        error: str | None = None,
        report: str | None = None,
        filament: dict[str, dict[str, float]] | None = None,
        pace: float | None = None,
        ended: float | None = None,
        heat_rates: dict[str, float] | None = None,
    ) -> None:
        """A job's new state; an ended one's error, M773 report, filament, pace and heat
        rates with it, and when it ended (``ended``, seconds since the epoch; by default
        now)."""
        now = ended or time.time()
        with self._transaction() as db:
            if state in ACTIVE:
                db.execute(
                    "UPDATE jobs SET state = ?, started = COALESCE(started, ?),"
                    " version = version + 1 WHERE id = ?",
                    (state.value, now, job_id),
                )
            elif state in ENDED:
                used = json.dumps(filament) if filament is not None else None
                rates = json.dumps(heat_rates) if heat_rates else None
                db.execute(
                    "UPDATE jobs SET state = ?, ended = ?, error = ?, report = ?, filament = ?,"
                    " pace = ?, heat_rates = ?, version = version + 1 WHERE id = ?",
                    (state.value, now, error, report, used, pace, rates, job_id),
                )
            else:
                db.execute(
                    "UPDATE jobs SET state = ?, version = version + 1 WHERE id = ?",
                    (state.value, job_id),
                )

    def cancel_queued(self, job_id: int) -> bool:
        """Cancel a job that has not started; False if it is not queued."""
        with self._transaction() as db:
            cursor = db.execute(
                "UPDATE jobs SET state = 'cancelled', ended = ?, version = version + 1"
                " WHERE id = ? AND state = 'queued'",
                (time.time(), job_id),
            )
            return cursor.rowcount == 1

    def mark_synced(self, job_id: int, version: int) -> None:
        """The farm was told the record's changes up to ``version``."""
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET synced_version = MAX(synced_version, ?) WHERE id = ?",
                (version, job_id),
            )

    def drop(self, job_id: int) -> None:
        """Forget a farm job that never started here (given back, or claimed elsewhere)."""
        with self._transaction() as db:
            db.execute("DELETE FROM jobs WHERE id = ? AND state = 'queued'", (job_id,))

    def progress(self, job_id: int, lines: int, last_line: int) -> None:
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET lines = ?, last_line = ?, version = version + 1"
                " WHERE id = ? AND (lines != ? OR last_line != ?)",
                (lines, last_line, job_id, lines, last_line),
            )

    def heat_rates(self, printer: str) -> list[dict[str, float]]:
        """The heat rates ``printer``'s last jobs timed, newest first."""
        rows = self._db.execute(
            "SELECT heat_rates FROM jobs WHERE printer = ? AND heat_rates IS NOT NULL"
            " ORDER BY ended DESC LIMIT ?",
            (printer, PACE_JOBS),
        )
        return [json.loads(row[0]) for row in rows]

    def paces(self, printer: str) -> list[float]:
        """The paces of ``printer``'s last jobs that have one, newest first."""
        rows = self._db.execute(
            "SELECT pace FROM jobs WHERE printer = ? AND pace IS NOT NULL"
            " ORDER BY ended DESC LIMIT ?",
            (printer, PACE_JOBS),
        )
        return [float(row[0]) for row in rows]

    def last_started(self, printer: str) -> JobRecord | None:
        """The printer's most recently started job."""
        row = self._db.execute(
            "SELECT * FROM jobs WHERE printer = ? AND started IS NOT NULL "
            "ORDER BY started DESC LIMIT 1",
            (printer,),
        ).fetchone()
        return _record(row) if row is not None else None

    def interrupt_active(self) -> list[JobRecord]:
        """At start: jobs that were streaming when the server stopped become interrupted,
        their safe stop owed."""
        with self._transaction() as db:
            rows = db.execute(
                "SELECT id FROM jobs WHERE state IN ('printing', 'paused')"
            ).fetchall()
            db.execute(
                "UPDATE jobs SET state = 'interrupted', ended = ?, error = ?, safe_stop = ?,"
                " version = version + 1 WHERE state IN ('printing', 'paused')",
                (time.time(), CRASHED, OWED),
            )
        return [record for row in rows if (record := self.job(row[0])) is not None]

    def owe_safe_stop(self, job_id: int) -> None:
        """The job ended without its safe stop confirmed: owed to the printer's next contact,
        whatever state the job is recorded in (kept across restarts)."""
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET safe_stop = ?, version = version + 1 WHERE id = ?", (OWED, job_id)
            )

    def owing(self, printer: str) -> list[int]:
        """The printer's jobs whose safe stop is owed."""
        rows = self._db.execute(
            "SELECT id FROM jobs WHERE printer = ? AND safe_stop = ? ORDER BY id", (printer, OWED)
        ).fetchall()
        return [row[0] for row in rows]

    def keep_upload_name(self, path: str, original: str) -> None:
        """The stored upload ``path`` was given the name ``original``."""
        with self._transaction() as db:
            db.execute(
                "INSERT INTO uploads (path, original) VALUES (?, ?) ON CONFLICT (path)"
                " DO UPDATE SET original = excluded.original",
                (path, original),
            )

    def upload_name(self, path: str) -> str | None:
        """The name the upload stored at ``path`` was given (None: not known)."""
        row = self._db.execute("SELECT original FROM uploads WHERE path = ?", (path,))
        found = row.fetchone()
        return str(found[0]) if found is not None else None

    def keep_heaters(self, printer: str, heaters: list[Heater]) -> None:
        """The heaters that may be on at ``printer`` now (kept across restarts)."""
        rows = [[h.kind, h.index, h.target, h.command] for h in heaters]
        with self._transaction() as db:
            db.execute(
                "INSERT INTO heaters (printer, heaters) VALUES (?, ?) ON CONFLICT (printer)"
                " DO UPDATE SET heaters = excluded.heaters",
                (printer, json.dumps(rows)),
            )

    def heaters(self, printer: str) -> list[Heater]:
        """The heaters kept by :meth:`keep_heaters` (none when nothing was kept)."""
        row = self._db.execute("SELECT heaters FROM heaters WHERE printer = ?", (printer,))
        found = row.fetchone()
        if found is None:
            return []
        return [
            Heater(kind, index, float(target), command)
            for kind, index, target, command in json.loads(found[0])
        ]

    def hold(self, printer: str, reason: str) -> None:
        """``printer``'s queue waits for a release, for ``reason`` (kept across restarts)."""
        with self._transaction() as db:
            db.execute(
                "INSERT INTO holds (printer, reason, since) VALUES (?, ?, ?) ON CONFLICT"
                " (printer) DO UPDATE SET reason = excluded.reason, since = excluded.since",
                (printer, reason, time.time()),
            )

    def release(self, printer: str) -> None:
        """``printer``'s queue runs again."""
        with self._transaction() as db:
            db.execute("DELETE FROM holds WHERE printer = ?", (printer,))

    def hold_reason(self, printer: str) -> str | None:
        """Why ``printer``'s queue is held; None when it is not."""
        row = self._db.execute("SELECT reason FROM holds WHERE printer = ?", (printer,))
        found = row.fetchone()
        return str(found[0]) if found is not None else None

    def safe_stop_sent(self, printer: str) -> list[int]:
        """The safe stop the printer was owed went (and was confirmed); returns those jobs.
        An error that said it was not sent says it went now (a farm reports the record)."""
        owed = self.owing(printer)
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET safe_stop = ?, version = version + 1,"
                " error = CASE WHEN error = ? THEN ? ELSE error END"
                " WHERE printer = ? AND safe_stop = ?",
                (SENT, CRASHED, CRASHED_SENT, printer, OWED),
            )
        return owed


def totals(records: list[JobRecord]) -> dict[str, Any]:
    """What a printer's ended jobs add up to: how many ended each way, the hours they
    streamed, and the filament each tool used (as each job's ``filament`` says)."""
    ended = [r for r in records if r.state in ENDED]
    filament: dict[str, dict[str, float]] = {}
    for record in ended:
        for tool, used in (json.loads(record.filament) if record.filament else {}).items():
            kept = filament.setdefault(tool, {"length": 0.0, "volume": 0.0})
            kept["length"] += used["length"]
            kept["volume"] += used["volume"]
    return {
        "jobs": {state.value: sum(r.state is state for r in ended) for state in ENDED},
        "print_seconds": sum(r.ended - r.started for r in ended if r.started and r.ended),
        "lines": sum(r.lines for r in ended),
        "filament": filament,
    }


def _record(row: sqlite3.Row) -> JobRecord:
    values = dict(row)
    values["state"] = JobState(values["state"])
    return JobRecord(**values)
