"""The signals that end a run from outside, for hyrel-send and its console alike.

Ctrl-C (SIGINT), SIGTERM (systemd, ``kill``), SIGHUP (a closed terminal, a dropped ssh
session) and SIGQUIT (Ctrl-\\) each mean the same: stop the job with its safe stop; a second
one abandons it. A run stopped so exits with 128 + the first signal's number, as shells
report a signal (130, 143, 129, 131), once the safe stop is confirmed.
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)
received: list[int] = []  # the stop signals this process received, in order


def stopping_text(signum: int) -> str:
    """What a run says as a stop signal stops its job."""
    if signum == signal.SIGINT:
        return "stopping: sending the safe-stop sequence (Ctrl-C again to abandon it)"
    name = signal.Signals(signum).name
    return f"{name}: stopping: sending the safe-stop sequence (a second signal abandons it)"


def exit_code(signum: int) -> int:
    """128 + the signal's number, as shells report a process a signal ended."""
    return 128 + signum


class StopSignals:
    """Calls ``on_signal(signum)`` on the loop for each stop signal while installed (each
    is kept in :data:`received` too)."""

    def __init__(self, on_signal: Callable[[int], None]) -> None:
        self._on_signal = on_signal
        self._loop: asyncio.AbstractEventLoop | None = None

    def install(self) -> None:
        self._loop = asyncio.get_running_loop()
        for signum in STOP_SIGNALS:
            self._loop.add_signal_handler(signum, self._received, signum)

    def remove(self) -> None:
        """Back to the handling outside a run (asyncio would leave SIGTERM and SIGHUP to
        end the process on the spot)."""
        if self._loop is not None:
            for signum in STOP_SIGNALS:
                self._loop.remove_signal_handler(signum)
            self._loop = None
            interrupt_on_stop_signals()

    def _received(self, signum: int) -> None:
        received.append(signum)
        self._on_signal(signum)


def interrupt_on_stop_signals() -> None:
    """Outside a run's own handling (before streaming begins), SIGTERM, SIGHUP and SIGQUIT raise
    KeyboardInterrupt as Ctrl-C does, instead of ending the process on the spot; the
    signal is kept in :data:`received`, for the exit code."""

    def handler(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        raise KeyboardInterrupt

    for signum in STOP_SIGNALS[1:]:
        signal.signal(signum, handler)


def exit_code_of_stop() -> int:
    """The exit code of a run a stop signal stopped safely: 128 + the first one's number
    (130 when none came: a stop asked for otherwise, as Ctrl-C's)."""
    return exit_code(received[0] if received else signal.SIGINT)
