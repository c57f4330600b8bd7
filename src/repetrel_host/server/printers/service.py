"""One printer of the print server: its long-lived session and its queue.

The service connects (and, when the port is not there, keeps trying with backoff:
the server never stops because a printer vanished), and whenever the session is READY
and the queue holds a job, prints the next one, recording how it goes in the store. It
never starts a job by itself after an interrupted one: the queue is held until someone
releases it, and the interrupted job's safe stop is sent as soon as the printer answers.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import repetrel_host as rh
from repetrel_host.config import Loadout, UserConfig
from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.heat_rates import learned_heat_rates
from repetrel_host.gcode.lint import Finding
from repetrel_host.gcode.timeline import learned_pace
from repetrel_host.server.analyses import Analyses
from repetrel_host.server.events import (
    JobChanged,
    PrinterMessage,
    PrinterState,
    ServerEvent,
    StateDetail,
    TemperatureReadings,
    ZChanged,
)
from repetrel_host.server.printers.checks import JobChecks
from repetrel_host.server.printers.config import PrinterConfig
from repetrel_host.server.printers.forecast import Forecast, forecast, iso
from repetrel_host.server.printers.host_actions import HostActions, snapshot_name
from repetrel_host.server.printers.running import (
    Running,
    filament_used,
    progress_event,
    read_file,
)
from repetrel_host.server.store import PROGRESS_INTERVAL, JobQueue, JobRecord, JobState, Store
from repetrel_host.session.camera import SnapshotFailed
from repetrel_host.session.events import PrinterEvent
from repetrel_host.session.job import HostAction
from repetrel_host.session.planning import (
    JobPlan,
    JobRequest,
    recovery_plan,
)
from repetrel_host.session.print_job import PLAN_AFTER
from repetrel_host.session.workers import in_worker

READING_GRACE = 10.0  # seconds a job's end waits for its file's reading (its filament)
log = logging.getLogger("repetrel_host.server")
RECONNECT_FIRST = 0.5
RECONNECT_MAX = 10.0
_OFFLINE = ("disconnected", "connecting")
TEMPERATURE_SAMPLES = 1800  # reports kept: 30 min at a report a second
SAFE_STOP_TIMEOUT = 30.0
# A cancel is answered once the job ended, or after this long (or once its safe stop is
# said to be held up): 202, the job still stopping, and why.
CANCEL_ANSWER = 10.0
SERVER_STOPPED = "the server was stopped"
STOPPED_SAFELY = "the server was stopped: the job was stopped with its safe stop, confirmed"
COMMAND_TIMEOUT = 60.0
CONTROLS = ("pause", "resume", "cancel", "hold", "release")
ON_REQUEST = "held on request"  # a hold someone asked for, not a part on the bed


class Refused(Exception):
    """A control or command the printer cannot take now; ``status`` is its HTTP status."""

    def __init__(self, message: str, status: int = 409) -> None:
        super().__init__(message)
        self.status = status


class PrinterService:
    """A printer's session, and the loop that feeds it its queue."""

    def __init__(
        self,
        name: str,
        config: PrinterConfig,
        store: Store,
        data_dir: Path,
        user: UserConfig,
        publish: Callable[[ServerEvent], None] = lambda event: None,
        analyses: Analyses | None = None,
    ) -> None:
        self.name = name
        self.config = config
        self.port = config.port
        self.store = store
        # Where its jobs come from: this server's queue, or a farm's (set by the server).
        self.queue: JobQueue = store
        self.data_dir = data_dir
        self.user = user
        self.publish = publish  # the server's events
        # The files' analyses (the server's, shared by its printers).
        self.analyses = analyses or Analyses(data_dir / "analysis", data_dir)
        self.printer: rh.Printer | None = None
        self.running: Running | None = None
        # Why the queue waits for a release (a part may be on the bed), kept in the store
        # across restarts; None while it runs.
        self.hold_reason: str | None = store.hold_reason(name)
        self._hold_after_start: str | None = None  # a hold a start lifted for its job only
        self.selected: Path | None = None  # OctoPrint's selected file, started by "start"
        # The last job, kept after it ended (OctoPrint shows its file and final progress
        # until another file is selected), with how and when it ended.
        self.finished: Running | None = None
        self.finished_state: JobState | None = None
        # Why it ended, as its record will say once it is written (a moment after the end).
        self.finished_error: str | None = None
        self.finished_at: float | None = None
        self.phase = ""  # "pausing", "resuming": asked for, not reached yet
        # The temperature reports of the last half hour or so (time, sensor: (actual, target)).
        self.temperature_history: deque[tuple[float, dict[str, tuple[float, float | None]]]] = (
            deque(maxlen=TEMPERATURE_SAMPLES)
        )
        self.offsets: dict[str, float] = {}  # OctoPrint's temperature offsets (kept, told)
        self.last_error = ""
        # Since when the printer is in its state, and why, as the session said (a lost
        # port's sentence): what "offline since 10:42" shows.
        self.state_since = time.time()
        self.state_reason = ""
        self._state_shown = "offline"
        # Told at once of every change of state or phase (the session's too): the push
        # socket's current state, which must not miss a short phase. Quick, never awaiting.
        self.watchers: list[Callable[[], None]] = []
        self._z: float | None = None  # the job's height last told (OctoPrint's ZChange)
        self._print_time: tuple[object, float, float | None] | None = None
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self.stop_timeout = SAFE_STOP_TIMEOUT  # how long stop() waits for a safe stop
        self._paused = False
        self._forwarding: asyncio.Task[None] | None = None
        self._connecting: asyncio.Task[None] | None = None
        # The session that owes the store's owed safe stop: only its own confirmation
        # settles it (another session confirmed nothing of it).
        self._owed_by: rh.Printer | None = None
        self._starting: int | None = None  # the job being started
        self._cancel_starting = False
        self._ended = asyncio.Event()  # a job ended and was recorded
        self._held = asyncio.Event()  # the running job's safe stop is held up
        self.stop_held = ""  # why, while it is
        self._cancelling: int | None = None  # the job a cancel was asked for
        # After a job ends, start the next one by itself (a farm with an automatic bed
        # change); else the queue is held until released (Moonraker's automatic_transition).
        self.automatic_transition = False
        # A person's start of a file releases the hold (they say the bed is clear); a farm
        # whose every start waits for a release sets this (start_waits_for_release).
        self.start_waits_for_release = False
        loadout = Path(config.loadout) if config.loadout is not None else None
        # What it checks before a job starts, and the files that passed (checks.py).
        self.checks = JobChecks(JobRequest(loadout, config.machine), user, self._firmware)
        # Its camera, and what its jobs' host codes do (host_actions.py).
        self.host_actions = HostActions(name, config, data_dir, publish)
        self.camera = self.host_actions.camera

    # --- lifecycle ---------------------------------------------------------------

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=self.name)

    async def stop(self) -> None:
        """Stop feeding; a running job is stopped with its safe stop first (and recorded as
        interrupted); the port is closed."""
        self._stopping = True
        self._wake.set()
        running = self.running
        if running is not None and not running.job.done:
            if not running.job.stopping:
                running.job.stop(rh.JobError(SERVER_STOPPED))
            # Held up (a heat wait nothing breaks): it goes once the wait ends, so the whole
            # stop timeout is given to it.
            if not await self._ending(self.stop_timeout, held_up_too=True):
                # Still held up (a long heat wait, a silent controller): the server does not
                # wait for it. The job is recorded so, and its safe stop owed.
                log.warning("printer %s: leaving the safe stop unconfirmed", self.name)
                running.job.stop()
                with contextlib.suppress(rh.HostError, TimeoutError):
                    await asyncio.wait_for(running.job.wait(), 5)
        if self._task is not None:
            # The loop records how the job ended, then sees it is stopping.
            done, _ = await asyncio.wait([self._task], timeout=2.0)
            if not done:
                self._task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await self._task
        if self.printer is not None:
            await self.printer.close()
        if self.camera is not None:
            await self.camera.close(2.0)

    def wake(self) -> None:
        """Something changed (a job queued, the queue released): look again."""
        self._wake.set()

    @property
    def state(self) -> str:
        printer = self.printer
        return printer.state.value if printer is not None else "disconnected"

    # --- the loop -------------------------------------------------------------------

    async def _run(self) -> None:
        self.connect()
        assert self._connecting is not None
        await self._connecting
        while not self._stopping:
            try:
                await self._next()
            except Exception:  # a store error, a bug: logged, and the printer goes on
                log.exception("printer %s: the queue loop failed; going on in 1 s", self.name)
                await asyncio.sleep(1.0)

    async def _next(self) -> None:
        """Print the next queued job if the printer is ready and the queue not held."""
        printer = self.printer
        assert printer is not None
        if (
            printer is self._owed_by
            and printer.state is rh.State.READY
            and not printer.owed_safe_stop
            and self.store.owing(self.name)
        ):
            self._sent()  # the session that owed it sent it, once the printer answered
        record = None
        if printer.state is rh.State.READY and not self.held:
            record = await self.queue.take(self.name)
            if record is not None and self._hold_after_start is not None:
                self._keep_hold(self._hold_after_start)
                self._hold_after_start = None
        if record is None:
            self._wake.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), 1.0)  # or a state change
            return
        await self._print(record)

    async def _connect(self) -> None:
        delay = RECONNECT_FIRST
        while not self._stopping:
            if not self.last_error:  # not again at each try of a port that stays away
                log.info("printer %s: connecting to %s", self.name, self.port)
            # A safe stop owed from before a restart goes first, for every heater kept.
            owed = self.store.heaters(self.name) if self.store.owing(self.name) else None
            try:
                self.printer = await self.config.connect(self.user, self._heard, owed)
                self._owed_by = self.printer if owed is not None else None
            except rh.HostError as exc:
                if str(exc) != self.last_error:
                    log.warning("printer %s: %s (trying again)", self.name, exc)
                self.last_error = str(exc)
                await asyncio.sleep(delay)
                delay = min(delay * 2, RECONNECT_MAX)
                continue
            log.info("printer %s: connected on %s", self.name, self.port)
            self.last_error = ""
            self._keep_heaters(self.printer)
            self.printer.watch(self.changed)
            self.changed()
            self._forwarding = asyncio.get_running_loop().create_task(self._forward(self.printer))
            return

    def _heard(self, event: PrinterEvent) -> None:
        """The session's events as they come, before connect() returns too: a greeting
        that goes again unanswered is logged as it happens (once the port fails alike
        again and again, only at the debug level)."""
        if isinstance(event, rh.NoAnswerYet):
            level = logging.DEBUG if self.last_error else logging.INFO
            where = f"{event.port} at {event.baud} baud"
            log.log(level, "printer %s: %s: %s", self.name, where, event.text)

    async def _ending(self, patience: float, held_up_too: bool = False) -> bool:
        """Wait until the running job ended, for at most ``patience`` seconds, or until its
        safe stop is said to be held up (unless ``held_up_too``); True when it ended."""
        running = self.running
        if running is None:
            return True
        ending: asyncio.Future[Any] = asyncio.ensure_future(running.job.wait())
        held: asyncio.Future[Any] = asyncio.ensure_future(self._held.wait())
        waits = [ending] if held_up_too else [ending, held]
        try:
            await asyncio.wait(waits, timeout=patience, return_when="FIRST_COMPLETED")
        finally:
            held.cancel()
            if not ending.done():
                ending.cancel()
            elif not ending.cancelled():
                ending.exception()  # retrieved: the loop records how it ended
        return running.job.done

    def _keep_heaters(self, printer: rh.Printer) -> None:
        """The heaters the session turned on, kept in the store as they change (before the
        line that turns one on goes), and now: a safe stop owed after a kill -9 and a
        restart turns every one of them off."""
        heaters = printer.heater_log

        def keep() -> None:
            self.store.keep_heaters(self.name, heaters.on())

        heaters.on_change = keep
        keep()

    def _sent(self) -> None:
        """The safe stop the printer was owed went: its jobs' records say so."""
        self._owed_by = None
        for job_id in self.store.safe_stop_sent(self.name):
            log.info("printer %s: job %d's safe stop went", self.name, job_id)
            self.job_changed(job_id)

    async def _print(self, record: JobRecord) -> None:
        printer = self.printer
        assert printer is not None
        path = self.data_dir / record.file
        history = self.data_dir / "history" / f"{record.id}-{Path(record.name).stem}.gcode"
        self._starting, self._cancel_starting = record.id, False
        try:
            plan = self.plan(path)
            checked = self.checks.passed(path, plan)
            job_or_path: JobPlan | Path = path
            if checked and record.from_line is not None:
                # Where a recovered job starts is found by reading the file up to there:
                # a thread's work, not the event loop's (every printer's stream).
                job_or_path = await asyncio.to_thread(recovery_plan, plan, record.from_line)
            elif checked:
                job_or_path = plan
            job = await printer.print(
                job_or_path,
                history=history,
                on_action=self._perform,
                report=self.config.report,
                from_line=record.from_line if job_or_path is path else None,
            )
        except rh.HostError as exc:  # refused (a check), or the printer went meanwhile
            if printer.state is not rh.State.READY and not isinstance(exc, rh.JobError):
                self.store.set_state(record.id, JobState.QUEUED)  # not the job's fault
                return
            self.store.set_state(record.id, JobState.FAILED, str(exc))
            log.warning("printer %s: job %d refused: %s", self.name, record.id, exc)
            self.job_changed(record.id)
            return
        finally:
            self._starting = None
        # Its time from its first second: its file's plan (its upload's analysis, if in
        # memory) at the printer's pace from its past jobs.
        analysed, prior = self.analyses.known(path), self.pace()
        running = self.running = Running(record, job, summary=analysed, prior=prior)
        self._z = None
        self.changed()
        self._held.clear()
        self.stop_held = ""
        watching = asyncio.ensure_future(self._watch(job))
        if self._cancel_starting:
            self._cancelling = record.id
            job.stop()
        self._paused = False
        farm = f", farm job {record.farm_id}" if record.farm_id is not None else ""
        log.info("printer %s: printing job %d (%s%s)", self.name, record.id, record.name, farm)
        self.job_changed(record.id)
        # The plan's time at each line (in a worker process), for the time left and the pace;
        # at once when its file's plan is not there to tell it meanwhile (an upload printed).
        rates = learned_heat_rates(self.store.heat_rates(self.name))
        after = PLAN_AFTER if analysed is not None and analysed.planned_seconds else 0.0
        following = asyncio.ensure_future(job.follow_time(prior, in_worker, after, rates))
        # Its file read while it streams (a big file takes long): its progress goes out
        # from the start, its layers and filament once they are known.
        reading = asyncio.ensure_future(read_file(running, self.analyses, path, self.name))
        state, error = JobState.COMPLETED, None
        ending = asyncio.ensure_future(job.wait())
        try:
            while not ending.done():
                await asyncio.wait({ending}, timeout=PROGRESS_INTERVAL)
                self._record_progress(record, job)
            summary = ending.result()
            if summary.outcome is rh.Outcome.CANCELLED:
                state = JobState.CANCELLED
                if self._stopping and self._cancelling != record.id:
                    state, error = JobState.INTERRUPTED, STOPPED_SAFELY
        except rh.HostError as exc:
            state, error = JobState.FAILED, str(exc)
            if self._cancelling == record.id:
                state = JobState.CANCELLED  # cancelled, its safe stop not confirmed: said
            elif self._stopping:
                state = JobState.INTERRUPTED
                if str(exc).startswith(SERVER_STOPPED) and not printer.owed_safe_stop:
                    error = STOPPED_SAFELY
        finally:
            completed = (
                state is JobState.COMPLETED
                and ending.done()
                and not ending.cancelled()
                and ending.exception() is None
            )
            self._record_progress(record, job, completed)
            self.finished, self.finished_state, self.finished_at = running, state, time.time()
            self.finished_error = error
            self.selected = None
            self.running = None
            self.changed()
            watching.cancel()
            following.cancel()
        # Its filament goes in its record: read by now, but for a big file (whose job ended
        # soon: it goes without rather than hold the queue up); its end is when it ended.
        await asyncio.wait({reading}, timeout=READING_GRACE)
        reading.cancel()
        report = job.report  # the controller's M773 report, kept with the job
        used = filament_used(running, completed)
        text = report.text if report else None
        self.store.set_state(
            record.id, state, error, text, used, job.pace, self.finished_at, job.heat_rates
        )
        if printer.owed_safe_stop or isinstance(ending.exception(), rh.SafeStopError):
            # Owed to the printer's next contact, whatever the job is recorded as (and
            # after a restart too): the session sends it once the printer answers.
            self.store.owe_safe_stop(record.id)
            self._owed_by = printer
            log.warning("printer %s: job %d's safe stop is owed", self.name, record.id)
        why = f": {error}" if error else ""
        log.info("printer %s: job %d %s%s", self.name, record.id, state, why)
        if not self.automatic_transition or state is JobState.INTERRUPTED:
            # The part is still on the bed (an automatic bed change ran only if the job
            # ended as written): the next job waits for someone to say so.
            self._keep_hold(f"job {record.id} {state}: its part may still be on the bed")
        self.job_changed(record.id)
        self._state_changed()
        self._ended.set()

    async def _watch(self, job: rh.PrintJob) -> None:
        """The job's word that its safe stop is held up: logged, told, and remembered."""
        async for event in job.events():
            if isinstance(event, rh.StopDelayed):
                on = f"; heaters that may be on: {', '.join(event.heaters)}" * bool(event.heaters)
                self.stop_held = f"the safe stop is held up: {event.reason}{on}"
                log.warning("printer %s: %s", self.name, self.stop_held)
                self.host_actions.tell(self.stop_held)
                self._held.set()

    def _record_progress(
        self, record: JobRecord, job: rh.PrintJob, completed: bool = False
    ) -> None:
        last = job.last
        self.store.progress(record.id, job.lines, last.source_line if last else 0)
        event = progress_event(self.name, record, job, self.running, completed)
        # The printer's free time goes with it: it moves with the time left (and the queue).
        free_at = self.forecast(event.time_left).free_at if not completed else None
        self.publish(replace(event, free_at=iso(free_at)))
        z = self.running.z if self.running is not None else None
        if z is not None and z != self._z:  # a new height, as the slicer marked it
            self.publish(ZChanged(self.name, z, self._z))
            self._z = z
        paused = self.printer is not None and self.printer.state is rh.State.PAUSED
        if paused != self._paused and not job.done:
            self._paused = paused
            log.info(
                "printer %s: job %d %s", self.name, record.id, "paused" if paused else "resumed"
            )
            self.store.set_state(record.id, JobState.PAUSED if paused else JobState.PRINTING)
            self.job_changed(record.id)

    # --- the queue's times (forecast.py) ------------------------------------------------

    def running_left(self) -> float | None:
        """The seconds the running job has left (None: no job runs, or none can tell)."""
        running = self.running
        return running.time_left()[0] if running is not None and not running.job.done else None

    def forecast(
        self, left: float | None, summaries: Mapping[int, FileSummary | None] | None = None
    ) -> Forecast:
        """The queued jobs' times and when the printer is free, the running job having
        ``left`` seconds to go (:meth:`running_left`, or its progress event's). ``summaries``:
        the queued jobs' files' analyses by job id (:meth:`queued_summaries`); by default
        those in memory (for the event loop: a file not read since the start has none yet)."""
        queued = self.store.queued(self.name)
        if summaries is None:
            summaries = {r.id: self.analyses.known(self.data_dir / r.file) for r in queued}
        pace = self.pace() if queued else 1.0
        return forecast(queued, summaries, pace, self._free_from(left), self.held)

    def pace(self) -> float:
        """This printer's pace from its past jobs (actual over planned moving time; 1: none
        yet): what its jobs' times are given at before a run shows its own."""
        return learned_pace(self.store.paces(self.name))

    def queued_summaries(self) -> dict[int, FileSummary | None]:
        """The analyses of the queued jobs' files (in a thread: read from the data folder;
        a file whose print time is not worked out yet is planned in the background)."""
        return {
            record.id: self.analyses.summary(self.data_dir / record.file)
            for record in self.store.queued(self.name)
        }

    def _free_from(self, left: float | None) -> float | None:
        """When the printer is free of what it does now: the running job's end, now when it
        is ready and idle; None when it cannot be told (paused, offline, a job's time left
        unknown, the queue held with nothing running: a part is on the bed)."""
        now = time.time()
        if self.running is not None:
            return now + left if self.state == "printing" and left is not None else None
        return now if self.state == "ready" and not self.held else None

    # --- checks (checks.py) ------------------------------------------------------------

    def plan_key(self) -> str:
        """What its jobs' plans depend on besides their file: its machine, its loadout and
        the firmware that answered (another key: a file's print time is planned again)."""
        firmware = self._firmware()
        return f"{self.checks.request}|{firmware.identity if firmware is not None else ''}"

    def _firmware(self) -> rh.Firmware | None:
        printer = self.printer
        return printer.firmware if printer else None

    def plan(self, path: Path) -> JobPlan:
        """What this printer would stream for ``path``: its machine, loadout and firmware."""
        return self.checks.plan(path)

    def check(self, path: Path) -> tuple[JobPlan, list[Finding], int]:
        """The job lint for this printer, and the lines the job sends (any thread but the
        event loop's: a worker process reads the file). A file with no errors is remembered
        as checked, so that its job starts without a second pass."""
        return self.checks.check(path)

    def was_checked(self, path: Path) -> bool:
        """``path``, as it is now, passed this printer's check already (any thread)."""
        return self.checks.was_checked(path)

    def plan_loadout(self) -> Loadout | None:
        """The printer's loadout (its heads), as a job's plan reads it; None without one or
        when it cannot be read (a job then says why)."""
        return self.checks.plan_loadout()

    def renamed(self, old: Path, new: Path) -> None:
        """``old`` is now ``new`` (the same file): its check goes with it."""
        self.checks.renamed(old, new)

    def forget(self, path: Path) -> None:
        """``path`` is gone: its check with it."""
        self.checks.forget(path)

    # --- host actions (host_actions.py) ------------------------------------------------

    async def _perform(self, action: HostAction) -> bool:
        return await self.host_actions.perform(action, self.running)

    async def snapshot(self) -> Path:
        """A snapshot now, awaited; :class:`Refused` without a camera or when it fails."""
        if self.camera is None:
            raise Refused(f"printer {self.name} has no camera (camera = ... in its settings)")
        try:
            return await self.camera.take_now(snapshot_name(""))
        except SnapshotFailed as exc:
            raise Refused(f"printer {self.name}: {exc}", 502) from None

    def url(self, snapshot: Path) -> str:
        """Where the API serves ``snapshot``."""
        return self.host_actions.url(snapshot)

    # --- events -----------------------------------------------------------------------

    def job_changed(self, job_id: int) -> None:
        record = self.store.job(job_id)
        if record is not None:
            self.publish(JobChanged(self.name, record))

    async def _forward(self, printer: rh.Printer) -> None:
        """The session's states, temperatures and messages, as the server's events."""
        name = self.name
        async for event in printer.events():
            if isinstance(event, rh.StateChanged):
                state = event.state.value
                # READY as a job ends is told once its end is recorded (its last progress
                # and its job event first): no dashboard sees "ready" at 99 %.
                if event.state is not rh.State.READY or self.running is None:
                    self.changed()  # since and reason follow the state shown
                    self.publish(self.state_event(state))
                self.wake()  # READY again: the queue may go on
            elif isinstance(event, rh.Temperatures):
                now, readings = time.time(), dict(event.readings)
                self.temperature_history.append((now, readings))
                self.publish(TemperatureReadings(name, now, readings))
            elif isinstance(event, rh.NoAnswerYet):
                continue  # logged as it came (_heard)
            else:
                self.publish(PrinterMessage(name, event.text))

    # --- control ----------------------------------------------------------------------

    def changed(self) -> None:
        """The state or a phase may have changed: the watchers are told."""
        # Offline is one state to a person, however often the session tries the port again
        # meanwhile (disconnected, connecting, disconnected...).
        shown = "offline" if self.state in _OFFLINE else self.state
        if shown != self._state_shown:
            self._state_shown, self.state_since, self.state_reason = shown, time.time(), ""
        reason = self.printer.state_reason if self.printer is not None else ""
        self.state_reason = reason or self.state_reason
        for watcher in self.watchers:
            watcher()

    def _state_changed(self) -> None:
        self.changed()
        self.publish(self.state_event(self.state))

    def state_event(self, state: str) -> PrinterState:
        """The event of a new state: with since when, why, and a phase asked for."""
        reason = self.state_reason or self.last_error or None
        # The phase: "pausing", "resuming", asked for and not reached.
        detail = StateDetail(self.state_since, reason, self.phase or None)
        return PrinterState(self.name, state, self.held, detail)

    def select(self, path: Path | None) -> None:
        """OctoPrint's selected file (None: unselect); the last job's is forgotten."""
        self.selected = path
        if path is not None or self.running is None:
            self.finished = None

    def last_print_time(self, path: Path) -> float | None:
        """How long the last completed print of ``path`` took, in seconds (asked of the
        store again after 10 s, or once a job ended: the push socket asks every tick)."""
        key = (path, self.finished_at)
        known = self._print_time
        if known is not None and known[0] == key and time.monotonic() - known[1] < 10.0:
            return known[2]
        try:
            file = path.relative_to(self.data_dir).as_posix()
        except ValueError:
            return None
        last = self.store.prints(file).get("last")
        seconds = last.get("printTime") if last else None
        self._print_time = (key, time.monotonic(), seconds)
        return seconds

    @property
    def held(self) -> bool:
        """The queue waits for a release."""
        return self.hold_reason is not None

    def hold(self, reason: str = ON_REQUEST) -> None:
        """Start no more jobs (the running one goes on) until :meth:`release`; the hold
        outlives a restart and a kill -9."""
        self._keep_hold(reason)
        self._state_changed()

    def _keep_hold(self, reason: str) -> None:
        """The hold, kept in the store (told by the caller, once its job is told)."""
        self.store.hold(self.name, reason)
        self.hold_reason = reason

    def hold_note(self) -> str:
        """The hold as a client shows it: why, and what ends it ("" when not held)."""
        if self.hold_reason is None:
            return ""
        if self.hold_reason == ON_REQUEST:
            return f"Queue held ({ON_REQUEST}): release the queue to run the queued jobs"
        then = "release the queue" if self.start_waits_for_release else "start a print"
        return f"Queue held ({self.hold_reason}): clear the bed, then {then}"

    def start_asked(self, file: str, by: str | None, via: str) -> bool:
        """A person's explicit start of ``file`` (``via`` a face's start: every face calls
        this one rule) says the bed is clear: a held queue is released, and True (the job
        then goes before those that waited behind the hold). :class:`Refused`, with why,
        when every start waits for a release (start_waits_for_release)."""
        reason = self.hold_reason
        if reason is None:
            return False
        if self.start_waits_for_release:
            raise Refused(
                f"printer {self.name}'s queue is held ({reason}): release it once nothing "
                "is still on the bed (start_waits_for_release: a start does not release it)"
            )
        who = f"{by or 'a client'} starting {file} ({via})"
        log.info("printer %s: the queue's hold (%s) released by %s", self.name, reason, who)
        self.release()
        if reason == ON_REQUEST:
            # A hold someone asked for is the queue's, not the bed's: it holds the jobs
            # that wait again as soon as the started one is taken.
            self._hold_after_start = reason
        return True

    def release(self) -> None:
        """Let the queue run again (after an interrupted job was looked at)."""
        self.store.release(self.name)
        self.hold_reason = None
        self.wake()
        self._state_changed()

    async def control(self, action: str) -> None:
        """pause, resume, cancel (the running job), hold or release; :class:`Refused` when
        the printer cannot do it now."""
        printer = self.printer
        try:
            if action == "release":
                self.release()
            elif action == "hold":
                self.hold()
            elif action == "cancel":
                if not await self.cancel():
                    raise Refused(f"printer {self.name} has no job to cancel")
            elif action in ("pause", "resume"):
                if printer is None:
                    raise Refused(f"printer {self.name} is not connected")
                self.phase = f"{action[:-1]}ing"  # until reached: OctoPrint's Pausing...
                self._state_changed()
                try:
                    await (printer.pause() if action == "pause" else printer.resume())
                finally:
                    self.phase = ""
                    self._state_changed()
            else:
                raise Refused(f"no action '{action}' ({', '.join(CONTROLS)})", 404)
        except rh.UsageError as exc:
            raise Refused(str(exc)) from None

    async def disconnect(self) -> None:
        """Close the port until :meth:`connect` (OctoPrint's disconnect); refused while a
        job runs (cancel it first: its safe stop needs the port)."""
        if self.running is not None or self._starting is not None:
            raise Refused(f"printer {self.name} is printing: cancel the job before disconnecting")
        printer = self.printer
        if printer is None or printer.state is rh.State.CLOSED:
            return
        if self._forwarding is not None:
            self._forwarding.cancel()
        await printer.close()
        log.info("printer %s: disconnected (the port is free until connect)", self.name)
        self._state_changed()

    def connect(self) -> None:
        """Open the port (at start, and again after :meth:`disconnect`, as OctoPrint's
        connect) in the background. One connect loop per printer: a second one would race
        the running session's own reconnect for the port, and a session that took it would
        owe nothing the job's session owes."""
        printer = self.printer
        if printer is not None and printer.state is not rh.State.CLOSED:
            return
        if self._connecting is None or self._connecting.done():
            self._connecting = asyncio.get_running_loop().create_task(self._connect())

    async def command(self, line: str) -> rh.Reply:
        """One G-code line to a printer that is not printing, with the controller's reply."""
        printer = self.printer
        if printer is None:
            raise Refused(f"printer {self.name} is not connected")
        try:
            return await printer.command(line, timeout=COMMAND_TIMEOUT)
        except rh.UsageError as exc:
            raise Refused(str(exc)) from None
        except rh.HostError as exc:
            raise Refused(f"printer {self.name}: {exc}") from None
        except TimeoutError:
            raise Refused(f"{line}: no reply within {COMMAND_TIMEOUT:.0f} s", 504) from None

    async def emergency_first(self, lines: Sequence[str]) -> bool:
        """An emergency line goes whatever surrounds it: when one of ``lines`` is M112, the
        emergency stop goes now, and True: nothing else of them goes (no move after an
        emergency stop; the session turns the heaters off itself)."""
        if not any(command_word(line.strip().upper()) == "M112" for line in lines):
            return False
        log.warning("printer %s: emergency stop (M112)", self.name)
        await self.command("M112")
        return True

    async def cancel(self, job_id: int | None = None) -> bool:
        """Cancel the running job (``job_id``, or whichever runs) with its safe stop first,
        or a queued one. Returns once it is recorded; False when there is no such job."""
        running = self.running
        if running is not None and job_id in (None, running.record.id):
            self._ended.clear()
            self._cancelling = running.record.id
            if not running.job.stopping:
                running.job.stop()
                log.info(
                    "printer %s: cancelling job %d: the safe stop goes first",
                    self.name,
                    running.record.id,
                )
            if await self._ending(CANCEL_ANSWER):
                with contextlib.suppress(TimeoutError):  # then recorded, at once
                    await asyncio.wait_for(self._ended.wait(), 5)
            return True
        if self._starting is not None and job_id in (None, self._starting):
            self._cancel_starting = True  # stopped as soon as it exists
            return True
        if job_id is not None and self.store.cancel_queued(job_id):
            self.job_changed(job_id)
            return True
        return False
