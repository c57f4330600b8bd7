"""Moonraker's print history and job queue over the server's store: a printer's jobs as
Moonraker's history (its ended and running jobs, their totals), its queue as Moonraker's
job queue (held is ``paused``, released ``ready``), and their notifications."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

from repetrel_host.server import jobs, uploads
from repetrel_host.server.events import JobChanged, PrinterState, ServerEvent
from repetrel_host.server.moonraker.face import MoonrakerFace
from repetrel_host.server.moonraker.files import file_metadata
from repetrel_host.server.moonraker.rpc import Call, RpcError, method
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import ENDED, JobRecord, JobState

_STATUS = {
    JobState.PRINTING: "in_progress",
    JobState.PAUSED: "in_progress",
    JobState.COMPLETED: "completed",
    JobState.CANCELLED: "cancelled",
    JobState.FAILED: "error",
    JobState.INTERRUPTED: "interrupted",
}


def job_uid(record: JobRecord) -> str:
    """A job's id as Moonraker writes it (six hex digits at least)."""
    return f"{record.id:06X}"


def _record_of(call: Call, uid: str) -> JobRecord:
    try:
        record = call.server.store.job(int(uid, 16))
    except ValueError:
        record = None
    if record is None or record.printer != call.service.name:
        raise RpcError(404, f"Invalid job uid: {uid}")
    return record


def _filament(record: JobRecord) -> float:
    used: dict[str, dict[str, float]] = json.loads(record.filament) if record.filament else {}
    return round(sum(tool["length"] for tool in used.values()), 2)


def history_job(server: PrintServer, record: JobRecord) -> dict[str, Any]:
    """A job as Moonraker's history shows it, with its file's metadata (Mainsail and Fluidd
    show its thumbnail and estimate in their history lists); reads the file's kept analysis,
    so not on the event loop."""
    end = record.ended
    duration = ((end or time.time()) - record.started) if record.started else 0.0
    path = server.data_dir / record.file
    return {
        "job_id": job_uid(record),
        "exists": path.is_file(),
        "end_time": end,
        "filament_used": _filament(record),
        "filename": record.location,
        "metadata": _job_metadata(server, path, record.location),
        "print_duration": round(duration, 3),
        "status": _STATUS.get(record.state, "in_progress"),
        "start_time": record.started,
        "total_duration": round(duration, 3),
        "user": record.user or "",
        "auxiliary_data": [],
    }


def _job_metadata(server: PrintServer, path: Path, location: str) -> dict[str, Any]:
    """The file's metadata as Moonraker's history keeps it: without what the job itself
    says (its start, its id, its name); empty once the file is gone."""
    try:
        found = file_metadata(path, location, server.analyses.cached(path), server.file_pace())
    except OSError:
        return {}
    for repeated in ("print_start_time", "job_id", "filename"):
        found.pop(repeated, None)
    return found


def _history(call: Call) -> list[JobRecord]:
    """The printer's started jobs, newest first."""
    return [r for r in call.server.store.jobs(call.service.name) if r.started is not None]


@method("/server/history/list")
async def history_list(call: Call) -> dict[str, Any]:
    found = await asyncio.to_thread(_history, call)
    since, before = call.number("since", 0.0), call.number("before", 0.0)
    found = [r for r in found if r.started and r.started >= since]
    if before:
        found = [r for r in found if r.started and r.started < before]
    if call.string("order", "desc") == "asc":
        found.reverse()
    start, limit = call.integer("start", 0), call.integer("limit", 50)
    shown = found[start : start + limit] if limit > 0 else found[start:]
    listed = await asyncio.to_thread(lambda: [history_job(call.server, r) for r in shown])
    return {"count": len(found), "jobs": listed}


@method("/server/history/job", "GET", name="server.history.get_job")
async def history_get_job(call: Call) -> dict[str, Any]:
    record = _record_of(call, call.string("uid"))
    if record.started is None:
        raise RpcError(404, f"Invalid job uid: {call.string('uid')}")
    return {"job": await asyncio.to_thread(history_job, call.server, record)}


@method("/server/history/totals")
async def history_totals(call: Call) -> dict[str, Any]:
    ended = [r for r in await asyncio.to_thread(_history, call) if r.state in ENDED]
    durations = [r.ended - r.started for r in ended if r.started and r.ended]
    return {
        "job_totals": {
            "total_jobs": len(ended),
            "total_time": round(sum(durations), 3),
            "total_print_time": round(sum(durations), 3),
            "total_filament_used": round(sum(_filament(r) for r in ended), 2),
            "longest_job": round(max(durations, default=0.0), 3),
            "longest_print": round(max(durations, default=0.0), 3),
        },
        "auxiliary_totals": [],
    }


# --- the job queue ------------------------------------------------------------------------


def queue_status(service: PrinterService) -> dict[str, Any]:
    """Moonraker's queue: the printer's queued jobs, and ``paused`` while it is held."""
    now = time.time()
    queued = [
        {
            "filename": record.location,
            "job_id": job_uid(record),
            "time_added": record.submitted,
            "time_in_queue": round(now - record.submitted, 3),
        }
        for record in service.store.queued(service.name)
    ]
    return {"queued_jobs": queued, "queue_state": "paused" if service.held else "ready"}


@method("/server/job_queue/status")
async def job_queue_status(call: Call) -> dict[str, Any]:
    return queue_status(call.service)


@method("/server/job_queue/job", "POST", name="server.job_queue.post_job")
async def post_job(call: Call) -> dict[str, Any]:
    names = call.required("filenames")
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise RpcError(400, "Invalid argument filenames: a list of file names is needed")
    server, service = call.server, call.service
    paths = [uploads.uploaded(server, name) for name in names]  # all there, or none queued
    if call.flag("reset"):
        for record in server.store.queued(service.name):
            await service.cancel(record.id)
    for path in paths:
        findings, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
        uploads.refuse_errors(path.name, findings)
        jobs.queue(server, service.name, path, commands, call.user)
    return queue_status(service)


@method("/server/job_queue/job", "DELETE", name="server.job_queue.delete_job")
async def delete_job(call: Call) -> dict[str, Any]:
    service = call.service
    if call.flag("all"):
        records = service.store.queued(service.name)
    else:
        ids = call.required("job_ids")
        if isinstance(ids, str):
            ids = [i.strip() for i in ids.split(",") if i.strip()]
        if not isinstance(ids, list):
            raise RpcError(400, "Invalid argument job_ids: a list of job ids is needed")
        records = [_record_of(call, str(uid)) for uid in ids]
    for record in records:
        if record.state is not JobState.QUEUED:
            raise RpcError(400, f"Job {job_uid(record)} is not queued")
    for record in records:
        await service.cancel(record.id)
    return queue_status(service)


@method("/server/job_queue/pause", "POST")
async def pause_queue(call: Call) -> dict[str, Any]:
    call.service.hold()
    return queue_status(call.service)


@method("/server/job_queue/start", "POST")
async def start_queue(call: Call) -> dict[str, Any]:
    call.service.release()
    return queue_status(call.service)


@method("/server/job_queue/jump", "POST")
async def jump(call: Call) -> dict[str, Any]:
    record = _record_of(call, call.string("job_id"))
    if record.state is not JobState.QUEUED:
        raise RpcError(400, f"Job {job_uid(record)} is not queued")
    jobs.to_front(call.server, record)
    return queue_status(call.service)


def tell_job_changes(face: MoonrakerFace) -> None:
    """``notify_history_changed`` as a job starts and ends, ``notify_job_queue_changed`` as
    the queue gains, loses or starts a job and as it is held or released."""
    held: dict[str, bool] = {}
    told: list[asyncio.Task[None]] = []  # the last, each after the one before

    def tell_history(printer: str, action: str, record: JobRecord) -> None:
        """``notify_history_changed``, its job made in a thread (its file's metadata is
        read from disk), in the order the jobs changed."""
        before = told[-1] if told else None

        async def tell() -> None:
            job = await asyncio.to_thread(history_job, face.server, record)
            if before is not None:
                await asyncio.gather(before, return_exceptions=True)
            face.notify(printer, "notify_history_changed", [{"action": action, "job": job}])

        told[:] = [asyncio.get_running_loop().create_task(tell())]

    def heard(event: ServerEvent) -> None:
        if isinstance(event, PrinterState) and event.printer is not None:
            if held.get(event.printer, event.held) != event.held:
                _queue_changed(face, event.printer, "state_changed")
            held[event.printer] = event.held
        if not isinstance(event, JobChanged):
            return
        record, printer = event.record, event.printer
        if record.state is JobState.QUEUED:
            _queue_changed(face, printer, "jobs_added")
        elif record.state is JobState.PRINTING and record.ended is None:
            _queue_changed(face, printer, "job_loaded")
            if not record.lines:  # its start (a resume says it again, with lines)
                tell_history(printer, "added", record)
        elif record.state in ENDED:
            if record.started is None:
                _queue_changed(face, printer, "jobs_removed")
            else:
                tell_history(printer, "finished", record)

    face.listeners.append(heard)


def _queue_changed(face: MoonrakerFace, printer: str, action: str) -> None:
    status = queue_status(face.server.services[printer])
    face.notify(
        printer,
        "notify_job_queue_changed",
        [
            {
                "action": action,
                "updated_queue": status["queued_jobs"],
                "queue_state": status["queue_state"],
            }
        ],
    )
