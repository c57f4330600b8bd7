"""A print server as a node of a farm: it registers its printers, keeps a lease, claims
farm jobs for its ready printers, and reports what they did.

The node's own SQLite store stays the authority on what its printers acknowledged: a
claimed farm job is recorded there first (with its fencing token), streams like any job,
and every change of its record is reported to PostgreSQL from there (the outbox:
``version`` and ``synced_version``). So a database that blinks never stops a print: the
node claims nothing new while it is away, and tells what happened once it is back.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import psycopg
from psycopg_pool import PoolTimeout

import repetrel_host as rh
from repetrel_host.config import load_library
from repetrel_host.errors import ConfigError, HostError
from repetrel_host.gcode.lint import Severity
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.server.analyses import Analyses
from repetrel_host.server.events import EventHub, FarmEvent
from repetrel_host.server.farm import estimates, needs
from repetrel_host.server.farm.db import FarmDB, LeaseLost
from repetrel_host.server.store import JobRecord, JobState, Store

if TYPE_CHECKING:
    from repetrel_host.server.printers.service import PrinterService

log = logging.getLogger("repetrel_host.server.farm")
# The pool's own retries are told in our one sentence (the database does not answer).
logging.getLogger("psycopg.pool").setLevel(logging.ERROR)

NODE_ID_FILE = "farm-node-id"
CACHE = "farm"  # the farm's files as this node fetched them, below the uploads folder
TIMEOUT = 5.0  # seconds a database call may take before the node counts it away
FILE_TIMEOUT = 600.0  # a file's transfer (a gigabyte over a slow link)
SYNC_INTERVAL = 1.0  # seconds between reports of what the node's printers did
RETRY_MAX = 10.0
RECHECK = 30.0  # a ready printer looks for a job this often even with no notification


@dataclass(frozen=True)
class FarmSettings:
    url: str  # postgresql://USER@HOST/DB (the password from PGPASSWORD or .pgpass)
    name: str  # the node's name, as the farm shows it
    node_url: str  # where people and other nodes reach this server
    lease: float = 15.0  # seconds a node is trusted without a heartbeat


class FarmAway(Exception):
    """The database did not answer (in time)."""


def node_id(data_dir: Path) -> str:
    """The node's id, kept in its data folder: the same across restarts."""
    path = data_dir / NODE_ID_FILE
    if path.exists():
        return path.read_text().strip()
    made = str(uuid.uuid4())
    path.write_text(made + "\n")
    return made


def shown_url(url: str) -> str:
    """The database's URL as logs show it: never a password (we refuse one in it anyway)."""
    with contextlib.suppress(Exception):
        info = psycopg.conninfo.conninfo_to_dict(url)
        return f"{info.get('host', 'localhost')}:{info.get('port', 5432)}/{info.get('dbname', '')}"
    return "the farm's database"


class FarmNode:
    """The farm as this server's printers see it: :meth:`take` is their queue."""

    def __init__(
        self,
        settings: FarmSettings,
        data_dir: Path,
        store: Store,
        services: dict[str, PrinterService],
        analyses: Analyses | None = None,
    ) -> None:
        self.settings = settings
        self.id = node_id(data_dir)
        self.data_dir = data_dir
        self.cache = data_dir / "files" / CACHE
        self.store = store
        self.services = services
        self.db = FarmDB(settings.url)
        self.events = EventHub()  # the farm's notifications, for /v1/farm/events
        # The files' analyses (the server's): a farm job's estimate is its file's plan.
        self.analyses = analyses or Analyses(data_dir / "analysis", data_dir)
        # Jobs whose file this node has, waiting for their estimate: (jobs, file, from line).
        self._unestimated: asyncio.Queue[tuple[list[int], Path, int | None]] = asyncio.Queue()
        self.caps: dict[str, dict[str, Any]] = {}
        self.loadouts: dict[str, str | None] = {}
        self.ready = False  # registered, lease held: may claim
        self.away_since: float | None = None
        # Counts the farm's news (a job queued, a reconnection): a printer whose last claim
        # found nothing looks again once there is news since (``_looked``: at which count).
        self.news = 0
        self._looked: dict[str, int] = {}
        self._last_check: dict[str, float] = {}
        self._dirty: set[str] = set(services)  # printers whose state the farm has not seen
        self._shown: dict[str, tuple[str, bool, int | None, float | None]] = {}
        self._tasks: list[asyncio.Task[None]] = []
        self._cancels: set[asyncio.Task[bool]] = set()  # cancels asked by the farm, running
        # Set as the server stops: psycopg may answer a cancelled wait with its own error,
        # which the loops would otherwise take for an outage and retry.
        self._stopping = False
        self._wake_sync = asyncio.Event()
        for name, service in services.items():
            service.queue = self
            service.watchers.append(functools.partial(self._changed, name))

    # --- lifecycle ---------------------------------------------------------------------

    async def start(self) -> None:
        """Run the node's loops: the heartbeats' first opens the database and joins
        (``hyrel-server`` checked the schema before it started; while the database is
        away the printers print their own queues)."""
        for name, service in self.services.items():
            self.caps[name], self.loadouts[name] = self._capabilities(name, service)
        loop = asyncio.get_running_loop()
        for run in (self._heartbeats, self._listen, self._sync, self._estimate_jobs):
            self._tasks.append(loop.create_task(run(), name=f"farm {run.__name__}"))

    async def stop(self) -> None:
        self._stopping = True
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        with contextlib.suppress(Exception):
            await self._push_records()  # the last outcomes, if the database is there
        await self.db.close()

    def _capabilities(
        self, name: str, service: PrinterService
    ) -> tuple[dict[str, Any], str | None]:
        loadout = service.plan_loadout()
        heads = [
            {
                "tool": head.tool,
                "slot": head.slot,
                "head": head.name,
                "material": head.material,
                "nozzle": head.nozzle,
            }
            for head in (loadout.heads if loadout is not None else ())
        ]
        machine = service.config.machine or (loadout.machine_name if loadout else None)
        machine = machine or service.user.printer.machine
        protocol = service.config.protocol or "reprap"
        if machine is not None and service.config.protocol is None:
            with contextlib.suppress(Exception):
                protocol = load_library(service.user).machines[machine].link.protocol
        caps = needs.capabilities(
            name, self.settings.name, machine, protocol, heads, service.config.tags
        )
        text = None
        if loadout is not None:
            with contextlib.suppress(OSError):
                text = loadout.path.read_text()
        return caps, text

    # --- calls to the database -------------------------------------------------------------

    async def _call(self, call: Any, timeout: float = TIMEOUT) -> Any:
        try:
            return await asyncio.wait_for(call, timeout + 1)
        except (psycopg.Error, PoolTimeout, OSError, TimeoutError) as exc:
            self._away(exc)
            raise FarmAway(str(exc)) from None

    def _away(self, exc: BaseException) -> None:
        if self.away_since is None:
            self.away_since = time.time()
            why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            log.warning(
                "farm: the database at %s does not answer (%s): printing goes on, no new "
                "claims until it is back",
                shown_url(self.settings.url),
                why,
            )
        self.ready = False

    async def _heartbeats(self) -> None:
        """Register, then renew the lease (and end others' leases that ran out)."""
        delay = 1.0
        registered = False
        while not self._stopping:
            try:
                if not registered:
                    await self._call(self.db.open(), TIMEOUT * 2)  # migrated once, pool open
                    await self._register()
                    registered = True
                ended = await self._call(self.db.heartbeat(self.id, self.settings.lease, TIMEOUT))
                for job in ended:
                    log.warning(
                        "farm: job %d on printer %s interrupted at line %d: its node stopped "
                        "answering (its lease ran out)",
                        job["id"],
                        job["printer"],
                        job["last_line"],
                    )
                if not self.ready:
                    # What its printers did goes first: a job the farm took for lost may
                    # have gone on (and its rest, resumed meanwhile, must not print).
                    await self._push_records()
                    back = self.away_since is not None
                    self.ready, self.away_since, delay = True, None, 1.0
                    self._dirty = set(self.services)
                    self._shown.clear()  # all of it told again, as the node (re)joins
                    self._wake_sync.set()
                    self._look_again()  # notifications may have been missed
                    if back:
                        log.info("farm: the database is back; claiming again")
            except LeaseLost:
                log.warning("farm: this node's lease had run out: joining again")
                registered = False
                continue
            except FarmAway:
                registered = False
                await asyncio.sleep(delay)
                delay = min(delay * 2, RETRY_MAX)
                continue
            except ConfigError as exc:
                log.error("farm: %s", exc)
                await asyncio.sleep(RETRY_MAX)
                continue
            await asyncio.sleep(self.settings.lease / 3)

    async def _register(self) -> None:
        printers = [(name, self.caps[name], self.loadouts[name]) for name in self.services]
        await self._call(
            self.db.register(
                self.id,
                self.settings.name,
                self.settings.node_url,
                rh.__version__,
                self.settings.lease,
                printers,
                TIMEOUT,
            )
        )
        log.info(
            "farm: node %s (%s) joined %s with printers %s",
            self.settings.name,
            self.id,
            shown_url(self.settings.url),
            ", ".join(self.services),
        )
        await self._reconcile()

    async def _reconcile(self) -> None:
        """Jobs the farm says this node holds that it has no record of (it stopped between
        the claim and its record): a claim goes back to the queue; a started one (its
        record lost with the data folder) is interrupted."""
        for job in await self._call(self.db.held_by(self.id, TIMEOUT)):
            local = self.store.farm_job(job["id"])
            if local is not None and local.fence == job["fence"]:
                continue
            if job["state"] == "claimed":
                await self._call(self.db.give_back(job["id"], job["fence"], "", "", TIMEOUT))
                log.info("farm: job %d went back to the queue (claimed, never started)", job["id"])
            else:
                fields = {
                    "state": JobState.INTERRUPTED.value,
                    "lines": job["lines"],
                    "last_line": job["last_line"],
                    "started": job["started"],
                    "ended": time.time(),
                    "error": f"node {self.settings.name} has no record of the job",
                    "report": None,
                    "filament": None,
                    "safe_stop": None,
                    "local_id": None,
                    "expected_end": None,
                }
                await self._call(self.db.report(job["id"], job["fence"], fields, TIMEOUT))

    async def _listen(self) -> None:
        """The farm's notifications: new jobs wake the printers, a cancel for a job here
        cancels it, and all of them go to the farm's event stream."""
        delay = 1.0
        while not self._stopping:
            try:
                connection = await self._call(self.db.listen(), TIMEOUT * 2)
            except FarmAway:
                await asyncio.sleep(delay)
                delay = min(delay * 2, RETRY_MAX)
                continue
            delay = 1.0
            self._look_again()  # what came while it was not listening
            try:
                async with connection:
                    while not self._stopping:
                        async for notice in connection.notifies(timeout=RECHECK):
                            await self._notified(json.loads(notice.payload))
                        self._look_again()  # quiet for a while: look anyway
            except (psycopg.Error, OSError) as exc:
                if self._stopping:
                    return
                self._away(exc)
                await asyncio.sleep(delay)

    async def _notified(self, message: dict[str, Any]) -> None:
        self.events.publish(FarmEvent(message))
        kind = message.get("kind")
        if kind == "job" and message.get("queued"):
            self._look_again()
        elif kind == "cancel" and message.get("node") == self.id:
            record = self.store.farm_job(int(message["job"]))
            if record is not None and record.printer in self.services:
                service = self.services[record.printer]
                log.info("farm: job %d cancelled from the farm", message["job"])
                # Kept while it runs (the loop holds only a weak reference to a task).
                cancelling = asyncio.get_running_loop().create_task(service.cancel(record.id))
                self._cancels.add(cancelling)
                cancelling.add_done_callback(self._cancels.discard)

    def _look_again(self) -> None:
        """News (a job queued, a reconnection, a quiet while): every printer whose last
        claim found nothing looks again."""
        self.news += 1
        for service in self.services.values():
            service.wake()

    # --- the printers' queue -----------------------------------------------------------------

    async def take(self, printer: str) -> JobRecord | None:
        """The printer's next job: one queued here for it (its own, or a farm job it claimed
        before), else the best farm job it can print, claimed now."""
        record = self.store.next_queued(printer)
        if record is None:
            record = await self._claim(printer)
            if record is None:
                return None
        if record.farm_id is not None and not await self._prepare(record):
            return None
        return self.store.claim(record.id)

    async def _claim(self, printer: str) -> JobRecord | None:
        now = time.monotonic()
        news = self.news
        if self._looked.get(printer) == news and now - self._last_check.get(printer, 0) < RECHECK:
            return None  # nothing new since it last found nothing
        if not self.ready:
            return None
        self._last_check[printer] = now
        try:
            row = await self._call(self.db.claim(self.id, printer, self.caps[printer], TIMEOUT))
        except FarmAway:
            return None
        if row is None:
            self._looked[printer] = news  # news that came meanwhile makes it look again
            return None
        self.cache.mkdir(parents=True, exist_ok=True)
        name = row["name"]
        path = self.cache_path(row["file"], name)
        log.info("farm: printer %s claimed farm job %d (%s)", printer, row["id"], name)
        return self.store.submit(
            printer,
            name,
            path.relative_to(self.data_dir).as_posix(),
            row["total_lines"],
            row["submitted_by"],
            from_line=row["from_line"],
            farm=(row["id"], row["fence"]),
        )

    def cache_path(self, digest: str, name: str) -> Path:
        """Where this node keeps a farm file (fetched, or uploaded here)."""
        return self.cache / f"{digest[:12]}-{name}"

    async def _prepare(self, record: JobRecord) -> bool:
        """A farm job about to stream here: its file fetched, checked for this printer (a
        job it cannot print goes back to the farm), and its claim still valid."""
        assert record.farm_id is not None and record.fence is not None
        if not self.ready:
            return False  # the database is away: it starts once the claim can be confirmed
        path = self.data_dir / record.file
        try:
            if not path.exists():
                job = await self._call(self.db.job(record.farm_id, TIMEOUT))
                if job is None or job["fence"] != record.fence:
                    self._drop(record, "its claim no longer holds (the farm gave it elsewhere)")
                    return False
                await self._call(self.db.fetch_file(job["file"], path, FILE_TIMEOUT), FILE_TIMEOUT)
            service = self.services[record.printer]
            errors: list[str] = []
            try:  # a file this printer passed before (another copy) is not read again
                if not await asyncio.to_thread(service.was_checked, path):
                    _, findings, _ = await asyncio.to_thread(service.check, path)
                    errors = [
                        f.format(record.name) for f in findings if f.severity is Severity.ERROR
                    ]
            except HostError as exc:
                errors = [str(exc)]
            if errors:
                key = f"{self.id}/{record.printer}"
                why = "; ".join(errors[:3])
                await self._call(self.db.give_back(record.farm_id, record.fence, key, why, TIMEOUT))
                self._drop(record, f"it cannot print it here: {why}")
                return False
            if not await self._call(self.db.start(record.farm_id, record.fence, TIMEOUT)):
                self._drop(record, "its claim no longer holds (the farm gave it elsewhere)")
                return False
        except FarmAway:
            return False
        except FileNotFoundError as exc:
            self._drop(record, str(exc))
            return False
        return True

    def _drop(self, record: JobRecord, why: str) -> None:
        log.warning("farm: job %d not printed on %s: %s", record.farm_id, record.printer, why)
        self.store.drop(record.id)

    # --- estimates ---------------------------------------------------------------------------

    def estimate(self, jobs: list[int], path: Path, from_line: int | None = None) -> None:
        """Plan ``path`` in the background (the rest from ``from_line``, when given) and
        give ``jobs`` the planned time: a request never waits for a plan."""
        self._unestimated.put_nowait((jobs, path, from_line))

    async def _estimate_jobs(self) -> None:
        """Plan the files of the jobs waiting for their estimate, one at a time (a plan
        takes a core for seconds), and write each estimate when the database answers."""
        while not self._stopping:
            jobs, path, from_line = await self._unestimated.get()
            try:
                found = await asyncio.to_thread(estimates.planned, self.analyses, path, from_line)
            except Exception as exc:  # unreadable, the host ending, a bug: they go without
                if not self._stopping:
                    log.warning("farm: jobs %s have no estimate: %s", jobs, exc)
                continue
            if found is None:
                continue  # a file without moves has no planned time
            seconds, heating, of = found
            delay = 1.0
            while not self._stopping:
                try:
                    await self._call(self.db.estimated(jobs, seconds, of, TIMEOUT, heating))
                    break
                except FarmAway:
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, RETRY_MAX)

    # --- reports -----------------------------------------------------------------------------

    def _changed(self, printer: str) -> None:
        self._dirty.add(printer)
        self._wake_sync.set()

    async def _sync(self) -> None:
        """Tell the farm what the printers did (their jobs' records) and how they stand."""
        while not self._stopping:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake_sync.wait(), SYNC_INTERVAL)
            self._wake_sync.clear()
            if not self.ready:
                continue
            try:
                await self._push_records()
                await self._push_printers()
            except FarmAway:
                continue
            except Exception:
                log.exception("farm: a report failed; trying again")
                await asyncio.sleep(SYNC_INTERVAL)

    async def _push_records(self) -> None:
        for record in self.store.unsynced():
            assert record.farm_id is not None and record.fence is not None
            fields = {
                "state": record.state.value,
                "lines": record.lines,
                "last_line": record.last_line,
                "started": record.started,
                "ended": record.ended,
                "error": record.error,
                "report": record.report,
                "filament": json.loads(record.filament) if record.filament else None,
                "safe_stop": record.safe_stop,
                "local_id": record.id,
                "expected_end": self._expected_end(record),
            }
            taken = await self._call(self.db.report(record.farm_id, record.fence, fields, TIMEOUT))
            if not taken:
                log.warning(
                    "farm: job %d: the farm no longer takes this node's word on it (a newer "
                    "claim holds it); kept here as job %d",
                    record.farm_id,
                    record.id,
                )
            self.store.mark_synced(record.id, record.version)

    def _expected_end(self, record: JobRecord) -> float | None:
        """When ``record``'s job should end (a timestamp), as its printer's page says; None
        unless it is printing (a paused job's end waits for a person) and its time left is
        known."""
        service = self.services.get(record.printer)
        running = service.running if service is not None else None
        if (
            record.state is not JobState.PRINTING
            or service is None
            or service.state != "printing"
            or running is None
            or running.record.id != record.id
        ):
            return None
        now = time.time()
        left, _ = running.time_left()
        return now + left if left is not None else None

    async def _push_printers(self) -> None:
        for name in list(self._dirty):
            self._dirty.discard(name)
            service = self.services[name]
            running = service.running
            state = "offline" if service.state in ("disconnected", "connecting") else service.state
            job = running.record.farm_id if running is not None else None
            pace = self._pace(name)
            shown = (state, service.held, job, pace)
            if self._shown.get(name) == shown:
                continue
            try:
                await self._call(
                    self.db.printer_state(self.id, name, state, service.held, job, pace, TIMEOUT)
                )
            except FarmAway:
                self._dirty.add(name)
                raise
            self._shown[name] = shown

    def _pace(self, printer: str) -> float | None:
        """The printer's pace as it plans its own jobs with it (learned from its past jobs'
        and kept in its store: a job's end changes it); None while none of its jobs has one."""
        paces = self.store.paces(printer)
        return learned_pace(paces) if paces else None
