"""Each uploaded file's analysis (:class:`~repetrel_host.gcode.analysis.FileSummary`: OctoPrint's
``gcodeAnalysis``, layers, slicer, the print time from the moves beside the slicer's), kept in
the data folder (``analysis/``, a small JSON file per file, valid while the file's size and
time are those it was made from) so that a restart reads no file again.

A file is analysed as it is uploaded (its print time from the moves follows in the
background once a listing shows it: the planner's pass takes seconds a megabyte, and an
upload printed at once gets its job's own plan), or as its job starts when it never was
(in a worker process, :mod:`~repetrel_host.session.workers`); a listing that finds a file
without one (put there by hand, moved with its folder) shows it without and has it
analysed in the background, one file at a time, as OctoPrint does. Nothing here runs on
the event loop but :meth:`Analyses.known` (memory only)."""

from __future__ import annotations

import hashlib
import json
import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from repetrel_host.errors import HostError
from repetrel_host.gcode.analysis import Analysis, FileSummary, analyse
from repetrel_host.gcode.estimate import PlanSettings
from repetrel_host.session.workers import in_worker

log = logging.getLogger("repetrel_host.server")

FORMAT = 4  # of the files kept: another number (a changed analysis) makes them stale
Stamp = tuple[int, int]  # a file's size and modification time (ns)


def stamp(path: Path) -> Stamp:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


class Analyses:
    """The summaries of the files below ``root``, kept in ``folder``."""

    def __init__(
        self, folder: Path, root: Path, on_made: Callable[[Path], None] | None = None
    ) -> None:
        self.folder = folder
        self.root = root
        self.on_made = on_made  # told of each file analysed in the background (its thread)
        # How a file's print time is planned: as the server's printer plans its jobs (its
        # machine, header, firmware), so that a list and a job give the same figure.
        self.plan_as: Callable[[Path], PlanSettings] | None = None
        # What that plan depends on besides the file (the printer's machine, loadout and
        # firmware): a print time planned for another is planned again.
        self.plan_key: Callable[[], str] | None = None
        self._known: dict[Path, tuple[Stamp, FileSummary, str]] = {}  # and planned_for
        self._waiting: queue.SimpleQueue[Path] = queue.SimpleQueue()
        self._queued: set[Path] = set()
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None

    # --- reading ---------------------------------------------------------------------

    def known(self, path: Path) -> FileSummary | None:
        """The summary of ``path`` as it is now, if it is in memory (for the event loop)."""
        found = self._known.get(path)
        try:
            current = found is not None and found[0] == stamp(path)
        except OSError:
            return None
        return self._as_planned(found[1], found[2]) if found is not None and current else None

    def cached(self, path: Path) -> FileSummary | None:
        """The summary of ``path`` as it is now, from memory or the folder; None when there
        is none (any thread but the event loop's)."""
        try:
            now = stamp(path)
        except OSError:
            return None
        found = self._known.get(path)
        if found is not None and found[0] == now:
            return self._as_planned(found[1], found[2])
        try:
            kept = json.loads(self._entry(path).read_text())
            if kept["format"] != FORMAT or kept["file"] != self._name(path):
                return None
            if (kept["size"], kept["mtime_ns"]) != now:
                return None
            summary = FileSummary.from_dict(kept["analysis"])
            planned_for = str(kept.get("planned_for", ""))
        except (OSError, ValueError, KeyError, TypeError):
            return None  # none yet, or unreadable: made again
        self._known[path] = (now, summary, planned_for)
        return self._as_planned(summary, planned_for)

    def _as_planned(self, summary: FileSummary, planned_for: str) -> FileSummary:
        """``summary``, without its print time when that was planned for another printer
        setting than the one now (:attr:`plan_key`): it is planned again."""
        if self.plan_key is None or summary.planned_seconds is None:
            return summary
        if planned_for == self.plan_key():
            return summary
        return replace(summary, planned_seconds=None, planned_points=(), planned_heating=0.0)

    def summary(self, path: Path) -> FileSummary | None:
        """:meth:`cached`, or None and the file analysed in the background (and one whose
        moves are not planned yet given its print time there)."""
        found = self.cached(path)
        if found is None or unplanned(found):
            self._enqueue(path)
        return found

    # --- making ----------------------------------------------------------------------

    def analyse(self, path: Path, moves: bool = True, planned: bool = True) -> Analysis:
        """``path`` read once, now (any thread but the event loop's): with ``moves``, its
        summary is kept, with ``planned`` the print time from its moves in it (a job's
        start does without: the job plans its own). :class:`OSError` when it cannot be
        read."""
        before = stamp(path)
        planned_for = self.plan_key() if self.plan_key is not None else ""
        settings = self._settings(path) if moves and planned else None
        found = in_worker(analyse, path, moves=moves, planned=moves and planned, settings=settings)
        if found.summary is not None and stamp(path) == before:  # not changed meanwhile
            self.keep(path, found.summary, before, planned_for)
        return found

    def _settings(self, path: Path) -> PlanSettings | None:
        if self.plan_as is None:
            return None
        try:
            return self.plan_as(path)
        except HostError as exc:  # a loadout unreadable now: the defaults, said in the log
            log.warning("%s is planned with the defaults: %s", path.name, exc)
            return None

    def keep(
        self, path: Path, summary: FileSummary, made_from: Stamp, planned_for: str | None = None
    ) -> None:
        """``summary`` is that of ``path`` while its size and time are ``made_from``; its
        print time planned for ``planned_for`` (:attr:`plan_key`; by default the one now)."""
        if planned_for is None:
            planned_for = self.plan_key() if self.plan_key is not None else ""
        self._known[path] = (made_from, summary, planned_for)
        entry = {
            "format": FORMAT,
            "planned_for": planned_for,
            "file": self._name(path),
            "size": made_from[0],
            "mtime_ns": made_from[1],
            "analysis": summary.as_dict(),
        }
        target = self._entry(path)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            partial = target.with_suffix(".part")
            partial.write_text(json.dumps(entry))
            partial.replace(target)
        except OSError as exc:  # kept in memory all the same
            log.warning("the analysis of %s was not kept: %s", path.name, exc)

    def forget(self, path: Path) -> None:
        """``path`` is gone."""
        self._known.pop(path, None)
        self._entry(path).unlink(missing_ok=True)

    # --- the background --------------------------------------------------------------

    def _enqueue(self, path: Path) -> None:
        with self._lock:
            if path in self._queued:
                return
            self._queued.add(path)
            if self._worker is None or not self._worker.is_alive():
                # A daemon: a big file being read never holds the server's exit up.
                self._worker = threading.Thread(target=self._work, name="analysis", daemon=True)
                self._worker.start()
        self._waiting.put(path)

    def _work(self) -> None:
        while True:
            path = self._waiting.get()
            try:
                kept = self.cached(path)
                if kept is None or unplanned(kept):
                    self.analyse(path)
                    if self.on_made is not None:
                        self.on_made(path)
            except OSError:
                pass  # gone meanwhile
            except Exception:  # a bug: the file goes without, the server on
                log.exception("the analysis of %s failed", path.name)
            finally:
                with self._lock:
                    self._queued.discard(path)

    def _name(self, path: Path) -> str:
        try:
            return path.relative_to(self.root).as_posix()
        except ValueError:
            return str(path)

    def _entry(self, path: Path) -> Path:
        digest = hashlib.sha1(self._name(path).encode(), usedforsecurity=False).hexdigest()
        return self.folder / f"{digest[:24]}.json"


def unplanned(summary: FileSummary) -> bool:
    """A summary of a file with moves, its print time not worked out yet (an upload's: the
    planner's pass takes seconds a megabyte, so it is made in the background when a listing
    shows the file)."""
    return summary.planned_seconds is None and summary.travel_area is not None


def describe(summary: FileSummary | None, pace: float = 1.0) -> dict[str, Any] | None:
    """The native API's ``analysis`` of a file: OctoPrint's, with layers and slicer, and
    both print times always there."""
    return summary.as_json(pace) if summary is not None else None
