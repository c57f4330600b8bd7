"""Connect to a printer, ask who it is, print a job, and report temperatures meanwhile.

python examples/session.py                      # the built-in fake controller
python examples/session.py /dev/ttyUSB0 part.gcode
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import repetrel_host as rh

HERE = Path(__file__).parent


async def main(port: str, job_path: Path) -> int:
    async with rh.connect(port, poll_interval=1.0) as printer:
        firmware = printer.firmware
        print(f"connected to {printer.port}: {firmware.name if firmware else 'a firmware'}")
        reply = await printer.command("M115")
        for line in reply.lines:
            print(f"  {line}")

        async def temperatures() -> None:
            async for event in printer.events():
                if isinstance(event, rh.Temperatures):
                    readings = ", ".join(f"{k} {v[0]:.1f}" for k, v in event.readings.items())
                    print(f"  temperatures: {readings}")

        reporter = asyncio.create_task(temperatures())
        job = await printer.print(job_path)
        async for event in job.events():
            if isinstance(event, rh.Progress):
                print(f"  {event.lines} lines acknowledged ({event.position})")
        try:
            summary = await job.wait()
        except rh.HostError as exc:
            print(f"the job failed: {exc}")
            return 1
        finally:
            reporter.cancel()
        print(
            f"{job.name}: {summary.outcome.value}, {summary.lines} lines in {summary.seconds:.1f} s"
        )
        print(f"temperatures now: {(await printer.command('M105')).ok_line}")
    return 0


if __name__ == "__main__":
    port = sys.argv[1] if len(sys.argv) > 1 else "fake"
    job = Path(sys.argv[2]) if len(sys.argv) > 2 else HERE / "square-tube.gcode"
    raise SystemExit(asyncio.run(main(port, job)))
