"""A session's jobs, one at a time: started (planned and checked off the event loop, its
history opened, its run begun on the pump), paused, resumed (the machine first brought back
to where the job stood, where commands moved it during the pause), stopped, and ended (how
it is reported, and the safe stop owed after it: :mod:`.owed`).

:class:`JobControl` is also what each job asks of its session (a
:class:`~repetrel_host.session.print_job.JobSession`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import Callable, Iterable
from itertools import chain
from pathlib import Path
from typing import Protocol

from repetrel_host.errors import HostError, JobError, LinkError, UsageError
from repetrel_host.session import history as print_history
from repetrel_host.session.command_queue import CommandQueue
from repetrel_host.session.commands import Reply
from repetrel_host.session.events import Notice, Resumed, State
from repetrel_host.session.job import JobItem, JobLine
from repetrel_host.session.machine_state import KEEPS_THE_JOB_STATE, MachineState, back_to_job
from repetrel_host.session.owed import OwedStopSender
from repetrel_host.session.planning import JobPlan, history_file, recovery_plan
from repetrel_host.session.print_job import ActionHandler, JobPrinter, PrintJob
from repetrel_host.session.pump import CANCEL_DRAIN_TIMEOUT, JobRun
from repetrel_host.session.settings import SessionSettings
from repetrel_host.session.wire import Wire

# Sent before a job when its report is asked for: reset the metrics, and have M30 send
# the M773 report (Hyrel's diagnostic codes, M772: bit 0 of S).
REPORT_COMMAND = "M772 S1"
BACK_TO_JOB_TIMEOUT = 60.0  # s: each command that brings a paused job's machine back


class SteeredPrinter(JobPrinter, Protocol):
    """The printer whose jobs these are, as they are started and brought back."""

    @property
    def settings(self) -> SessionSettings: ...

    def plan(self, path: Path | str, *, header: bool, from_line: int | None) -> JobPlan: ...

    async def command(self, line: str, *, timeout: float | None = None) -> Reply: ...

    def heaters_on(self) -> list[str]: ...


class JobControlSession(Protocol):
    """What the session's jobs need of it besides its public face."""

    @property
    def reconnects(self) -> bool:
        """A lost or failed link is taken up again (the session is not closing)."""
        ...

    def set_state(self, state: State, reason: str) -> None:
        """The session's state is now ``state``."""

    async def until(self, ready: Callable[[], bool]) -> None:
        """Until ``ready()`` holds, looked at each time the state changes."""

    def changed(self) -> None:
        """The job's phase changed: the session's watchers are told."""

    def broadcast(self, event: Notice) -> None:
        """To the session's subscribers and the running job's."""


def _state_at(plan: JobPlan, line: int) -> MachineState:
    """The state the file's lines up to source ``line`` leave the machine in."""
    state = MachineState()
    for number, command, _, _ in plan.job.commands():
        if number > line:
            break
        state.apply(number, command)
    return state


class JobControl:
    """The session's running job and the last one started, and what is done to them (see
    the module)."""

    def __init__(
        self,
        printer: SteeredPrinter,
        session: JobControlSession,
        wire: Wire,
        commands: CommandQueue,
        owing: OwedStopSender,
    ) -> None:
        self._printer = printer
        self._session = session
        self._wire = wire
        self._commands = commands
        self._owing = owing
        self.job: PrintJob | None = None  # streaming now
        self.last_job: PrintJob | None = None  # started last, streaming or ended
        # The words of the commands sent during the job's pause that may have moved the
        # machine or changed a mode (jog, home, extrude, T...): resume() comes back first.
        self._paused_words: set[str] = set()

    # --- commands beside a job

    def check_can_command(self) -> None:
        """A caller's command may go now, else a UsageError or a LinkError that says why."""
        printer = self._printer
        state = printer.state
        if state is State.PRINTING:
            raise UsageError(
                "a job is printing: commands wait until it ends or is paused (pause() first)"
            )
        if state is not State.READY and state is not State.PAUSED:
            raise LinkError(f"{printer.port} is not connected (the session is {state.value})")
        pump = self._wire.pump
        if state is State.PAUSED and pump is not None and pump.controller_holds:
            raise UsageError(
                "the controller holds the paused job's lines (Hyrel's link): a command "
                "would wait behind them; it can go after resume() or cancel()"
            )

    def check_can_break_wait(self) -> None:
        """M108 may go now: on Hyrel's link it is end-wait, which would end the pause's
        hold behind the session's back (and the later resume() a heat-up's wait)."""
        pump = self._wire.pump
        if pump is not None and pump.controller_holds:
            raise UsageError("the job is paused: resume() ends the pause, not M108")

    def before_command(self, word: str) -> None:
        """A caller's command (``word``) goes now: during a pause, one that may move the
        machine or change a mode has the job's state restored before it goes on."""
        if self._printer.state is State.PAUSED and word not in KEEPS_THE_JOB_STATE:
            self._paused_words.add(word)

    # --- starting

    async def start(
        self,
        job: Path | str | JobPlan,
        *,
        header: bool,
        force: bool,
        history: Path | str | bool,
        on_action: ActionHandler | None,
        on_warning: Callable[[str], None] | None,
        report: bool,
        from_line: int | None,
        command_line: Iterable[str],
    ) -> PrintJob:
        """:meth:`Printer.print <repetrel_host.session.printer.Printer.print>`'s work."""
        printer = self._printer
        if self.job is not None or printer.state is State.PRINTING or printer.state is State.PAUSED:
            raise UsageError("a job is already running on this printer")
        self.check_can_command()
        # Planning (a recovery reads up to its line) and the check before the first line
        # read the file: a thread's work, not the event loop's (every printer's stream).
        if isinstance(job, JobPlan):
            plan = (
                job if from_line is None else await asyncio.to_thread(recovery_plan, job, from_line)
            )
        else:
            plan = await asyncio.to_thread(
                functools.partial(printer.plan, job, header=header, from_line=from_line)
            )
        warn = on_warning or self._warn
        checker = None
        if plan.checked_as_it_streams:
            checker = plan.streaming_checker(warn, force)
        elif not isinstance(job, JobPlan):
            findings = await asyncio.to_thread(plan.check)
            for finding in findings:
                warn(finding.format(plan.job.name))
            plan.refuse(findings, force, "force=True")
        async with self._commands.lock:
            if self.job is not None:  # another print() got here first
                raise UsageError("a job is already running on this printer")
            self.check_can_command()
            pump = self._wire.pump
            assert pump is not None
            path = self._open_history(plan, history)
            items: Iterable[JobItem] = plan.items(checker, pump.dialect.pause_command)
            if report:
                items = chain([JobLine(0, 0, REPORT_COMMAND, 0, "report")], items)
            run = JobRun(items, plan.safe_stop, started_at=self._wire.loop.time())
            if plan.recovery is not None:  # progress by bytes goes on from the skipped part
                run.offset = plan.recovery.start_offset
            print_job = PrintJob(printer, self, plan, run, on_action, path)
            if path is not None and print_history.parse_run(path) is not None:
                # Its progress in the run's record, written before the first line goes.
                print_job.record_progress(
                    print_history.ProgressKeeper(
                        path,
                        plan.job.path,
                        command_line,
                        printer.port,
                        print_job.started,
                        pump.dialect.last_sent,
                    )
                )
            self.job = self.last_job = print_job
            self._paused_words.clear()  # an earlier job's pause is not this one's
            pump.begin(run)
            self._session.set_state(State.PRINTING, plan.job.name)
            self._wire.drive()
        if path is not None and print_history.parse_run(path) is not None:
            self._prune_history(path)  # a history folder's: never a folder of other files
        return print_job

    def _warn(self, text: str) -> None:
        self._session.broadcast(Notice(text))

    def _open_history(self, plan: JobPlan, history: Path | str | bool) -> Path | None:
        if history is False:
            return None
        if history is True:
            path = history_file(None, self._printer.settings.user, plan.job)
        else:
            path = Path(history)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # Unbuffered: what is written reaches the OS at once (Wire.write), so that a killed
            # host leaves every byte the port got in the stream.
            self._wire.log = path.open("wb", buffering=0)
        except OSError as exc:
            raise JobError(f"cannot write the print history {path}: {exc.strerror}") from None
        return path

    def _prune_history(self, started: Path) -> None:
        """The oldest runs beside ``started`` go, down to ``history_max_mb``: in a thread,
        as the first lines stream."""
        limit = self._printer.settings.user.host.history_max_mb
        if limit > 0:
            prune = functools.partial(print_history.prune, started.parent, limit, started)
            self._wire.loop.run_in_executor(None, prune)

    # --- pausing, resuming, stopping

    async def pause(self, at_layer_end: bool) -> None:
        """:meth:`Printer.pause <repetrel_host.session.printer.Printer.pause>`'s work."""
        job = self.job
        if job is None:
            raise UsageError("no job is printing")
        printer = self._printer
        if printer.state is State.PAUSED:
            return
        pump = self._wire.pump
        if pump is not None:
            pump.pause(at_layer_end)
            self._wire.drive()
        await self._session.until(lambda: printer.state is not State.PRINTING or job.done)
        if printer.state not in (State.PAUSED,):  # (a tuple: the await changed it)
            raise UsageError(f"{job.name} ended before the pause could hold it")

    async def resume(self) -> None:
        """:meth:`Printer.resume <repetrel_host.session.printer.Printer.resume>`'s work."""
        job = self.job
        printer = self._printer
        if job is None or printer.state is not State.PAUSED:
            raise UsageError("no job is paused")
        if self._paused_words:
            await self._back_to_job(job)
            if self.job is not job or printer.state is not State.PAUSED:
                raise UsageError(f"{job.name} ended before it could resume")
        self._session.set_state(State.PRINTING, "resumed")
        job.publish(Resumed())
        if job.m0 is not None:
            m0, job.m0 = job.m0, None
            m0.set_result(None)
        elif (pump := self._wire.pump) is not None:
            pump.resume()
            self._wire.drive()

    async def _back_to_job(self, job: PrintJob) -> None:
        """Commands moved the machine during the pause (or changed its modes): back to where
        the job stood, in its modes, before its next line (:func:`machine_state.back_to_job`). The
        state is read from the file's lines up to the last one sent, in a thread."""
        last = job.last
        line = last.source_line if last is not None else 0
        words = self._paused_words
        tool_changed = any(word.startswith("T") for word in words)
        motors_off = bool(words & {"M84", "M18"})
        state = await asyncio.to_thread(_state_at, job.plan, line)
        for entry in back_to_job(state, tool_changed, motors_off):
            await self._printer.command(entry.command, timeout=BACK_TO_JOB_TIMEOUT)
        self._paused_words.clear()

    async def cancel(self) -> None:
        """:meth:`Printer.cancel <repetrel_host.session.printer.Printer.cancel>`'s work."""
        job = self.job
        if job is None:
            return
        if not job.stopping:
            job.stop()
        with contextlib.suppress(HostError):
            await job.wait()

    async def stop_for_close(self) -> None:
        """The session closes: a running job stops with its safe stop first, while the link
        can still take it."""
        job = self.job
        if job is not None and self._wire.pump is not None:
            if not job.stopping:
                job.stop()  # a stop under way goes on: a second one would abandon it
            with contextlib.suppress(HostError, TimeoutError):
                await asyncio.wait_for(job.wait(), CANCEL_DRAIN_TIMEOUT + 5)

    # --- what a job asks of its session (JobSession)

    def stop_job(self, job: PrintJob, error: HostError | None) -> bool:
        """Stop ``job`` (see :meth:`PrintJob.stop`)."""
        if self._owing.owed.waits_for(job):
            self._owing.give_up("given up before the controller answered again")
            return True
        wire = self._wire
        if job is not self.job or wire.pump is None:
            return False
        job.drop_m0()
        if self._printer.state is State.PAUSED:
            self._session.set_state(State.PRINTING, "stopping")
        abandoned = wire.pump.stop(wire.loop.time(), error)
        self._session.changed()  # stopping
        wire.drive()
        return abandoned

    def waits_for_safe_stop(self, job: PrintJob) -> bool:
        """``job`` waits for its safe stop to go after a reconnect."""
        return self._owing.owed.waits_for(job)

    @property
    def last_sent(self) -> object | None:
        """The link's last line sent (None while unlinked)."""
        pump = self._wire.pump
        return pump.dialect.last_sent if pump else None

    # --- from the pump

    def ended(self, run: JobRun) -> None:
        """The running job's run ended: how it is reported, and what is owed after it."""
        job, self.job = self.job, None
        self._wire.close_log()
        pump = self._wire.pump
        connection_ends = pump is None or pump.dialect.failure is not None
        owed = self._owing.owed
        if run.error is not None:
            # What of the safe stop was not confirmed is owed: it goes first at the next
            # greeting (or, on a link that goes on, as the controller takes it).
            owed.commands = run.owed_safe_stop
        if job is not None:
            job.drop_m0()
            owes = bool(owed.commands) and connection_ends and not run.emergency
            if owes and self._session.reconnects:
                self._owing.wait_for(job, run)
            else:
                heaters_on = self._printer.heaters_on
                job.finish(run, *owed.run_ended(run, connection_ends, heaters_on))
        healthy = pump is not None and pump.dialect.failure is None
        state = self._printer.state
        if healthy and (state is State.PRINTING or state is State.PAUSED):
            self._session.set_state(State.READY, "the job ended")
