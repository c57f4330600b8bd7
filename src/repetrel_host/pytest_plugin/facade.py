"""What tests hold: the printer (synchronous or awaitable), its jobs, the controller."""

from __future__ import annotations

import contextlib
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import pytest

from repetrel_host.pytest_plugin.jobs import HyrelJob, PrintResult, as_job

if TYPE_CHECKING:
    import repetrel_host as rh
    from repetrel_host.fakes.fake_controller import BuiltInFake
    from repetrel_host.pytest_plugin.teardown import PluginSession
    from repetrel_host.session.events import PrinterEvent

T = TypeVar("T")


class HyrelPrinter:
    """A READY printer session for synchronous tests: each call returns when done.

    ``session`` is the :class:`repetrel_host.Printer` itself. It lives on the plugin's
    own event loop, in another thread: run its coroutines with :meth:`run`."""

    def __init__(self, session: PluginSession) -> None:
        self._session = session
        self._portal = session.portal
        self.session = session.printer

    @property
    def state(self) -> rh.State:
        return self.session.state

    @property
    def firmware(self) -> rh.Firmware | None:
        """What the controller said to M115, if it answered."""
        return self.session.firmware

    @property
    def temperatures(self) -> dict[str, tuple[float, float | None]]:
        """The last reading of each sensor: (current, target)."""
        return dict(self.session.temperatures)

    @property
    def port(self) -> str:
        return self.session.port

    def run(self, work: Callable[[rh.Printer], Awaitable[T]], timeout: float | None = None) -> T:
        """``await work(session)`` on the session's event loop, and return its result."""

        async def call() -> T:
            return await work(self.session)

        return self._portal.call(call(), timeout)

    def command(self, line: str, *, timeout: float | None = None) -> rh.Reply:
        """Send one command and return the controller's reply (``reply.lines``, ``reply.ok``)."""
        return self._portal.call(self._session.command(line, timeout))

    def print(
        self,
        job: HyrelJob | Path | str,
        *,
        force: bool = False,
        check: bool = True,
        timeout: float | None = None,
    ) -> PrintResult:
        """Stream ``job`` and return once the controller acknowledged all of it; raises
        what ended it if it failed (``check=False``: the result tells, in ``error``)."""
        return self.start(job, force=force).wait(check=check, timeout=timeout)

    def start(self, job: HyrelJob | Path | str, *, force: bool = False) -> RunningJob:
        """Start streaming ``job`` and return at once (to pause, cancel, watch it)."""
        job = as_job(job)
        running = self._portal.call(self._session.start(job, force))
        return RunningJob(self._session, job, running)

    def pause(self) -> None:
        """Pause the running job; returns once every line sent is confirmed."""
        self._portal.call(self.session.pause())

    def resume(self) -> None:
        self._portal.call(self.session.resume())

    def cancel(self) -> None:
        """Stop the running job with the safe-stop sequence; returns once it went."""
        self._portal.call(self.session.cancel())

    def wait_for(self, *states: rh.State, timeout: float | None = None) -> None:
        """Wait until the session is in one of ``states`` (READY after a reset, an unplug)."""
        self._portal.call(self.session.wait_for(*states, timeout=timeout))

    def wait_for_temperature(
        self, sensor: str, target: float, *, tolerance: float = 2.0, timeout: float = 60.0
    ) -> float:
        """Wait until ``sensor`` (``T``, ``B``...) reads within ``tolerance`` of ``target``;
        returns the reading, or fails the test after ``timeout`` seconds."""
        work = self._session.wait_for_temperature(sensor, target, tolerance, timeout)
        return self._portal.call(work)

    def events(self, timeout: float) -> Iterator[PrinterEvent]:
        """State changes (the current one first), temperatures and controller messages,
        for ``timeout`` seconds (or until the session closes)."""
        portal = self._portal
        stream = portal.call(self._session.subscribe())
        deadline = time.monotonic() + timeout
        try:
            while (left := deadline - time.monotonic()) > 0:
                try:
                    yield portal.call(anext(stream), left)  # type: ignore[arg-type]
                except (StopAsyncIteration, TimeoutError):
                    return
        finally:
            with contextlib.suppress(Exception):
                portal.call(stream.aclose(), 5)  # type: ignore[attr-defined]


class RunningJob:
    """A job streaming from :meth:`HyrelPrinter.start`."""

    def __init__(self, session: PluginSession, job: HyrelJob, running: rh.PrintJob) -> None:
        self._session = session
        self.job = job
        self.print_job = running  # the session's rh.PrintJob

    @property
    def lines(self) -> int:
        """Job lines the controller acknowledged so far."""
        return self.print_job.lines

    @property
    def done(self) -> bool:
        return self.print_job.done

    def wait(self, *, check: bool = True, timeout: float | None = None) -> PrintResult:
        """Wait for the end (see :meth:`HyrelPrinter.print`)."""
        work = self._session.finish(self.job, self.print_job, check)
        return self._session.portal.call(work, timeout)

    def pause(self) -> None:
        self._session.portal.call(self.print_job.pause())

    def resume(self) -> None:
        self._session.portal.call(self.print_job.resume())

    def cancel(self) -> PrintResult:
        """Stop this job with the safe-stop sequence first; returns how far it got."""
        return self._session.portal.call(self._session.cancel(self.job, self.print_job))


class AsyncHyrelPrinter:
    """:class:`HyrelPrinter` for async tests: the same calls, awaited, from any asyncio loop."""

    def __init__(self, session: PluginSession) -> None:
        self._session = session
        self._portal = session.portal
        self.session = session.printer

    state = HyrelPrinter.state
    firmware = HyrelPrinter.firmware
    temperatures = HyrelPrinter.temperatures
    port = HyrelPrinter.port

    async def run(self, work: Callable[[rh.Printer], Awaitable[T]]) -> T:
        async def call() -> T:
            return await work(self.session)

        return await self._portal.acall(call())

    async def command(self, line: str, *, timeout: float | None = None) -> rh.Reply:
        return await self._portal.acall(self._session.command(line, timeout))

    async def print(
        self, job: HyrelJob | Path | str, *, force: bool = False, check: bool = True
    ) -> PrintResult:
        return await (await self.start(job, force=force)).wait(check=check)

    async def start(self, job: HyrelJob | Path | str, *, force: bool = False) -> AsyncRunningJob:
        job = as_job(job)
        running = await self._portal.acall(self._session.start(job, force))
        return AsyncRunningJob(self._session, job, running)

    async def pause(self) -> None:
        await self._portal.acall(self.session.pause())

    async def resume(self) -> None:
        await self._portal.acall(self.session.resume())

    async def cancel(self) -> None:
        await self._portal.acall(self.session.cancel())

    async def wait_for(self, *states: rh.State, timeout: float | None = None) -> None:
        await self._portal.acall(self.session.wait_for(*states, timeout=timeout))

    async def wait_for_temperature(
        self, sensor: str, target: float, *, tolerance: float = 2.0, timeout: float = 60.0
    ) -> float:
        work = self._session.wait_for_temperature(sensor, target, tolerance, timeout)
        return await self._portal.acall(work)

    async def events(self) -> AsyncIterator[PrinterEvent]:
        """State changes (the current one first), temperatures and controller messages."""
        portal = self._portal
        stream = await portal.acall(self._session.subscribe())
        try:
            while True:
                try:
                    yield await portal.acall(anext(stream))  # type: ignore[arg-type]
                except StopAsyncIteration:
                    return
        finally:
            with contextlib.suppress(Exception):
                await portal.acall(stream.aclose())  # type: ignore[attr-defined]


class AsyncRunningJob(RunningJob):
    """A job streaming from :meth:`AsyncHyrelPrinter.start`: the same calls, awaited."""

    async def wait(  # type: ignore[override]
        self, *, check: bool = True
    ) -> PrintResult:
        return await self._session.portal.acall(
            self._session.finish(self.job, self.print_job, check)
        )

    async def pause(self) -> None:  # type: ignore[override]
        await self._session.portal.acall(self.print_job.pause())

    async def resume(self) -> None:  # type: ignore[override]
        await self._session.portal.acall(self.print_job.resume())

    async def cancel(self) -> PrintResult:  # type: ignore[override]
        return await self._session.portal.acall(self._session.cancel(self.job, self.print_job))


# --- the controller -----------------------------------------------------------------


class HyrelController:
    """What the tests talk to: a real printer's port, or the fake controller.

    The fake-only parts (executed commands, faults, heaters) skip the test on real
    hardware. After :meth:`reset` or :meth:`unplug` the session greets the controller
    again: ``hyrel_printer.wait_for(rh.State.READY)`` before the next command."""

    def __init__(self, port: str, fake: BuiltInFake | None = None) -> None:
        self.port = port
        self.fake = fake
        # Each line the session sent, as it first went on the wire: (command, the host's own)
        self._sent: deque[tuple[str, bool]] = deque()

    def note_sent(self, command: str, own: bool) -> None:
        """The session's line tap (:meth:`repetrel_host.Printer.tap_lines`): what tells
        the host's own lines from the test's in :attr:`executed`."""
        self._sent.append((command, own))

    @property
    def is_fake(self) -> bool:
        return self.fake is not None

    def _fake(self, what: str) -> BuiltInFake:
        if self.fake is None:
            pytest.skip(f"{what} needs the fake controller; this run drives {self.port}")
        return self.fake

    def _request(self, what: str, text: str) -> dict[str, Any]:
        answer = self._fake(what).request(text)
        if not answer.get("ok"):
            raise ValueError(f"the fake controller refused '{text}': {answer.get('error')}")
        return answer

    @property
    def log_path(self) -> Path:
        """The fake's log of executed commands (kept after the test)."""
        log = self._fake("the executed-command log").log_path
        assert log is not None  # the plugin gives its fakes a log
        return log

    @property
    def executed(self) -> list[str]:
        """The commands the fake executed for the test, in order: its commands and its
        jobs' lines (a job's header, its safe stop), without the host's own lines (the
        greeting, temperature polls, the syncs of Hyrel's link): :attr:`all_executed`
        has those too."""
        return callers_commands(self.all_executed, self._sent)

    @property
    def all_executed(self) -> list[str]:
        """Every command the fake executed, in order, the host's own lines included."""
        self._request("the executed-command log", "status")  # flushes the log first
        return self.log_path.read_text(encoding="ascii", errors="replace").splitlines()

    @property
    def temperatures(self) -> dict[str, tuple[float, float]]:
        """The fake's heaters: (current, target) of ``T`` and ``B``."""
        readings = self._request("simulated temperatures", "status")["temperatures"]
        return {name: (float(now), float(target)) for name, (now, target) in readings.items()}

    @property
    def fault_counts(self) -> dict[str, int]:
        """How many of each fault the fake injected (corrupted_lines, dropped_oks...)."""
        counts: dict[str, int] = self._request("fault counts", "status")["counts"]
        return counts

    def set_faults(self, faults: str) -> None:
        """Switch faults from now on: ``"corrupt=0.02 drop_ok=0.05 seed=3"`` (the fake's
        ``--faults``: corrupt, garble, drop_ok, duplicate_ok, spurious_resend,
        resend_without_ok, flush_on_error, drop_duplicates, counted_resend,
        drop_with_error, seed)."""
        self._request("fault injection", f"set {faults}")

    def set_heat_rate(self, degrees_per_second: float | None) -> None:
        """How fast the fake's heaters move (None: at once, the default)."""
        rate = "none" if degrees_per_second is None else str(degrees_per_second)
        self._request("simulated heaters", f"heat_rate {rate}")

    def reset(self) -> None:
        """Reboot the fake: it says ``start``, as a controller does after a reset."""
        self._request("a controller reset", "reset")

    def hang(self) -> None:
        """The fake stops answering for good."""
        self._request("a hung controller", "hang")

    def unplug(self, seconds: float = 1.0) -> None:
        """Pull the cable: the pty vanishes, and comes back at the same path after ``seconds``."""
        self._request("an unplug", f"link_drop {seconds}")


def callers_commands(executed: Iterable[str], sent: Iterable[tuple[str, bool]]) -> list[str]:
    """What a controller ran (``executed``, its log) without the host's own lines, told by
    what the session sent (``sent``: each line as it first went, and whether it was the
    host's own, as :meth:`repetrel_host.Printer.tap_lines` tells them): the n-th time the
    controller ran a command is the n-th time the session sent it. (A line lost to a fault
    or an abort shifts that count: read the whole log then.)"""
    owners: dict[str, deque[bool]] = {}
    for command, own in list(sent):
        owners.setdefault(command, deque()).append(own)
    ran = []
    for command in executed:
        owner = owners.get(command)
        if not (owner and owner.popleft()):
            ran.append(command)
    return ran
