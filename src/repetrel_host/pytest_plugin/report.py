"""The failure report: the last lines on the wire and the controller's messages."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Generator
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    import repetrel_host as rh


WIRE_LINES = 2000  # kept for the report of a failed test
REPORT_LINES = 100  # shown in it
WIRE_LINE_MAX = 4096
REPORTS_KEY = pytest.StashKey[dict[str, pytest.TestReport]]()
RECORDER_KEY = pytest.StashKey["WireRecorder"]()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    item.stash.setdefault(REPORTS_KEY, {})[report.when] = report
    recorder = item.stash.get(RECORDER_KEY, None)
    if report.failed and recorder is not None:
        for title, text in recorder.sections(item):
            report.sections.append((title, text))
    return report


def failed(item: pytest.Item) -> bool:
    """The test failed (an expected failure too: the machine may be in any state)."""
    reports = item.stash.get(REPORTS_KEY, {}).values()
    return any(r.failed or hasattr(r, "wasxfail") for r in reports)


class WireRecorder:
    """The last lines each way on the wire, and the session's messages and state changes,
    for the report of a failed test."""

    def __init__(self) -> None:
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._partial = {True: bytearray(), False: bytearray()}
        self.wire: deque[tuple[int, str]] = deque(maxlen=WIRE_LINES)
        self.messages: deque[tuple[int, str]] = deque(maxlen=WIRE_LINES)
        self._count = 0  # lines and messages so far, to tell what came during a test

    def tap(self, sent: bool, data: bytes) -> None:
        partial = self._partial[sent]
        partial += data
        *lines, rest = partial.split(b"\n")
        if len(rest) > WIRE_LINE_MAX:  # noise without line ends: shown, not hoarded
            lines.append(rest[:])
            rest.clear()
        partial[:] = rest
        for raw in lines:
            text = raw.rstrip(b"\r").decode("ascii", errors="backslashreplace")
            self._add(self.wire, f"{'>' if sent else '<'} {text}")

    def note(self, text: str) -> None:
        self._add(self.messages, text)

    def _add(self, kept: deque[tuple[int, str]], text: str) -> None:
        with self._lock:
            self._count += 1
            kept.append((self._count, f"{time.monotonic() - self._started:9.3f} {text}"))

    def mark(self) -> int:
        with self._lock:
            return self._count

    def since(self, kept: deque[tuple[int, str]], mark: int) -> list[str]:
        with self._lock:
            return [text for count, text in kept if count > mark]

    def sections(self, item: pytest.Item) -> list[tuple[str, str]]:
        mark = item.stash.get(MARK_KEY, 0)
        wire = self.since(self.wire, mark)
        shown = wire[-REPORT_LINES:]
        skipped = (
            f"({len(wire) - len(shown)} earlier lines not shown)\n" if wire[:-REPORT_LINES] else ""
        )
        messages = self.since(self.messages, mark)
        return [
            (
                "hyrel: last lines on the wire (> sent, < received)",
                skipped + "\n".join(shown) or "(none)",
            ),
            ("hyrel: controller messages and session states", "\n".join(messages) or "(none)"),
        ]


MARK_KEY = pytest.StashKey[int]()


async def record_events(printer: rh.Printer, recorder: WireRecorder) -> None:
    import repetrel_host as rh

    async for event in printer.events():
        if isinstance(event, rh.StateChanged):
            why = f" ({event.reason})" if event.reason else ""
            recorder.note(f"state: {event.state.value}{why}")
        elif isinstance(event, rh.NoAnswerYet):
            recorder.note(f"session: {event.text}")
        elif isinstance(event, rh.Message | rh.Notice):
            recorder.note(f"{type(event).__name__.lower()}: {event.text}")
