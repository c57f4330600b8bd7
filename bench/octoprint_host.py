"""Print a file with OctoPrint's own serial layer (``octoprint.util.comm.MachineCom``).

Run it with the Python of a virtualenv that has OctoPrint::

    /tmp/octo-venv/bin/python bench/octoprint_host.py JOB --port /tmp/vp

It sets OctoPrint up as its server would for a connection (settings in a scratch base
folder, their defaults; the plugin manager without plugins; the default printer
profile), connects to PORT at 115200 baud, waits until the printer is operational,
selects JOB as a local file and starts the print. It prints ``seconds S`` (from the start
of the print to OctoPrint's "print job done") and exits 0, or exits 1 with the reason if
the print failed or the connection closed first.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from typing import Any

from octoprint.events import eventManager
from octoprint.plugin import plugin_manager
from octoprint.printer.profile import PrinterProfileManager
from octoprint.settings import settings
from octoprint.util.comm import MachineCom, MachineComPrintCallback


class Callback(MachineComPrintCallback):  # type: ignore[misc]
    def __init__(self) -> None:
        self.operational = threading.Event()
        self.finished = threading.Event()
        self.failure: str | None = None

    def on_comm_state_change(self, state: int) -> None:
        if state == MachineCom.STATE_OPERATIONAL:
            self.operational.set()
        elif state in (MachineCom.STATE_ERROR, MachineCom.STATE_CLOSED_WITH_ERROR):
            self.failure = f"connection state {state}"
            self.finished.set()

    def on_comm_print_job_done(self, *_: Any, **__: Any) -> None:
        self.finished.set()

    def on_comm_print_job_failed(self, reason: str | None = None) -> None:
        self.failure = f"print failed: {reason}"
        self.finished.set()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("job")
    parser.add_argument("--port", required=True)
    parser.add_argument("--timeout", type=float, default=600.0)
    args = parser.parse_args()

    settings(init=True, basedir=tempfile.mkdtemp(prefix="octoprint-host-"))
    plugin_manager(init=True, plugin_folders=[], plugin_entry_points=[], plugin_bases=[])
    eventManager()
    callback = Callback()
    comm = MachineCom(args.port, 115200, callback, PrinterProfileManager())
    comm.start()
    try:
        if not callback.operational.wait(60):
            print("not operational after 60 s", file=sys.stderr)
            return 1
        comm.selectFile(args.job, False)
        start = time.monotonic()
        comm.startPrint()
        if not callback.finished.wait(args.timeout):
            print(f"not done after {args.timeout} s", file=sys.stderr)
            return 1
        seconds = time.monotonic() - start
        if callback.failure is not None:
            print(callback.failure, file=sys.stderr)
            return 1
        print(f"seconds {seconds:.3f}", flush=True)
        return 0
    finally:
        comm.close(wait=False)


if __name__ == "__main__":
    sys.exit(main())
