"""What a printer of the server checks before a job starts: the plan of a file for its
machine, loadout and firmware, and the job lint on it (in a worker process). A file that
passed is remembered as it is on disk, so that its job starts without a second pass."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import repetrel_host as rh
from repetrel_host.config import Loadout, UserConfig, find_loadout, load_library, load_loadout
from repetrel_host.gcode.lint import Finding, Severity
from repetrel_host.protocol.reports import Firmware
from repetrel_host.session.planning import (
    JobPlan,
    JobRequest,
    plan_job,
)
from repetrel_host.session.workers import in_worker

LOADOUT_RETRY = 10.0  # s: a loadout that could not be read is read again after this long


def _fingerprint(plan: JobPlan) -> tuple[object, ...]:
    """The job's file as it is on disk (an edit changes its time, a new file its inode),
    and what its check depends on."""
    try:
        stat = plan.job.path.stat()
    except OSError:
        return ()  # gone: never the fingerprint of a check
    return stat.st_size, stat.st_mtime_ns, stat.st_ino, plan.lint_settings


class JobChecks:
    """The checks of one printer's files, remembered while a file stays as it was."""

    def __init__(
        self, request: JobRequest, user: UserConfig, firmware: Callable[[], Firmware | None]
    ) -> None:
        self.request = request  # as the session's
        self.user = user
        self.firmware = firmware  # the printer's, once it answered
        # Files checked for this printer (as they were on disk, and the check's settings):
        # a job is checked once, at its upload, not again (on the event loop) as it starts.
        self._checked: dict[Path, tuple[object, ...]] = {}
        self._loadout: tuple[Path, Loadout] | None = None
        self._failed: tuple[Path, float] | None = None  # a loadout unread, until when

    def plan(self, path: Path) -> JobPlan:
        """What this printer would stream for ``path``: its machine, loadout and firmware."""
        return plan_job(path, self.request, self.user, self.firmware())

    def check(self, path: Path) -> tuple[JobPlan, list[Finding], int]:
        """The job lint for this printer, and the lines the job sends (any thread but the
        event loop's: a worker process reads the file). A file with no errors is remembered
        as checked, so that its job starts without a second pass."""
        plan = self.plan(path)
        before = _fingerprint(plan)
        findings, lines = in_worker(plan.check_and_count)
        if not any(f.severity is Severity.ERROR for f in findings):
            self._checked[path] = before
        return plan, findings, lines

    def passed(self, path: Path, plan: JobPlan) -> bool:
        """``path``, planned as ``plan``, passed the check as it is now."""
        return self._checked.get(path) == _fingerprint(plan)

    def was_checked(self, path: Path) -> bool:
        """``path``, as it is now, passed this printer's check already (any thread)."""
        return self._checked.get(path) == _fingerprint(self.plan(path))

    def plan_loadout(self) -> Loadout | None:
        """The printer's loadout (its heads), as a job's plan reads it; None without one or
        when it cannot be read (a job then says why)."""
        path = self.request.loadout or self.user.printer.loadout
        if path is None:
            return None
        if self._loadout is None or self._loadout[0] != path:
            failed = self._failed
            if failed is not None and failed[0] == path and time.monotonic() < failed[1]:
                return None  # not read again at each look of a client (four a second)
            try:
                loadout = load_loadout(find_loadout(path), load_library(self.user))
            except rh.HostError:
                self._failed = (path, time.monotonic() + LOADOUT_RETRY)
                return None
            self._loadout = (path, loadout)
        return self._loadout[1]

    def renamed(self, old: Path, new: Path) -> None:
        """``old`` is now ``new`` (the same file): its check goes with it."""
        checked = self._checked.pop(old, None)
        if checked is not None:
            self._checked[new] = checked

    def forget(self, path: Path) -> None:
        """``path`` is gone: its check with it."""
        self._checked.pop(path, None)
