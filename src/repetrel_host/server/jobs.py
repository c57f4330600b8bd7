"""A job as the API makes it: an uploaded file queued on a printer, and where a stopped
job would be recovered (its line, its layer, and the command that recovers it)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from fastapi import HTTPException

import repetrel_host as rh
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import JobRecord, JobState
from repetrel_host.server.uploads import relative
from repetrel_host.session.planning import layer_line
from repetrel_host.session.recovery import recovery_command

log = logging.getLogger("repetrel_host.server")


def queue(
    server: PrintServer,
    printer: str,
    path: Path,
    commands: int,
    user: str | None = None,
    from_line: int | None = None,
) -> JobRecord:
    record = server.store.submit(
        printer, path.name, relative(server, path), commands, user, from_line
    )
    log.info("job %d (%s) queued on printer %s", record.id, path.name, printer)
    # Its estimate needs its file's print time: planned once a listing of the queue shows
    # it (planning costs a stream about a fifth of its speed on two cores).
    service = server.services[printer]
    service.job_changed(record.id)
    service.wake()
    return record


def start(
    server: PrintServer,
    service: PrinterService,
    path: Path,
    commands: int,
    user: str | None,
    via: str,
    first: bool = False,
) -> JobRecord:
    """A person's start of ``path`` from any face (``via`` names the face's start): a held
    queue is released (:meth:`PrinterService.start_asked`, which refuses when every start
    waits for a release), the job queued, and put first when the queue was held (the jobs
    that waited behind the hold wait on: the start asked for goes first) or ``first``.
    Nothing awaits in between: the queue's loop takes this job, not one that waited."""
    released = service.start_asked(path.name, user, via)
    record = queue(server, service.name, path, commands, user)
    if released or first:
        to_front(server, record)
    return record


def to_front(server: PrintServer, record: JobRecord) -> None:
    """The queued job ``record`` goes first in its printer's queue."""
    first = server.store.next_queued(record.printer)
    if first is not None and first.id != record.id:
        server.store.move(record.id, first.id)


def recovery_line(path: Path, from_layer: int | None, from_line: int | None) -> int | None:
    """The source line a job recovered at ``from_layer`` (or ``from_line``) starts from
    (in a thread: it reads the file); 400 when the file has no such layer."""
    if from_layer is not None and from_line is not None:
        raise HTTPException(400, "from_layer and from_line both say where to resume: give one")
    if from_layer is None:
        return from_line
    try:
        return layer_line(path, from_layer)
    except rh.UsageError as exc:
        raise HTTPException(400, str(exc)) from None


def recovery_json(server: PrintServer, record: JobRecord) -> dict[str, Any]:
    """Where ``record``'s job would be recovered (in a thread): its first line not acknowledged,
    the layer holding it, and the commands that recover it (409 when it completed, or when
    none of it ran: print it again)."""
    if record.state not in (JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED):
        raise HTTPException(409, f"job {record.id} is {record.state.value}: nothing to resume")
    if record.last_line < 1:
        raise HTTPException(409, f"job {record.id}: none of it ran, print it again")
    path = server.data_dir / record.file
    if not path.is_file():
        raise HTTPException(409, f"job {record.id}'s file {record.name} is gone")
    line = record.last_line + 1
    layer = scan_marks(path, until_line=line).at(line).layer
    file = path.relative_to(server.files).as_posix()
    port = server.services[record.printer].port if record.printer in server.services else "PORT"
    arguments = (file, "--port", port)
    return {
        "job": record.id,
        "file": file,
        "from_line": line,
        "from_layer": layer.number if layer is not None else None,
        "command": recovery_command(arguments, line),
        "layer_command": recovery_command(arguments, layer.number, "--from-layer")
        if layer is not None
        else None,
    }
