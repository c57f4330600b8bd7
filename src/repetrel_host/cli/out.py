"""Where hyrel-send prints (stdout, stderr): one stream type for its run at a terminal,
its answers without a printer and its ``--server`` runs."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import Console


class Out:
    """A terminal stream through rich, imported on first use: a job's first line goes out
    before rich's modules (a good share of the start-up) have been read."""

    def __init__(self, stderr: bool = False) -> None:
        self._stderr = stderr
        self._console: Console | None = None

    @property
    def console(self) -> Console:
        if self._console is None:
            from rich.console import Console

            self._console = Console(stderr=self._stderr, highlight=False, soft_wrap=True)
        return self._console

    def print(self, text: str, markup: bool | None = None) -> None:
        # A terminal that went away (a closed window, a dropped ssh session: SIGHUP) takes
        # no more words; the run goes on to its safe stop, and its record says how it ended.
        with contextlib.suppress(OSError):
            self.console.print(text, markup=markup)

    def bell(self) -> None:
        self.console.bell()
