"""The heaters a ``hyrel-send`` or console run turned on at a port, kept on disk as they
change, so that a run killed with them on (``kill -9``, a crash, a power cut of the host)
leaves its safe stop owed to the next run on that port, as the server's store keeps it
across its restarts.

``<data>/repetrel-host/heaters/<port>.json`` holds the process that keeps it and the heaters
that may be on (written before the line that turns one on goes). A run that ends and closes
its port with its safe stop confirmed (or nothing on) removes it; one that leaves a safe
stop owed keeps it. The next run on that port, finding it left by a process that is gone,
sends the safe stop first, for those heaters, and says why.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
from pathlib import Path

from repetrel_host.gcode.heaters import Heater
from repetrel_host.session.history import process_alive, process_identity, this_host
from repetrel_host.session.planning import default_history_dir
from repetrel_host.session.printer import Printer

log = logging.getLogger(__name__)

# Ports opened afresh each time (the built-in fake, the simulator): nothing carries over.
FRESH_PORTS = ("fake", "sim")


class HeatLedger:
    """What a run at ``port`` heated, kept in ``folder`` (default: beside the history)."""

    def __init__(self, port: str, folder: Path | None = None) -> None:
        self.port = port
        folder = folder or default_history_dir().parent / "heaters"
        self.path = folder / (re.sub(r"[^A-Za-z0-9._-]", "_", port.strip("/")) + ".json")
        self._warned = False

    @property
    def kept(self) -> bool:
        return self.port not in FRESH_PORTS

    def owed(self) -> tuple[list[Heater], str] | None:
        """The heaters a run that is gone left on at this port, and the sentence that says
        so; None when nothing is owed (or the run that keeps it is still there)."""
        if not self.kept:
            return None
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            heaters = [Heater(kind, index, float(t), c) for kind, index, t, c in data["heaters"]]
            alive = process_alive(data["host"], data["pid"], data["process"])
        except (OSError, ValueError, KeyError, TypeError):
            return None  # none kept, or not readable: nothing to go on
        if not heaters or alive is not False:
            return None
        on = ", ".join(heater.describe() for heater in heaters)
        return heaters, (
            f"the last run on {self.port} (process {data['pid']}) ended without its safe stop "
            f"(it was killed?) with heaters that may be on: {on}; sending its safe stop first"
        )

    def keep(self, printer: Printer) -> None:
        """Keep the session's heaters from now on, as they change (this process's)."""
        if not self.kept:
            return
        heaters = printer.heater_log

        def write() -> None:
            self._write([[h.kind, h.index, h.target, h.command] for h in heaters.on()])

        heaters.on_change = write
        write()

    def closed(self, printer: Printer) -> None:
        """The run closed its port: nothing is kept unless a safe stop is still owed."""
        if self.kept and not printer.owed_safe_stop:
            with contextlib.suppress(OSError):
                self.path.unlink()

    def _write(self, heaters: list[list[object]]) -> None:
        pid = os.getpid()
        data = {
            "port": self.port,
            "host": this_host(),
            "pid": pid,
            "process": process_identity(pid),
            "heaters": heaters,
        }
        partial = self.path.with_name(self.path.name + ".part")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            partial.write_text(json.dumps(data), encoding="utf-8")
            os.replace(partial, self.path)
        except OSError as exc:
            if not self._warned:  # once: the run goes on without it
                self._warned = True
                log.warning("cannot keep the heaters that are on in %s: %s", self.path, exc)
