"""The farm's queue in PostgreSQL: nodes and their leases, printers and what they have,
files by content in chunks, and jobs claimed with a fencing token.

psycopg 3: one library for the async server and for the synchronous tests and bench,
``LISTEN/NOTIFY`` on an async connection, a maintained pool, and libpq's own handling of
``PGPASSWORD``, ``.pgpass`` and the service file (the password never passes through us).

Every method is one transaction. A change that others should see sends a notification on
the channel ``farm`` in the same transaction (delivered when it commits): ``{"kind":
"job"|"node"|"printer"|"cancel", ...}``. Every change of a job's state goes through
:meth:`FarmDB._move`, checked against the table of states.py and guarded on the state it
was in (two people resuming one job: one wins, the other is refused), and its notification
carries the new state (``{"kind": "job", "job": 12, "state": "interrupted"}``).

A job's estimate (``estimated_time``: planned seconds, the plan's own) is filled after its
submit, once the node that received the file has planned it (``{"kind": "job", "jobs": [...],
"estimated": true}`` tells); a printing job's ``expected_end`` comes with its node's progress
reports, a printer's ``pace`` with its state.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from psycopg import AsyncConnection
from psycopg.rows import dict_row
from psycopg.types.json import Jsonb
from psycopg_pool import AsyncConnectionPool

from repetrel_host.server.farm import states
from repetrel_host.server.farm.schema import migrate
from repetrel_host.server.farm.states import MoveRefused

CHANNEL = "farm"
CHUNK = 1 << 20  # a file goes in and out a megabyte at a time: never whole in memory
# The connection's own watch on a dead network (a pulled cable gives no reset): libpq
# gives up on a write unacknowledged this long, and on a silent peer after the probes.
CONNECTION: dict[str, Any] = {
    "connect_timeout": 5,
    "keepalives": 1,
    "keepalives_idle": 5,
    "keepalives_interval": 2,
    "keepalives_count": 2,
    "tcp_user_timeout": 8000,  # ms
    "application_name": "hyrel-server",
}
ACTIVE = states.ACTIVE

_JOB = """
    id, name, file, needs, priority, state, submitted_by, total_lines, node::text AS node,
    printer, fence, refused, lines, last_line, error, report, filament, safe_stop, local_id,
    from_line, resumes, resumed_by, estimated_time, estimated_heating, estimate_of,
    extract(epoch FROM expected_end)::float8 AS expected_end,
    extract(epoch FROM submitted)::float8 AS submitted,
    extract(epoch FROM claimed)::float8 AS claimed,
    extract(epoch FROM started)::float8 AS started,
    extract(epoch FROM ended)::float8 AS ended
"""


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _reported_fields(to: str) -> str:
    """The fields a node's report sets (SQL), for a job that becomes ``to``: its expected
    end only while it prints."""
    end = ", expected_end = to_timestamp(%(expected_end)s)" if to == states.PRINTING else ""
    return (
        "lines = %(lines)s, last_line = %(last_line)s,"
        " started = to_timestamp(%(started)s), ended = to_timestamp(%(ended)s),"
        " error = %(error)s, report = %(report)s, filament = %(filament)s,"
        " safe_stop = %(safe_stop)s, local_id = %(local_id)s" + end
    )


class FarmDB:
    """A pool of connections to the farm's database."""

    def __init__(self, url: str, size: int = 4) -> None:
        self.url = url
        self.version: int | None = None  # the schema's, once migrated
        self.pool = AsyncConnectionPool(
            url,
            min_size=1,
            max_size=size,
            open=False,
            kwargs={**CONNECTION, "autocommit": True, "row_factory": dict_row},
            check=AsyncConnectionPool.check_connection,  # a connection the outage killed
            reconnect_timeout=0,  # never give up: the database comes back
        )

    async def open(self) -> int:
        """Migrate (once: a node that joins again after an outage does not), then open the
        pool; the schema's version."""
        if self.version is None:
            async with await AsyncConnection.connect(self.url, **CONNECTION) as connection:
                self.version = await migrate(connection)
        await self.pool.open(wait=False)
        return self.version

    async def close(self) -> None:
        await self.pool.close(timeout=1.0)

    async def listen(self) -> AsyncConnection[Any]:
        """A connection of its own that listens on the farm's channel."""
        connection = await AsyncConnection.connect(self.url, **CONNECTION, autocommit=True)
        await connection.execute(f"LISTEN {CHANNEL}")
        return connection

    @asynccontextmanager
    async def _transaction(self, timeout: float) -> AsyncIterator[Any]:
        async with self.pool.connection(timeout) as connection, connection.transaction():
            yield connection

    async def _rows(self, timeout: float, query: str, params: Any = ()) -> list[dict[str, Any]]:
        """The rows of one read, as dicts (the pool's row factory)."""
        async with self.pool.connection(timeout) as db:
            cursor: Any = await db.execute(query, params)
            return list(await cursor.fetchall())

    async def _notify(self, db: Any, message: dict[str, Any]) -> None:
        await db.execute("SELECT pg_notify(%s, %s)", (CHANNEL, json.dumps(message)))

    async def _move(
        self,
        db: Any,
        job: int,
        was: str,
        to: str,
        sets: str = "",
        params: dict[str, Any] | None = None,
        told: dict[str, Any] | None = None,
        pick: str = "%(job)s",
    ) -> dict[str, Any] | None:
        """The one way a job's state changes: from ``was`` to ``to`` (MoveRefused when the
        table does not allow it), with more ``sets`` (SQL, its ``params`` by name), only
        while the job is still ``was`` (and, given ``params["fence"]``, still that claim).
        ``pick``: SQL that gives the job's id in one statement (a claim's choice) in place
        of ``job``. A job not printing has no expected end. The job as it is now; None when
        it was no longer ``was``. A new state is notified, with ``told`` besides."""
        if not states.allowed(was, to):
            raise MoveRefused(f"farm job {job} is {was}: it cannot become {to}")
        values = {**(params or {}), "job": job, "was": was, "to": to}
        query = "UPDATE jobs SET state = %(to)s, updated = now()"
        if to != states.PRINTING:
            query += ", expected_end = NULL"
        if sets:
            query += f", {sets}"
        query += f" WHERE id = ({pick}) AND state = %(was)s"
        if "fence" in values:
            query += " AND fence = %(fence)s"
        row = await (await db.execute(f"{query} RETURNING {_JOB}", values)).fetchone()
        if row is not None and was != to:
            message = {"kind": "job", "job": row["id"], "state": to, **(told or {})}
            await self._notify(db, message)
        return dict(row) if row is not None else None

    async def _locked(self, db: Any, job: int) -> dict[str, Any] | None:
        """The job, locked until the transaction ends (its state cannot change meanwhile)."""
        row = await (
            await db.execute(f"SELECT {_JOB} FROM jobs WHERE id = %s FOR UPDATE", (job,))
        ).fetchone()
        return dict(row) if row is not None else None

    # --- nodes and printers ----------------------------------------------------------

    async def register(
        self,
        node: str,
        name: str,
        url: str,
        version: str,
        lease: float,
        printers: list[tuple[str, dict[str, Any], str | None]],
        timeout: float,
    ) -> None:
        """The node and its printers (name, capabilities, loadout text), as they are now;
        its lease starts. Printers it no longer has are forgotten."""
        async with self._transaction(timeout) as db:
            await db.execute(
                "INSERT INTO nodes (id, name, url, version, lease_until) VALUES "
                "(%s, %s, %s, %s, now() + make_interval(secs => %s)) ON CONFLICT (id) DO UPDATE"
                " SET name = EXCLUDED.name, url = EXCLUDED.url, version = EXCLUDED.version,"
                " lease_until = EXCLUDED.lease_until, lost_at = NULL",
                (node, name, url, version, lease),
            )
            await db.execute(
                "DELETE FROM printers WHERE node = %s AND NOT name = ANY(%s)",
                (node, [printer[0] for printer in printers]),
            )
            for printer, caps, loadout in printers:
                await db.execute(
                    "INSERT INTO printers (node, name, caps, loadout) VALUES (%s, %s, %s, %s)"
                    " ON CONFLICT (node, name) DO UPDATE SET caps = EXCLUDED.caps,"
                    " loadout = EXCLUDED.loadout, updated = now()",
                    (node, printer, Jsonb(caps), loadout),
                )
            await self._notify(db, {"kind": "node", "node": node, "name": name})

    async def heartbeat(self, node: str, lease: float, timeout: float) -> list[dict[str, Any]]:
        """Renew the node's lease, and end the leases that ran out: a lost node's printing
        jobs become interrupted (never handed on: the part may be on its bed), its claimed
        ones that never started go back to the queue. Returns the jobs it interrupted."""
        async with self._transaction(timeout) as db:
            cursor = await db.execute(
                "UPDATE nodes SET lease_until = now() + make_interval(secs => %s)"
                " WHERE id = %s AND lost_at IS NULL RETURNING id",
                (lease, node),
            )
            if await cursor.fetchone() is None:
                raise LeaseLost(node)
            lost = await (
                await db.execute(
                    "UPDATE nodes SET lost_at = now() WHERE lease_until < now() AND lost_at IS NULL"
                    " RETURNING id::text AS id, name"
                )
            ).fetchall()
            interrupted: list[dict[str, Any]] = []
            for gone in lost:
                why = (
                    f"node {gone['name']} stopped answering (its lease ran out): the job was "
                    "streaming there; the part may be on its bed"
                )
                held = await (
                    await db.execute(
                        f"SELECT {_JOB} FROM jobs WHERE node = %s AND state = ANY(%s)"
                        " ORDER BY id FOR UPDATE",
                        (gone["id"], list(ACTIVE)),
                    )
                ).fetchall()
                await self._notify(db, {"kind": "node", "node": gone["id"], "lost": True})
                for job in held:
                    if job["state"] == states.CLAIMED:  # never started: another may take it
                        sets = "node = NULL, printer = NULL, claimed = NULL"
                        queued = {"queued": True}
                        await self._move(
                            db, job["id"], job["state"], states.QUEUED, sets, None, queued
                        )
                        continue
                    moved = await self._move(
                        db,
                        job["id"],
                        job["state"],
                        states.INTERRUPTED,
                        "ended = now(), error = %(why)s",
                        {"why": why},
                        {"error": why},
                    )
                    if moved is not None:
                        interrupted.append(moved)
            return interrupted

    async def printer_state(
        self,
        node: str,
        name: str,
        state: str,
        held: bool,
        job: int | None,
        pace: float | None,
        timeout: float,
    ) -> None:
        """How the printer stands: its state, its hold, its job, and its pace (actual over
        planned moving time, learned from its past jobs; None: it has none yet)."""
        async with self._transaction(timeout) as db:
            await db.execute(
                "UPDATE printers SET state = %s, held = %s, job = %s, pace = %s, updated = now()"
                " WHERE node = %s AND name = %s",
                (state, held, job, pace, node, name),
            )
            await self._notify(
                db, {"kind": "printer", "node": node, "printer": name, "state": state}
            )

    async def printers(self, timeout: float) -> list[dict[str, Any]]:
        """Every registered printer, with its node and whether that node is alive."""
        return await self._rows(
            timeout,
            "SELECT p.node::text AS node, n.name AS node_name, n.url, p.name, p.caps,"
            " p.loadout, p.state, p.held, p.job, p.pace, n.lost_at IS NOT NULL AS lost,"
            " extract(epoch FROM n.lease_until)::float8 AS lease_until"
            " FROM printers p JOIN nodes n ON n.id = p.node ORDER BY n.name, p.name",
        )

    async def nodes(self, timeout: float) -> list[dict[str, Any]]:
        return await self._rows(
            timeout,
            "SELECT id::text AS id, name, url, version, lost_at IS NOT NULL AS lost,"
            " extract(epoch FROM joined)::float8 AS joined,"
            " extract(epoch FROM lease_until)::float8 AS lease_until,"
            " extract(epoch FROM lost_at)::float8 AS lost_at FROM nodes ORDER BY name",
        )

    # --- files ------------------------------------------------------------------------

    async def store_file(self, path: Path, digest: str, timeout: float) -> None:
        """The file's content under its hash, a chunk at a time (kept once however often
        it is submitted)."""
        async with self._transaction(timeout) as db:
            cursor = await db.execute("SELECT 1 FROM files WHERE hash = %s", (digest,))
            if await cursor.fetchone() is not None:
                return
            size = path.stat().st_size
            count = 0
            with path.open("rb") as handle:
                while chunk := handle.read(CHUNK):
                    await db.execute(
                        "INSERT INTO file_chunks (hash, n, data) VALUES (%s, %s, %s)"
                        " ON CONFLICT DO NOTHING",
                        (digest, count, chunk),
                    )
                    count += 1
            await db.execute(
                "INSERT INTO files (hash, size, chunks) VALUES (%s, %s, %s) ON CONFLICT DO NOTHING",
                (digest, size, count),
            )

    async def fetch_file(self, digest: str, target: Path, timeout: float) -> None:
        """The file's content into ``target`` (written beside it, checked, then moved)."""
        partial = target.with_name(f".{target.name}.{os.getpid()}.part")
        check = hashlib.sha256()
        try:
            async with self._transaction(timeout) as db:
                row = await (
                    await db.execute("SELECT chunks FROM files WHERE hash = %s", (digest,))
                ).fetchone()
                if row is None:
                    raise FileNotFoundError(f"the farm has no file {digest[:12]}")
                with partial.open("wb") as out:
                    for number in range(row["chunks"]):
                        chunk = await (
                            await db.execute(
                                "SELECT data FROM file_chunks WHERE hash = %s AND n = %s",
                                (digest, number),
                            )
                        ).fetchone()
                        out.write(chunk["data"])
                        check.update(chunk["data"])
            if check.hexdigest() != digest:
                raise OSError(f"the farm's file {digest[:12]} came back changed")
            partial.replace(target)
        finally:
            partial.unlink(missing_ok=True)

    # --- jobs ---------------------------------------------------------------------------

    async def submit(
        self,
        name: str,
        digest: str,
        needs: dict[str, Any],
        priority: int,
        copies: int,
        total_lines: int,
        user: str | None,
        timeout: float,
    ) -> list[int]:
        async with self._transaction(timeout) as db:
            ids = []
            for _ in range(copies):
                cursor = await db.execute(
                    "INSERT INTO jobs (name, file, needs, priority, total_lines, submitted_by)"
                    " VALUES (%s, %s, %s, %s, %s, %s) RETURNING id",
                    (name, digest, Jsonb(needs), priority, total_lines, user),
                )
                row = await cursor.fetchone()
                ids.append(row["id"])
            await self._notify(db, {"kind": "job", "jobs": ids, "queued": True, "state": "queued"})
            return ids

    async def claim(
        self, node: str, printer: str, caps: dict[str, Any], timeout: float
    ) -> dict[str, Any] | None:
        """The best queued job this printer can take (priority, then age), claimed for it
        with a new fencing token; None when there is none (or this node lost its lease)."""
        key = f"{node}/{printer}"
        async with self._transaction(timeout) as db:
            # The queue's order is its index's: walked from the top, it stops at the first
            # job this printer can take. Left to a stale row estimate (a thousand jobs just
            # queued), the planner sorts the whole queue at every claim instead.
            await db.execute("SET LOCAL enable_sort = off")
            await db.execute("SET LOCAL enable_bitmapscan = off")
            # Chosen and claimed in one statement: a round trip less at every claim.
            chosen = (
                "SELECT id FROM jobs WHERE state = 'queued'"
                " AND %(caps)s @> needs"
                " AND NOT refused ? %(key)s"
                " AND EXISTS (SELECT 1 FROM nodes WHERE id = %(node)s AND lost_at IS NULL"
                "   AND lease_until > now())"
                " ORDER BY priority DESC, id LIMIT 1 FOR UPDATE SKIP LOCKED"
            )
            sets = (
                "node = %(node)s, printer = %(printer)s, fence = nextval('fence'), claimed = now()"
            )
            params = {"caps": Jsonb(caps), "key": key, "node": node, "printer": printer}
            return await self._move(db, 0, states.QUEUED, states.CLAIMED, sets, params, pick=chosen)

    async def give_back(self, job: int, fence: int, key: str, why: str, timeout: float) -> None:
        """A claimed job this printer cannot print (its lint says why): queued again, and
        never offered to this printer again."""
        async with self._transaction(timeout) as db:
            sets = (
                "node = NULL, printer = NULL, claimed = NULL,"
                " refused = refused || jsonb_build_object(%(key)s::text, %(why)s::text)"
            )
            params = {"key": key, "why": why, "fence": fence}
            await self._move(db, job, states.CLAIMED, states.QUEUED, sets, params, {"queued": True})

    async def start(self, job: int, fence: int, timeout: float) -> bool:
        """The claim still holds (its token is the job's): the job may stream."""
        async with self._transaction(timeout) as db:
            sets = "started = COALESCE(started, now())"
            for was in (states.CLAIMED, states.PRINTING):  # given back or lost: neither
                if await self._move(db, job, was, states.PRINTING, sets, {"fence": fence}):
                    return True
            return False

    async def report(self, job: int, fence: int, fields: dict[str, Any], timeout: float) -> bool:
        """What the node streaming the job knows of it (its state, lines acknowledged, its
        end, when a printing job should end), written only with the claim's token: False
        when it no longer holds."""
        values = {
            "expected_end": None,  # a report that does not say: not printing
            **fields,
            "filament": Jsonb(fields["filament"]) if fields.get("filament") else None,
            "job": job,
            "fence": fence,
        }
        async with self._transaction(timeout) as db:
            reported = fields["state"]
            # Mostly a printing job's progress or end, else the state it is in: taken as
            # the node says in one statement (as after_report would take it).
            for was in dict.fromkeys((states.PRINTING, reported)):
                if await self._move(db, job, was, reported, _reported_fields(reported), values):
                    return True
            found = await self._locked(db, job)
            if found is None or found["fence"] != fence:
                return False
            was = found["state"]
            to = states.after_report(was, reported)
            sets = ""
            went_on = was == states.RESUMED and reported in states.WENT_ON
            if went_on and await self._cancel_rest(db, found, reported):
                to, sets = reported, "resumed_by = NULL, "
            # A new state is told; progress is not: every printing printer reports it each
            # second, and notifying commits take turns on one lock in PostgreSQL.
            await self._move(db, job, was, to, sets + _reported_fields(to), values)
            return True

    async def _cancel_rest(self, db: Any, job: dict[str, Any], reported: str) -> bool:
        """A resumed job's node says it went on (it was cut from the database, not
        stopped): its rest, while still queued, is cancelled (printing it would print on a
        finished part); True then. False when the rest is under way already."""
        rest = await self._locked(db, job["resumed_by"])
        if rest is None or rest["state"] != states.QUEUED:
            return False
        why = (
            f"farm job {job['id']} went on at its node after all ({reported}): "
            "its rest is not needed"
        )
        sets, told = "ended = now(), error = %(why)s", {"why": why}
        await self._move(
            db, rest["id"], states.QUEUED, states.CANCELLED, sets, told, {"error": why}
        )
        return True

    async def estimated(
        self, jobs: list[int], seconds: float, of: str, timeout: float, heating: float = 0.0
    ) -> None:
        """The jobs' planned print time: ``of`` the whole ``file``, or the ``rest`` from
        their first line (a recovered job's); ``heating``: of it, the heat waits'."""
        async with self._transaction(timeout) as db:
            await db.execute(
                "UPDATE jobs SET estimated_time = %s, estimated_heating = %s, estimate_of = %s"
                " WHERE id = ANY(%s)",
                (seconds, heating, of, jobs),
            )
            await self._notify(db, {"kind": "job", "jobs": jobs, "estimated": True})

    async def recover(self, job: int, from_line: int, rest_lines: int, timeout: float) -> int:
        """Queue the rest of an ended job from ``from_line`` (``rest_lines`` lines to
        send), for the printer that printed it (its part is on that bed); the job becomes
        ``resumed`` (once: a second resume is refused). The new job's number, its estimate
        the whole file's until the rest is planned. ValueError (a sentence) when the job
        cannot be recovered."""
        async with self._transaction(timeout) as db:
            # Locked: of two resumes at once, the second sees the first's "resumed".
            row = await (
                await db.execute(
                    "SELECT j.*, n.name AS node_name FROM jobs j LEFT JOIN nodes n"
                    " ON n.id = j.node WHERE j.id = %s FOR UPDATE OF j",
                    (job,),
                )
            ).fetchone()
            if row is None:
                raise LookupError(f"the farm has no job {job}")
            if row["state"] not in states.RESUMABLE:
                raise MoveRefused(states.resume_refusal(job, row["state"], row["resumed_by"]))
            if row["printer"] is None or row["node_name"] is None:
                raise ValueError(f"farm job {job} never ran on a printer: queue it again")
            pinned = {"names": [f"{row['node_name']}/{row['printer']}"]}
            whole = row["estimated_time"] if row["estimate_of"] == "file" else None
            cursor = await db.execute(
                "INSERT INTO jobs (name, file, needs, priority, total_lines, submitted_by,"
                " from_line, resumes, estimated_time, estimated_heating, estimate_of)"
                " VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s) RETURNING id",
                (
                    row["name"],
                    row["file"],
                    Jsonb(pinned),
                    row["priority"],
                    rest_lines,
                    row["submitted_by"],
                    from_line,
                    job,
                    whole,
                    row["estimated_heating"] if whole is not None else None,
                    "file" if whole is not None else None,
                ),
            )
            made = (await cursor.fetchone())["id"]
            await self._notify(
                db, {"kind": "job", "jobs": [made], "queued": True, "state": "queued"}
            )
            sets, params = "resumed_by = %(made)s", {"made": made}
            await self._move(
                db, job, row["state"], states.RESUMED, sets, params, {"resumed_by": made}
            )
            return int(made)

    async def cancel(self, job: int, timeout: float) -> dict[str, Any] | None:
        """Cancel a queued job at once; a claimed or streaming one is asked of its node
        (told by notification). The job as it was; None if there is no such job."""
        async with self._transaction(timeout) as db:
            row = await (
                await db.execute(f"SELECT {_JOB} FROM jobs WHERE id = %s FOR UPDATE", (job,))
            ).fetchone()
            if row is None:
                return None
            if row["state"] == states.QUEUED:
                await self._move(db, job, states.QUEUED, states.CANCELLED, "ended = now()")
            elif row["state"] in ACTIVE:
                await self._notify(db, {"kind": "cancel", "job": job, "node": row["node"]})
            return dict(row)

    async def job(self, job: int, timeout: float) -> dict[str, Any] | None:
        rows = await self._rows(timeout, f"SELECT {_JOB} FROM jobs WHERE id = %s", (job,))
        return rows[0] if rows else None

    async def jobs(self, timeout: float, ended: int = 200) -> list[dict[str, Any]]:
        """Queued jobs in the order they will be claimed, those claimed or streaming, and
        the last ``ended`` that ended, newest first."""
        return await self._rows(
            timeout,
            f"(SELECT {_JOB} FROM jobs WHERE state = 'queued' ORDER BY priority DESC, id)"
            f" UNION ALL (SELECT {_JOB} FROM jobs WHERE state IN ('claimed', 'printing',"
            " 'paused') ORDER BY id)"
            f" UNION ALL (SELECT {_JOB} FROM jobs WHERE state NOT IN ('queued', 'claimed',"
            " 'printing', 'paused') ORDER BY ended DESC NULLS LAST, id DESC LIMIT %s)",
            (ended,),
        )

    async def counts(self, timeout: float) -> dict[str, int]:
        """How many jobs are in each state."""
        rows = await self._rows(timeout, "SELECT state, count(*) AS n FROM jobs GROUP BY state")
        return {row["state"]: row["n"] for row in rows}

    async def held_by(self, node: str, timeout: float) -> list[dict[str, Any]]:
        """The jobs the farm thinks this node holds (claimed, printing, paused)."""
        return await self._rows(
            timeout,
            f"SELECT {_JOB} FROM jobs WHERE node = %s AND state IN ('claimed', 'printing',"
            " 'paused')",
            (node,),
        )


class LeaseLost(Exception):
    """The node's lease ran out (others marked it lost): it registers again."""
