"""The handle of one job streaming on a session: its progress (read from the pump's run),
its events, its end (what :meth:`PrintJob.wait` returns or raises), and the record of it
beside the print history.

The session's job control (:mod:`.job_control`) starts it and tells it how it went; the job
reaches the session only through :class:`JobPrinter` and :class:`JobSession`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from datetime import datetime
from pathlib import Path
from typing import Protocol

from repetrel_host.errors import HostError
from repetrel_host.gcode.heat_rates import HeatClimbs
from repetrel_host.gcode.timeline import PlannedTime, TimeLeft, Timeline
from repetrel_host.protocol.reports import JobReport, ReportReader
from repetrel_host.session import history as print_history
from repetrel_host.session.events import Done, Failed, JobEvent, Progress, Report, State
from repetrel_host.session.hub import EventFanout
from repetrel_host.session.job import HostAction, JobLine
from repetrel_host.session.planning import JobPlan
from repetrel_host.session.pump import JobRun, Outcome, Summary

# A job's progress goes to its event subscribers at most this often.
PROGRESS_INTERVAL = 0.1
# What a controller holds acknowledged behind the move it runs, so that the time left counts
# from that move. Marlin: its planner's 16 blocks and 4 command slots, the move it runs half
# done on average (on the fake, 15.5 left the time left at a quarter of the cone's first
# layers 7 % short; 19.5 came within 0.2 %). Hyrel's controller holds up to 8 KB.
MARLIN_HELD_MOVES = 19.5
HYREL_HELD_BYTES = 8192
# Seconds a job runs before its time is planned (see PrintJob.follow_time): the planner's
# CPU would slow the stream's start (bench/run.py: a short job 12-20 % slower). A caller that
# shows the time left to a person plans at once (hyrel-send's status line); the server has
# its file's plan from the upload meanwhile.
PLAN_AFTER = 3.0
# Seconds between looks at the line acknowledged, for the pace a job keeps.
PACE_INTERVAL = 0.25
# Events a late subscriber to a job still gets.
JOB_EVENT_BACKLOG = 1000


class JobPrinter(Protocol):
    """The printer a job streams on, as the job (and whoever holds it) sees it."""

    @property
    def state(self) -> State: ...

    @property
    def port(self) -> str: ...

    @property
    def temperatures(self) -> dict[str, tuple[float, float | None]]: ...

    @property
    def protocol(self) -> str: ...

    async def pause(self, at_layer_end: bool = False) -> None: ...

    async def resume(self) -> None: ...

    async def cancel(self) -> None: ...


class JobSession(Protocol):
    """What a job asks of the session that runs it."""

    def stop_job(self, job: PrintJob, error: HostError | None) -> bool:
        """Stop ``job`` (see :meth:`PrintJob.stop`)."""
        ...

    def waits_for_safe_stop(self, job: PrintJob) -> bool:
        """``job`` waits for its safe stop to go after a reconnect."""
        ...

    @property
    def last_sent(self) -> object | None:
        """The link's last line sent (None while unlinked)."""
        ...


ActionHandler = Callable[[HostAction], Awaitable[bool]]
# Runs a function with its arguments (in another process, say) and gives its result.
Runner = Callable[..., Timeline]


class PrintJob:
    """One job streaming on a session: its progress, events and end."""

    def __init__(
        self,
        printer: JobPrinter,
        session: JobSession,
        plan: JobPlan,
        run: JobRun,
        on_action: ActionHandler | None,
        history: Path | None,
    ) -> None:
        self.printer = printer
        self._session = session
        self.plan = plan
        self.name = plan.job.name
        self.size = plan.job.size
        self.history = history  # the stream as transmitted, or None
        self.on_action = on_action
        self._run = run
        self._done: asyncio.Future[Summary] = asyncio.get_running_loop().create_future()
        self._hub: EventFanout[JobEvent] = EventFanout(JOB_EVENT_BACKLOG)
        self._ticking = False  # progress goes out while someone listens
        self._reported = -1
        self.m0: asyncio.Future[None] | None = None  # an M0 waiting for resume()
        self.reports = ReportReader()  # the M773 report, read from the messages
        self.started = datetime.now()
        self.following: TimeLeft | None = None  # the planned time, once follow_time made it
        self._watch: asyncio.Task[None] | None = None
        self.climbs = HeatClimbs()  # its heaters' climbs, timed as it runs
        self._keeper: print_history.ProgressKeeper | None = None  # the progress record

    @property
    def report(self) -> JobReport | None:
        """The M773 report the controller sent (at M30, after M772 S1), or None."""
        return self.reports.report

    # --- progress -------------------------------------------------------------

    @property
    def lines(self) -> int:
        """Job lines the controller acknowledged (the header's and safe stop's not counted)."""
        return self._run.lines

    @property
    def offset(self) -> int:
        """Bytes of the file up to the last acknowledged line."""
        return self._run.offset

    @property
    def last(self) -> JobLine | None:
        """The last job line the controller acknowledged."""
        return self._run.last

    async def follow_time(
        self,
        prior: float = 1.0,
        run: Runner | None = None,
        after: float = PLAN_AFTER,
        heat_rates: Mapping[str, float] | None = None,
    ) -> None:
        """Plan the job's time at its lines, so that :meth:`time_left` can say it; its heat
        waits start where the printer's heaters are, at ``heat_rates`` (the printer's from
        its past jobs, by kind: :func:`~repetrel_host.gcode.heat_rates.learned_heat_rates`;
        else its machine's). ``prior``: the printer's pace from its
        past jobs (see :class:`~repetrel_host.gcode.timeline.TimeLeft`). A long file takes
        seconds of CPU: planned in a thread, through ``run`` when given (``hyrel-send`` and
        the server give :func:`~repetrel_host.session.workers.in_worker`, a worker process,
        so the streams keep the interpreter; a script may too, from a ``__main__`` guard).
        A file that cannot be planned (gone, unreadable, its worker ended) leaves the job
        without it: :meth:`time_left` stays None. Planning starts once the job has run
        ``after`` seconds: its start keeps the CPU, and a job over by then needs no time
        left. The heaters' climbs are timed from the start (:attr:`heat_rates`)."""
        self._watch = asyncio.get_running_loop().create_task(self._watch_run())
        await asyncio.sleep(after)
        if self.done:
            return
        temperatures = {name: current for name, (current, _) in self._heaters().items()}
        rates = dict(heat_rates or {})
        try:
            planning = self.plan.timeline
            timeline = await (
                asyncio.to_thread(run, planning, temperatures, rates)
                if run is not None
                else asyncio.to_thread(planning, temperatures, rates)
            )
        except (OSError, HostError):
            return
        hyrel = self.printer.protocol == "hyrel"
        if hyrel:  # its buffer's bytes, in this job's moves (its commands', not comments)
            held = HYREL_HELD_BYTES * timeline.total_moves / max(timeline.command_bytes, 1)
        else:
            held = MARLIN_HELD_MOVES
        self.following = TimeLeft(timeline, prior, held, received_only=hyrel)

    async def _watch_run(self) -> None:
        """Watched as it runs, whoever asks for the time left or not: the pace it keeps and
        its heaters' climbs go in its record, for the printer's next jobs."""
        while not self.done:
            self.climbs.observe(self._heaters(), time.monotonic())
            if self.following is not None:
                self.time_left()
            await asyncio.sleep(PACE_INTERVAL)

    @property
    def heat_rates(self) -> dict[str, float] | None:
        """The heaters' climbs this run timed, degrees a second by kind (None: none)."""
        return dict(self.climbs.rates) or None

    @property
    def pace(self) -> float | None:
        """The pace this run kept: actual over planned moving time (None: not planned, or
        too little of it watched; see :attr:`TimeLeft.measured`)."""
        return self.following.measured if self.following is not None else None

    @property
    def planned_time(self) -> PlannedTime | None:
        """The job's plan, split into moving, heating and tool changes (None before
        :meth:`follow_time` made it)."""
        following = self.following
        return following.timeline.planned if following is not None else None

    def time_left(self, now: float | None = None) -> float | None:
        """Seconds the job has left at the line acknowledged last: the plan's remainder at
        the pace the run keeps (:meth:`follow_time` first; None before it is planned, and
        0 once the job ended)."""
        if self.done:
            return 0.0
        following = self.following
        if following is None:
            return None
        last = self._run.last
        line = last.source_line if last is not None else 0
        moving = self.printer.state is not State.PAUSED
        now = time.monotonic() if now is None else now
        return following.left(line, now, moving, self._heaters())

    def _heaters(self) -> dict[str, tuple[float, float | None]]:
        """The controller's last temperature reports, named as the plan names its heaters
        (Marlin's T is the active hotend: the first, where it reports no T0)."""
        heard = self.printer.temperatures
        return {
            ("T0" if name == "T" and "T0" not in heard else name): reading
            for name, reading in heard.items()
        }

    def time_until(self, line: int) -> float | None:
        """Seconds until the file's ``line`` is done, from the move the controller runs, at
        the pace the run keeps (0 for a line already run). None before the job is planned
        (:meth:`follow_time`), and once it ended."""
        following = self.following
        if following is None or self.done:
            return None
        last = self._run.last
        return following.until(line, last.source_line if last is not None else 0)

    @property
    def header_lines(self) -> int:
        """Lines of the header (the plan's) the controller acknowledged."""
        return self._run.header_acknowledged

    @property
    def done(self) -> bool:
        return self._done.done()

    @property
    def report_path(self) -> Path | None:
        """Where the M773 report is kept: beside the history, ``<run>-report.txt``."""
        history = self.history
        return history.with_name(f"{history.stem}-report.txt") if history else None

    def where(self) -> str:
        """The last line the controller acknowledged, as error messages name it."""
        return self._run.where()

    @property
    def recovery_line(self) -> int | None:
        """The source line a recovered run would start from (``print(path, from_line=...)``):
        the one after the last job line known to have run. On Hyrel's link, where an ACK
        says only *received*, that is what the controller's answers confirmed (what it held
        when a stop aborted counts as not run); elsewhere the last acknowledged. None when
        no job line ran, or every one did."""
        return self._run.recovery_line

    @property
    def sent_through(self) -> int | None:
        """The source line of the last job line on the wire when the job ended (None while
        it runs, or when none went): from :attr:`recovery_line` to it, lines were sent and
        not confirmed, and some may have run (a lost link takes their oks with it)."""
        sent = self._run.last_sent
        return sent.source_line if sent is not None else None

    @property
    def recovery_known_to_run(self) -> bool:
        """:attr:`recovery_line` follows a line known to have run (Hyrel's link), not one
        acknowledged (an ok: taken to run, as its firmware took it)."""
        return self._run.acks_say_received

    @property
    def all_sent(self) -> bool:
        """The job was read to its end: what is left is the controller's to run."""
        run = self._run
        return run.exhausted and not run.stopping and not run.pause_requested

    @property
    def stopping(self) -> bool:
        """A stop was asked for (the safe stop is going, or went)."""
        return self._run.stop_requests > 0

    @property
    def reconnecting_for_safe_stop(self) -> bool:
        """The link failed before the safe stop went: the job ends once it went after a
        reconnect (or after ``reconnect_wait``); :meth:`stop` gives up waiting."""
        return self._session.waits_for_safe_stop(self)

    @property
    def safe_stop_missing(self) -> list[str]:
        """Safe-stop commands the controller did not confirm (after an abandoned stop)."""
        return self._run.safe_stop_missing

    def events(self) -> AsyncIterator[JobEvent]:
        """Progress, messages, resends, pauses, then Done or Failed (the last event)."""
        if not self._ticking and not self.done:
            self._ticking = True
            asyncio.get_running_loop().call_later(PROGRESS_INTERVAL, self._tick)
        return self._hub.stream()

    async def wait(self) -> Summary:
        """The summary once the job ended; raises what ended it (the errors hyrel-send shows)."""
        return await asyncio.shield(self._done)

    # --- control ----------------------------------------------------------------

    async def pause(self, at_layer_end: bool = False) -> None:
        await self.printer.pause(at_layer_end)

    async def resume(self) -> None:
        await self.printer.resume()

    async def cancel(self) -> None:
        await self.printer.cancel()

    def stop(self, error: HostError | None = None) -> bool:
        """Stop without waiting: the safe-stop sequence goes ahead of anything not sent,
        and :meth:`wait` raises ``error`` once it went (a cancel, without one).

        A second call abandons the safe stop and ends the job at once; it returns True
        then (:attr:`safe_stop_missing` says what was not confirmed)."""
        return self._session.stop_job(self, error)

    # --- from the session ---------------------------------------------------------

    def publish(self, event: JobEvent) -> None:
        """To the job's event subscribers."""
        self._hub.publish(event)

    def record_progress(self, keeper: print_history.ProgressKeeper) -> None:
        """Keep the progress in the run's record (``keeper``) as the job streams, from now."""
        self._keeper = keeper
        self._keep_progress()

    def drop_m0(self) -> None:
        """An M0's wait ends without a resume (the job stops, or ended)."""
        if self.m0 is not None:
            self.m0.cancel()
            self.m0 = None

    def _tick(self) -> None:
        # Polled, not pushed per line: a line's acknowledgement costs nothing here.
        if self.done:
            return
        if self.lines != self._reported:
            self._reported = self.lines
            self.publish(self._progress())
        asyncio.get_running_loop().call_later(PROGRESS_INTERVAL, self._tick)

    def _progress(self) -> Progress:
        last = self._run.last
        return Progress(self.lines, self.offset, self.size, last.position if last else "")

    def _keep_progress(self) -> None:
        """The progress in the run's record as the job streams, every PROGRESS_INTERVAL
        (written when it moved): a killed run is recovered from it (``--history-list``)."""
        keeper = self._keeper
        if keeper is None or self.done:
            return
        last = self._run.last
        acknowledged = last.source_line if last else 0
        keeper.update(
            self.lines,
            self.where(),
            acknowledged,
            self.recovery_line,
            self.recovery_known_to_run,
            self.all_sent,
            self._session.last_sent,
        )
        asyncio.get_running_loop().call_later(print_history.PROGRESS_INTERVAL, self._keep_progress)

    def finish(self, run: JobRun, error: HostError | None, summary: Summary | None) -> None:
        """The job ended: its last events, its report and record, then :meth:`wait`'s end."""
        if self._done.done():
            return
        self.publish(self._progress())
        report, path = self.report, self.report_path
        if report is not None:
            self.publish(Report(report))
            if path is not None:  # beside the stream, under the same run's name
                with contextlib.suppress(OSError):
                    path.write_text(report.text + "\n")
        history = self.history
        if history is not None and print_history.parse_run(history) is not None:
            # How it ended, beside a stream in a history folder (--history-list); not
            # beside a file of the caller's own naming (history=Path("/dev/null")...).
            print_history.write_record(history, self._record(error, summary))
        if error is not None:
            self.publish(Failed(error))
            self._done.set_exception(error)
            self._done.exception()  # retrieved: a job nobody waits for is no error
        else:
            assert summary is not None
            self.publish(Done(summary))
            self._done.set_result(summary)
        self._hub.close()

    def _record(self, error: HostError | None, summary: Summary | None) -> print_history.Record:
        if error is not None:
            outcome = print_history.FAILED
        elif summary is not None and summary.outcome is Outcome.CANCELLED:
            outcome = print_history.CANCELLED
        else:
            outcome = print_history.COMPLETED
        ended = datetime.now()
        seconds = summary.seconds if summary else (ended - self.started).total_seconds()
        return print_history.Record(
            job=self.name,
            outcome=outcome,
            lines=self.lines,
            seconds=round(seconds, 3),
            where=self.where(),
            port=self.printer.port,
            started=self.started.isoformat(timespec="seconds"),
            ended=ended.isoformat(timespec="seconds"),
            error=str(error) if error is not None else "",
            error_kind=print_history.error_kind(error) if error is not None else "",
            machine=self.plan.profile.name or "",
            pace=round(self.pace, 4) if self.pace is not None else None,
            heat_rates=self.heat_rates,
        )
