"""The session as tests use it, and how it leaves the machine safe after each test."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import repetrel_host as rh
    from repetrel_host.pytest_plugin.report import WireRecorder
    from repetrel_host.session.events import PrinterEvent

from repetrel_host.pytest_plugin.jobs import HyrelJob, PrintResult
from repetrel_host.pytest_plugin.portal import Portal


class PluginSession:
    """One printer session on the portal, and how to leave the machine safe."""

    def __init__(
        self, portal: Portal, printer: rh.Printer, recorder: WireRecorder, deadline: float
    ) -> None:
        self.portal = portal
        self.printer = printer
        self.recorder = recorder
        self.deadline = deadline  # for the safe stop after a test

    async def start(self, job: HyrelJob, force: bool) -> rh.PrintJob:
        history: Path | bool = job.history if job.history is not None else False
        return await self.printer.print(job.path, header=job.header, force=force, history=history)

    async def finish(self, job: HyrelJob, running: rh.PrintJob, check: bool) -> PrintResult:
        import repetrel_host as rh

        try:
            return PrintResult(job, running, await running.wait(), None)
        except rh.HostError as exc:
            if check:
                raise
            return PrintResult(job, running, None, exc)

    async def cancel(self, job: HyrelJob, running: rh.PrintJob) -> PrintResult:
        if not running.done and not running.stopping:
            running.stop()  # this job only, should another be running
        return await self.finish(job, running, check=False)

    async def command(self, line: str, timeout: float | None) -> rh.Reply:
        try:
            return await self.printer.command(line, timeout=timeout)
        except TimeoutError:
            raise TimeoutError(f"{line}: no reply within {timeout:g} s") from None

    async def wait_for_temperature(
        self, sensor: str, target: float, tolerance: float, timeout: float
    ) -> float:
        import repetrel_host as rh

        last: float | None = self.printer.temperatures.get(sensor, (None, None))[0]
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                async for event in self.printer.events():
                    if isinstance(event, rh.Temperatures) and sensor in event.readings:
                        last = event.readings[sensor][0]
                        if abs(last - target) <= tolerance:
                            return last
        raise AssertionError(
            f"{sensor} did not reach {target:g} (within {tolerance:g}) in {timeout:g} s; "
            f"last reading: {'none' if last is None else f'{last:g}'}"
        )

    async def subscribe(self) -> AsyncIterator[PrinterEvent]:
        """The session's events, subscribed to on its own loop (for another thread's use)."""
        return self.printer.events()

    async def leave_safe(self, failed: bool) -> str | None:
        """Cancel a running job (its safe stop first); after a failure, send the safe stop.
        Returns what went wrong, or None once the machine is safe."""
        import repetrel_host as rh

        printer = self.printer
        job = printer.job
        if job is None and not failed:
            return None
        firmware = printer.firmware
        emergency = firmware is not None and firmware.can("EMERGENCY_PARSER")
        connected = printer.state in (rh.State.READY, rh.State.PAUSED, rh.State.PRINTING)
        if emergency and connected and (job is not None or printer.pending):
            await printer.command("M108")  # a heat wait must not hold the safe stop back
        missing: list[str] = []
        if job is not None:
            if not job.stopping:
                job.stop()
            try:
                await asyncio.wait_for(job.wait(), self.deadline)
            except TimeoutError:
                job.stop()  # abandoned: what was not confirmed is missing
            except rh.HostError:
                pass
            missing = job.safe_stop_missing if job.stopping else []
        if failed and (job is None or not job.stopping):
            missing = await self._send_safe_stop()
        if not missing:
            return None
        problem = f"the safe stop was not confirmed within {self.deadline:g} s (missing: "
        problem += f"{', '.join(missing)})"
        if emergency and printer.state is not rh.State.CLOSED:
            with contextlib.suppress(rh.HostError):
                await printer.command("M112")
                problem += "; sent M112 (emergency stop)"
        return problem + ": check the machine"

    async def _send_safe_stop(self) -> list[str]:
        """Send the machine's safe-stop sequence; returns the commands not confirmed."""
        import repetrel_host as rh

        printer = self.printer
        commands = printer.safe_stop
        loop = asyncio.get_running_loop()
        end = loop.time() + self.deadline
        try:
            await printer.wait_for(rh.State.READY, rh.State.PAUSED, timeout=self.deadline)
            for done, command in enumerate(commands):
                try:
                    await printer.command(command, timeout=max(0.001, end - loop.time()))
                except (rh.HostError, TimeoutError):
                    return commands[done:]
        except TimeoutError:
            return commands
        return []

    async def close(self, safe_stop: bool) -> str | None:
        """Close the session; with ``safe_stop``, send the safe-stop sequence first."""
        problem = await self.leave_safe(failed=safe_stop)
        await self.printer.close()
        return problem
