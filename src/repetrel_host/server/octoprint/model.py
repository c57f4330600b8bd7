"""A printer's state in OctoPrint's shapes: the state text and flags, the job, its
progress, the temperatures; what ``/api/job``, ``/api/printer`` and the push socket's
``current`` message say (OctoPrint 1.11: ``octoprint/printer/standard.py``'s
``get_current_data``, ``octoprint/util/comm.py``'s states).

Each function reads the printer's service as it stands now; none changes it."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from repetrel_host.server.printers.running import Running
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import JobRecord, JobState

# OctoPrint's states whose "printing" flag is set: a job is under way.
_PRINTING = ("Starting", "Printing", "Pausing", "Resuming", "Finishing", "Cancelling")
_OPERATIONAL = (*_PRINTING, "Operational", "Paused")
# The queue held after a job (its part may be on the bed): operational, and ready for a
# start (a person's start says the bed is clear) unless every start waits for a release.
HELD_TEXT = "Operational (bed not cleared)"


def state_text(service: PrinterService) -> str:
    """OctoPrint's state string: Operational, Printing, Pausing, Paused, Resuming,
    Finishing, Cancelling, Connecting, Offline, Offline after error."""
    state = service.state
    running = service.running
    if running is None and state in ("printing", "paused"):
        return "Starting"  # the session streams; the server has yet to take it on
    if running is not None and state in ("printing", "paused"):
        job = running.job
        if job.stopping:
            return "Cancelling"
        if service.phase == "pausing":
            return "Pausing"
        if service.phase == "resuming":
            return "Resuming"
        if state == "paused":
            return "Paused"
        return "Finishing" if job.all_sent else "Printing"
    if state == "ready":
        return HELD_TEXT if service.held else "Operational"
    if state == "connecting":
        return "Connecting"
    return "Offline after error" if service.last_error else "Offline"


def flags(service: PrinterService, text: str | None = None) -> dict[str, bool]:
    """OctoPrint's state flags, each true while its phase lasts; ``held``: the queue waits
    for the bed to be cleared (ours). A held printer is ``ready`` (a client's start works,
    and says the bed is clear), but where every start waits for a release."""
    text = text or state_text(service)
    startable = text == HELD_TEXT and not service.start_waits_for_release
    return {
        "operational": text in _OPERATIONAL or text == HELD_TEXT,
        "printing": text in _PRINTING,
        "cancelling": text == "Cancelling",
        "pausing": text == "Pausing",
        "resuming": text == "Resuming",
        "finishing": text == "Finishing",
        "closedOrError": text.startswith("Offline"),
        "error": text == "Offline after error",
        "paused": text == "Paused",
        "ready": text == "Operational" or startable,
        "sdReady": False,
        "held": service.held,
    }


def state(service: PrinterService) -> dict[str, Any]:
    """``{"text", "flags", "error"}``, as OctoPrint's ``current`` and ``/api/printer``."""
    text = state_text(service)
    return {"text": text, "flags": flags(service, text), "error": service.last_error}


def _shown(service: PrinterService) -> Running | None:
    """The job /api/job shows: the running one, else the last one (until another file is
    selected), as OctoPrint keeps a finished job's file and progress."""
    return service.running or service.finished


def file_entry(service: PrinterService, path: Path | None) -> dict[str, Any]:
    """The job's ``file``: its name and place below the uploads, size and date."""
    if path is None or not path.is_file():
        return {"name": None, "path": None, "display": None, "origin": None, "size": None}
    stat = path.stat()
    try:
        location = path.relative_to(service.data_dir / "files").as_posix()
    except ValueError:
        location = path.name
    return {
        "name": path.name,
        "path": location,
        "display": path.name,
        "origin": "local",
        "size": stat.st_size,
        "date": int(stat.st_mtime),
    }


def job(service: PrinterService) -> dict[str, Any]:
    """OctoPrint's ``job``: the file, its estimated print time (its plan from its moves at
    the printer's pace: the figure every face gives) with the slicer's beside it
    (``slicerEstimatedPrintTime``, which OctoPrint's clients ignore) and its filament (from
    the file's analysis, None without one), the last print's time."""
    shown = _shown(service)
    path = service.selected
    summary = None
    if shown is not None and (service.running is not None or path is None):
        path = service.data_dir / shown.record.file
        summary = shown.summary
        planned, slicer = shown.expected, shown.slicer_seconds
    else:
        if path is not None:
            summary = service.analyses.known(path)  # read as it was selected
        plan = summary.planned if summary is not None else None
        planned = plan.total(service.pace()) if plan is not None else None
        slicer = summary.slicer_seconds if summary is not None else None
    filament = None
    if summary is not None and summary.filament:
        filament = {
            tool: {"length": used.length, "volume": used.volume}
            for tool, used in summary.filament.items()
        }
    last = service.last_print_time(path) if path is not None else None
    return {
        "file": file_entry(service, path),
        "estimatedPrintTime": planned,
        "slicerEstimatedPrintTime": slicer,
        "averagePrintTime": last,
        "lastPrintTime": last,
        "filament": filament,
        "user": shown.record.user if shown is not None else None,
    }


# The server's names for where a time left came from, as OctoPrint says them.
_ORIGINS = {"plan": "analysis", "slicer": "analysis"}


def progress(service: PrinterService) -> dict[str, Any]:
    """OctoPrint's ``progress``: completion (%), file position, print time and time left,
    with its origin in OctoPrint's words: ``estimate`` (the plan at the run's or the
    printer's pace), ``analysis`` (the plan, or the slicer's figure)."""
    shown = _shown(service)
    none = {"completion": None, "filepos": None, "printTime": None, "printTimeLeft": None}
    if shown is None or (service.running is None and service.selected is not None):
        return {**none, "printTimeLeftOrigin": None}
    record, job = shown.record, shown.job
    started = record.started or time.time()
    ended = None if service.running is not None else (service.finished_at or time.time())
    elapsed = (ended or time.time()) - started
    completed = ended is not None and service.finished_state is JobState.COMPLETED
    fraction = 1.0 if completed else shown.fraction
    left: float | None = 0.0 if completed else None
    origin: str | None = None
    if ended is None:
        left, origin = shown.time_left()
        origin = _ORIGINS.get(origin, origin) if origin is not None else None
    return {
        "completion": 100.0 * fraction,
        "filepos": job.size if completed else job.offset,
        "printTime": int(elapsed),
        "printTimeLeft": int(left) if left is not None else None,
        "printTimeLeftOrigin": origin,
    }


def tool_key(sensor: str) -> str:
    """The session's sensor name (``T``, ``T1``, ``B``, ``C``) as OctoPrint's key."""
    if sensor == "B":
        return "bed"
    if sensor == "C":
        return "chamber"
    if sensor.startswith("T"):
        return f"tool{sensor[1:] or '0'}"
    return sensor


def tool_count(service: PrinterService) -> int:
    """How many tools the printer has: the loadout's heads, else the firmware's
    EXTRUDER_COUNT, else one."""
    loadout = service.plan_loadout()
    if loadout is not None:
        return max(len(loadout.heads), 1)
    printer = service.printer
    firmware = printer.firmware if printer is not None else None
    count = firmware.fields.get("EXTRUDER_COUNT", "1") if firmware is not None else "1"
    return int(count) if count.isdigit() and int(count) > 0 else 1


def temperatures(service: PrinterService) -> dict[str, dict[str, float | None]]:
    """``{"tool0": {"actual", "target", "offset"}, "bed": ...}`` as the session heard them;
    every tool and the bed are there (None until a report names them), as clients expect."""
    printer = service.printer
    readings = printer.temperatures if printer is not None else {}
    heaters: dict[str, dict[str, float | None]] = {
        key: {"actual": None, "target": None, "offset": 0}
        for key in [*(f"tool{i}" for i in range(tool_count(service))), "bed"]
    }
    for sensor, (actual, target) in readings.items():
        heaters[tool_key(sensor)] = {"actual": actual, "target": target, "offset": 0}
    return heaters


def resends(service: PrinterService) -> dict[str, int]:
    """OctoPrint's resend statistics: resends the controller asked for, lines sent."""
    printer = service.printer
    stats = printer.link_stats if printer is not None else None
    if stats is None:
        return {"count": 0, "transmitted": 0, "ratio": 0}
    count, sent = stats.resend_requests, stats.lines_sent
    return {"count": count, "transmitted": sent, "ratio": round(100 * count / sent) if sent else 0}


def current(service: PrinterService, job_now: dict[str, Any] | None = None) -> dict[str, Any]:
    """The push socket's ``current`` payload but for its buffers (temps, logs, messages),
    which the socket adds: what changed since its last message. ``job_now``: :func:`job`,
    when the caller has it."""
    job_now = job_now or job(service)
    running = service.running
    printing = job_now["file"]["path"] if running is not None else None
    return {
        "state": state(service),
        "job": job_now,
        "currentZ": running.z if running is not None else None,
        "progress": progress(service),
        "offsets": dict(service.offsets),
        "resends": resends(service),
        "busyFiles": [{"origin": "local", "path": printing}] if printing is not None else [],
        "markings": [],
        "serverTime": time.time(),
    }


def temperature_sample(
    when: float, readings: Mapping[str, Sequence[float | None]]
) -> dict[str, Any]:
    """One of OctoPrint's temperature data points: ``{"time", "tool0": {"actual",
    "target"}, "bed": ...}`` from the session's readings (sensor: (actual, target))."""
    sample: dict[str, Any] = {"time": int(when)}
    for sensor, (actual, target) in readings.items():
        sample[tool_key(sensor)] = {"actual": actual, "target": target}
    return sample


def print_event(
    service: PrinterService, record: JobRecord, running: Running | None = None
) -> dict[str, Any]:
    """The payload of OctoPrint's print events (PrintStarted, PrintDone...): the file's
    name, path below the uploads, origin, size, owner and user; with ``running`` (the
    job as it streams or ended), where it stands (``fileposition``, ``progress`` in %)."""
    path = service.data_dir / record.file
    try:
        location = path.relative_to(service.data_dir / "files").as_posix()
    except ValueError:
        location = path.name
    try:
        size: int | None = path.stat().st_size
    except OSError:
        size = None
    payload: dict[str, Any] = {
        "name": path.name,
        "path": location,
        "origin": "local",
        "size": size,
        "owner": record.user,
        "user": record.user,
    }
    if running is not None:
        job = running.job
        payload["fileposition"] = job.offset
        payload["progress"] = int(100 * job.offset / job.size) if job.size else 0
    if record.started is not None and record.ended is not None:
        payload["time"] = record.ended - record.started
    return payload
