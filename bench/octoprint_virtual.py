"""OctoPrint's VirtualPrinter behind a pty, as a printer on a USB link.

Run it with the Python of a virtualenv that has OctoPrint (not this project's)::

    python3 -m venv /tmp/octo-venv && /tmp/octo-venv/bin/pip install octoprint==1.11.8
    /tmp/octo-venv/bin/python bench/octoprint_virtual.py --link /tmp/vp [--log executed.txt]
    hyrel-send JOB --port /tmp/vp

It builds ``octoprint.plugins.virtual_printer.virtual.VirtualPrinter`` with the plugin's
default settings (its simulated errors at lines 100, 105, 110 and 115, a 64-byte receive
buffer, 4 command slots, moves that take a tenth of their time) and passes bytes between
the pty and it, as OctoPrint's serial layer would: a line per ``write()``, the part it did
not take written again (its ``write()`` returns how much fit, and raises
``SerialTimeoutException`` while its buffer stays full, during a heat-up). While a line
waits, nothing more is read from the pty, so the host's writes block: the push-back of a
USB link. Each reply line goes to the pty as VirtualPrinter gives it.

``--log FILE`` lists the commands VirtualPrinter executed (each line it handed to its
command handling, after the line number and checksum checks; each after its time in
seconds), ``--wire FILE`` every line
each way with its time. It prints ``ready PATH`` once the printer is up, and stops on
SIGTERM or SIGINT. This file is not part of the package and is not type-checked by it:
OctoPrint is not among the project's dependencies.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import tempfile
import threading
import time
import tty
from pathlib import Path
from typing import IO, Any

from octoprint.plugin import plugin_manager
from octoprint.plugins.virtual_printer import VirtualPrinterPlugin, virtual
from serial import SerialTimeoutException


class DefaultSettings:
    """The plugin's defaults, through the part of OctoPrint's settings API it reads."""

    def __init__(self, folder: str) -> None:
        self._values = VirtualPrinterPlugin().get_settings_defaults()
        self._folder = folder

    def get(self, path: list[str], merged: bool = False, **_: Any) -> Any:
        value: Any = self._values
        for key in path:
            value = value[key]
        return value

    def get_int(self, path: list[str]) -> int:
        return int(self.get(path))

    def get_float(self, path: list[str]) -> float:
        return float(self.get(path))

    def get_boolean(self, path: list[str]) -> bool:
        return bool(self.get(path))

    def global_get_basefolder(self, name: str) -> str:
        folder = os.path.join(self._folder, name)
        os.makedirs(folder, exist_ok=True)
        return folder


class Tap:
    """Stands for VirtualPrinter's command pattern: notes each command it is asked to match."""

    def __init__(self, pattern: re.Pattern[str], log: IO[str], start: float) -> None:
        self._pattern = pattern
        self._log = log
        self._start = start

    def match(self, data: str) -> re.Match[str] | None:
        self._log.write(f"{time.monotonic() - self._start:.6f} {data.strip()}\n")
        return self._pattern.match(data)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--link", type=Path, required=True, help="symlink to the pty's device")
    parser.add_argument("--log", type=Path, help="write the executed commands here")
    parser.add_argument("--wire", type=Path, help="write every line each way, with its time")
    args = parser.parse_args()

    folder = tempfile.mkdtemp(prefix="octoprint-virtual-")
    plugin_manager(init=True, plugin_folders=[], plugin_entry_points=[], plugin_bases=[])
    executed = open(args.log, "w") if args.log else None  # noqa: SIM115
    wire = open(args.wire, "w") if args.wire else None  # noqa: SIM115
    wire_lock = threading.Lock()
    start = time.monotonic()
    if executed is not None:
        virtual.VirtualPrinter.command_regex = Tap(  # type: ignore[assignment]
            virtual.VirtualPrinter.command_regex, executed, start
        )

    def note(direction: str, data: bytes) -> None:
        if wire is not None:
            with wire_lock:
                wire.write(f"{time.monotonic() - start:.6f} {direction} {data!r}\n")

    master, slave = os.openpty()  # the bridge keeps the slave open: no EIO between hosts
    tty.setraw(slave)
    if args.link.is_symlink() or args.link.exists():
        args.link.unlink()
    args.link.symlink_to(os.ttyname(slave))

    printer = virtual.VirtualPrinter(DefaultSettings(folder), None, data_folder=folder)

    def host_to_printer() -> None:
        pending = b""
        while True:
            pending += os.read(master, 4096)
            *lines, pending = pending.split(b"\n")
            for line in lines:
                rest = line + b"\n"
                note(">", rest)
                while rest:  # its buffer stayed full (a heat-up): write it again
                    with contextlib.suppress(SerialTimeoutException):
                        rest = rest[printer.write(rest) :]

    def printer_to_host() -> None:
        while True:
            line = printer.readline()
            if line:
                note("<", line)
                os.write(master, line if line.endswith(b"\n") else line + b"\n")

    for target in (host_to_printer, printer_to_host):
        threading.Thread(target=target, daemon=True).start()

    def stop(*_: object) -> None:
        for log in (executed, wire):
            if log is not None:
                log.flush()
        args.link.unlink(missing_ok=True)
        os._exit(0)  # VirtualPrinter's own threads would keep the process alive

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print("ready", args.link, flush=True)
    while True:
        signal.pause()


if __name__ == "__main__":
    sys.exit(main())
