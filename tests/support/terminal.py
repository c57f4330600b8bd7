"""A program on a real pseudo-terminal (pexpect), read as a person sees it: escapes gone."""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

import pexpect

# CSI sequences (colours, cursor moves), OSC titles, and the odd lone escape.
_ESCAPES = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b\][^\x07]*\x07|\x1b[()][A-Z0-9]|\x1b[=>]")


class Screen:
    """``hyrel-send ARGS`` on a pty of ``rows`` x ``columns``, in ``home`` (its HOME too)."""

    def __init__(self, *args: str, home: Path, rows: int = 30, columns: int = 120) -> None:
        env = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
        env.update(HOME=str(home), TERM="xterm", COLUMNS=str(columns), LINES=str(rows))
        self.child = pexpect.spawn(
            sys.executable,
            ["-m", "repetrel_host.cli", *args],
            env=env,
            cwd=str(home),
            dimensions=(rows, columns),
            encoding="utf-8",
            codec_errors="replace",
        )
        self._text = ""  # what was read, escapes removed
        self._tail = ""  # a piece that may be the start of an escape cut in two
        self._seen = 0  # where the next expect() starts looking, in text()

    def text(self) -> str:
        return self._text

    def expect(self, pattern: str, timeout: float = 30) -> re.Match[str]:
        """Wait until ``pattern`` (a regular expression) appears after the last match."""
        deadline = time.monotonic() + timeout
        compiled = re.compile(pattern)
        while True:
            found = compiled.search(self.text(), self._seen)
            if found:
                self._seen = found.end()
                return found
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"{pattern!r} not seen; the screen ends:\n{self.text()[-2000:]}"
                )
            self._read(0.1)

    def send(self, keys: str) -> None:
        self.child.send(keys)

    def wait(self, timeout: float = 30) -> int:
        """The exit status, once the program ended (the rest of its output read)."""
        deadline = time.monotonic() + timeout
        while self.child.isalive() or self._read(0):
            if time.monotonic() > deadline:
                self.child.kill(9)
                raise AssertionError(f"still running; the screen ends:\n{self.text()[-2000:]}")
            self._read(0.1)
        self.child.close()
        status = self.child.exitstatus
        return status if status is not None else 128 + (self.child.signalstatus or 0)

    def _read(self, timeout: float) -> bool:
        try:
            data = self._tail + self.child.read_nonblocking(65536, timeout)
        except (pexpect.TIMEOUT, pexpect.EOF):
            return False
        cut = data.rfind("\x1b")
        if cut < 0 or len(data) - cut > 64:  # no escape still open at the end
            cut = len(data)
        data, self._tail = data[:cut], data[cut:]
        self._text += _ESCAPES.sub("", data).replace("\r", "")
        return True

    def close(self) -> None:
        if self.child.isalive():
            self.child.kill(9)
        self.child.close(force=True)
