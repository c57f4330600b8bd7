"""The native API, under ``/v1``: printers, their queues and jobs, files, snapshots,
commands, and a stream of server-sent events."""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import AsyncIterator, Mapping
from dataclasses import astuple
from typing import Annotated, Any

from fastapi import (
    APIRouter,
    File,
    Form,
    HTTPException,
    Query,
    Request,
    UploadFile,
)
from fastapi import Path as PathParameter
from fastapi.responses import (
    FileResponse,
    JSONResponse,
    Response,
    StreamingResponse,
)
from pydantic import BaseModel, Field

from repetrel_host.server import folders as shared_folders
from repetrel_host.server import jobs, store, timelapse, uploads
from repetrel_host.server.access import (
    LINK_LONGEST,
    LINK_SECONDS,
    OWNER,
    LinkRefused,
    make_page_link,
    redeem_page_link,
)
from repetrel_host.server.auth import user_of
from repetrel_host.server.events import AppKeyEvent
from repetrel_host.server.octoprint import appkeys
from repetrel_host.server.print_server import PrintServer, answered, server_of
from repetrel_host.server.printers.forecast import iso
from repetrel_host.server.printers.heaters import heaters
from repetrel_host.server.printers.running import layer_times, progress_event
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import ACTIVE

MAX_ID = 2**63 - 1  # SQLite's largest integer: a job id beyond it is no job
JobId = Annotated[int, PathParameter(ge=1, le=MAX_ID)]
HISTORY_SHOWN = 1800.0  # s: the temperature reports given without ``since``
KEEPALIVE = 15.0  # seconds of quiet before the event stream says it is alive
_SNAPSHOT = re.compile(r"[A-Za-z0-9_-]+\.(jpg|png|gif|webp|mp4)")


def _printer_json(service: PrinterService) -> dict[str, Any]:
    printer = service.printer
    running = service.running
    job = _running_json(service) if running is not None else None
    free_at = service.forecast(job["time_left"] if job is not None else None).free_at
    return {
        "name": service.name,
        "port": service.port,
        "state": service.state,
        "since": service.state_since,  # in that state since (seconds since the epoch)
        "reason": service.state_reason or service.last_error or None,  # why, if said
        "held": service.held,
        "hold_reason": service.hold_reason,  # why the queue waits for a release
        "error": service.last_error or None,
        "firmware": printer.firmware.name if printer and printer.firmware else None,
        "protocol": printer.settings.protocol if printer else None,  # the link's: reprap, hyrel
        "temperatures": _readings(printer.temperatures if printer else {}),
        "heaters": heaters(service),
        "job": job,
        # When it should be free: the end of its last queued job, else of its running one.
        "free_at": iso(free_at),
        "camera": service.camera is not None,
        "snapshot": _latest_snapshot(service),
    }


def _readings(readings: Mapping[str, tuple[float, float | None]]) -> dict[str, Any]:
    return {
        sensor: {"actual": actual, "target": target}
        for sensor, (actual, target) in readings.items()
    }


def _latest_snapshot(service: PrinterService) -> str | None:
    images = service.camera.images()[:1] if service.camera is not None else []
    return service.url(images[0]) if images else None


def _running_json(service: PrinterService) -> dict[str, Any]:
    running = service.running
    assert running is not None
    progress = progress_event(service.name, running.record, running.job, running, False)
    planned, limits_from = running.planned
    split = astuple(planned) if planned is not None else (None, None, None)
    return {
        **running.record.as_json(),
        "state": "paused" if service.state == "paused" else "printing",
        # Its safe stop under way (a cancel held up by a heat wait): OctoPrint's Cancelling.
        "stopping": running.job.stopping,
        # Lines, bytes, layer, completion, the time left and how it was found, the end.
        **{
            k: v
            for k, v in progress.as_json().items()
            if k not in ("type", "printer", "job", "free_at")  # the printer's, not the job's
        },
        # The whole job's time, what it ran and has left (None until its file is read or
        # planned); its plan split (the plan's own seconds), the pace its moves are given
        # at, and the slicer's own figure beside it.
        "estimated_time": running.expected,
        **dict(zip(SPLIT_FIELDS, split, strict=True)),
        "estimated_pace": running.pace,
        "estimated_time_limits_from": limits_from,
        "slicer_estimated_time": running.slicer_seconds,
    }


SPLIT_FIELDS = ("estimated_moving", "estimated_heating", "estimated_tool_changes")


async def _jobs_json(server: PrintServer, name: str) -> list[dict[str, Any]]:
    """The printer's jobs (queued ones first, in queue order), the queued ones with their
    estimate and when they should start and end."""
    service = server.service(name)
    summaries = await asyncio.to_thread(service.queued_summaries)
    times = service.forecast(service.running_left(), summaries).jobs
    return [
        {**r.as_json(), **times[r.id].as_json()} if r.id in times else r.as_json()
        for r in server.store.jobs(service.name)
    ]


def _sse(event: dict[str, Any]) -> str:
    return f"event: {event['type']}\ndata: {json.dumps(event)}\n\n"


class Move(BaseModel):
    before: Annotated[int, Field(ge=1, le=MAX_ID)] | None = None  # a queued job; None: the end


class GcodeCommand(BaseModel):
    """A line of G-code to send to a printer: ``{"command": "G28"}``."""

    command: str


class Decision(BaseModel):
    allow: bool


class LinkToken(BaseModel):
    token: str = Field(max_length=200)  # a one-time link's (its #token=)


class LinkWanted(BaseModel):
    app: str | None = Field(default=None, min_length=1, max_length=200)  # its app key's name
    seconds: float = Field(default=LINK_SECONDS, gt=0, le=LINK_LONGEST)  # how long it is good


class Folder(BaseModel):
    path: str  # below the uploads: "parts/brackets"


class Queued(BaseModel):
    """A stored file to print; recovered from a layer or line (hyrel-send's --from-layer)."""

    file: str  # below the uploads, as /v1/files names it
    from_layer: Annotated[int, Field(ge=1)] | None = None
    from_line: Annotated[int, Field(ge=1)] | None = None


class Timelapse(BaseModel):
    job: Annotated[int, Field(ge=1, le=MAX_ID)]


def router() -> APIRouter:
    router = APIRouter(prefix="/v1")

    @router.get("/printers")
    async def printers(request: Request) -> list[dict[str, Any]]:
        return [_printer_json(s) for s in server_of(request).services.values()]

    @router.get("/printers/{name}")
    async def printer(request: Request, name: str) -> dict[str, Any]:
        return _printer_json(server_of(request).service(name))

    @router.get("/printers/{name}/temperatures")
    async def temperatures(
        request: Request,
        name: str,
        since: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    ) -> dict[str, Any]:
        """The printer's temperature reports kept by the server (the last half hour by
        default; ``since``: after that time, in seconds since the epoch), oldest first, each
        heater as ``{"actual", "target"}``: what a chart shows at load, before the event
        stream's ``temperatures`` events go on from there."""
        service = server_of(request).service(name)
        start = time.time() - HISTORY_SHOWN if since is None else since
        samples = [
            {"time": when, "readings": _readings(readings)}
            for when, readings in list(service.temperature_history)
            if when > start
        ]
        return {"printer": service.name, "samples": samples}

    @router.get("/printers/{name}/totals")
    async def printer_totals(request: Request, name: str) -> dict[str, Any]:
        """What the printer's ended jobs add up to: jobs by outcome, seconds printed, lines,
        and filament by tool (``{"length": mm, "volume": cm3}``; a stopped job counts the
        share of its file that ran)."""
        server = server_of(request)
        service = server.service(name)
        return {"printer": service.name, **store.totals(server.store.jobs(service.name))}

    @router.get("/printers/{name}/jobs")
    async def printer_jobs(request: Request, name: str) -> list[dict[str, Any]]:
        return await _jobs_json(server_of(request), name)

    @router.post("/printers/{name}/jobs", status_code=201)
    async def submit(
        request: Request, name: str, file: Annotated[UploadFile, File()]
    ) -> dict[str, Any]:
        server = server_of(request)
        service = server.service(name)
        upload = await uploads.save_upload(server, service.name, file)
        record = jobs.queue(server, service.name, upload.path, upload.commands, user_of(request))
        return {**record.as_json(), "findings": upload.findings, "note": upload.note or None}

    @router.post("/printers/{name}/queue", status_code=201)
    async def queue_file(request: Request, name: str, queued: Queued) -> dict[str, Any]:
        """Queue a stored file (print again), or recover it from a layer or a line: the
        server's ``hyrel-send FILE --from-layer N``. Checked for this printer first."""
        server = server_of(request)
        service = server.service(name)
        path = uploads.uploaded(server, queued.file)
        from_line = await asyncio.to_thread(
            jobs.recovery_line, path, queued.from_layer, queued.from_line
        )
        findings, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
        uploads.refuse_errors(path.name, findings)
        record = jobs.queue(server, service.name, path, commands, user_of(request), from_line)
        return {**record.as_json(), "findings": findings}

    @router.get("/presets")
    async def presets(request: Request) -> dict[str, Any]:
        """The material presets of the configuration (``[presets.PLA] head = 210, bed =
        60``): temperatures in °C for a head, the bed, the chamber."""
        return server_of(request).presets

    @router.get("/files")
    async def files_listed(request: Request) -> list[dict[str, Any]]:
        server = server_of(request)
        return await asyncio.to_thread(uploads.uploads_json, server)

    @router.post("/files", status_code=201)
    async def upload(
        request: Request,
        file: Annotated[UploadFile, File()],
        folder: Annotated[str, Form()] = "",
        printer: str | None = None,
    ) -> dict[str, Any]:
        """Store a file without printing it (in ``folder``), checked by the lint for
        ``printer`` (the first one by default): refused (400) with errors, else its entry
        with the findings."""
        server = server_of(request)
        service = server.service(printer)
        upload = await uploads.save_upload(server, service.name, file, folder)
        entry = await asyncio.to_thread(uploads.file_json, server, upload.path)
        return {**entry, "findings": upload.findings, "note": upload.note or None}

    @router.get("/folders")
    async def folders(request: Request) -> list[str]:
        """Every folder below the uploads (empty ones too), by path."""
        root = server_of(request).files
        return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_dir())

    @router.post("/folders", status_code=201)
    async def make_folder(request: Request, folder: Folder) -> dict[str, str]:
        server = server_of(request)
        parent, _, name = folder.path.strip("/").rpartition("/")
        made = shared_folders.make_folder(server, parent, name)
        uploads.file_changed(server, made, "added", "add", folder=True)
        return {"path": made.relative_to(server.files).as_posix()}

    @router.delete("/folders/{location:path}", status_code=204)
    async def delete_folder(request: Request, location: str) -> Response:
        """Remove a folder and what is in it; 409 while a job uses a file in it."""
        server = server_of(request)
        path = server.files / uploads.safe_folder(location)
        if not path.is_dir() or path == server.files:
            raise HTTPException(404, f"no folder '{location}'")
        shared_folders.delete_folder(server, location)
        uploads.file_changed(server, path, "removed", "remove", folder=True)
        return Response(status_code=204)

    @router.get("/files/{location:path}/check")
    async def check_file(request: Request, location: str, printer: str | None = None) -> Any:
        """The lint's findings for the file on ``printer`` (the first by default), as a
        print would meet them, and the lines it sends."""
        server = server_of(request)
        service = server.service(printer)
        path = uploads.uploaded(server, location)
        findings, lines = await asyncio.to_thread(uploads.check, server, service.name, path)
        errors = sum(1 for f in findings if f.startswith("error"))
        return {"printer": service.name, "findings": findings, "errors": errors, "lines": lines}

    @router.get("/files/{location:path}/layers/{number}")
    async def layer(
        request: Request,
        location: str,
        number: Annotated[int, PathParameter(ge=1)],
        printer: str | None = None,
        moves: bool = True,
    ) -> dict[str, Any]:
        """Layer ``number``'s moves, for a layer view: ``[line, x0, y0, x1, y1, extrudes]``
        each (arcs as straight lines; ``moves=false``: left out), its Z, the file's layer
        count, and when ``printer`` (the first by default) prints the layer, if its running
        job prints this file."""
        server = server_of(request)
        service = server.service(printer)
        found = await asyncio.to_thread(uploads.layer_json, server, location, number, moves)
        running = service.running
        if running is not None and server.data_dir / running.record.file != (
            uploads.uploaded(server, location)
        ):
            running = None  # it prints another file: this one's layers are not printed now
        return {**found, **layer_times(running, found["first_line"], found["last_line"])}

    @router.get("/files/{location:path}/thumbnail")
    async def file_thumbnail(request: Request, location: str) -> Response:
        """The largest preview image the slicer embedded in the file (PrusaSlicer's,
        OrcaSlicer's, Cura's): PNG or JPEG as it was, QOI made PNG. 404 when it has none."""
        image, media_type = await asyncio.to_thread(uploads.thumbnail, server_of(request), location)
        return Response(image, media_type=media_type, headers={"Cache-Control": "no-cache"})

    @router.delete("/files/{location:path}", status_code=204)
    async def delete_file(request: Request, location: str) -> Response:
        uploads.delete_upload(server_of(request), location)
        return Response(status_code=204)

    @router.get("/events")
    async def events(request: Request, printer: str | None = None) -> StreamingResponse:
        """Server-sent events: each printer as it stands first, then printer states, jobs,
        progress, temperatures and controller messages as they come (JSON data)."""
        server = server_of(request)
        only = server.service(printer).name if printer else None
        names = [only] if only is not None else list(server.services)
        # Open reads hear no app-key requests: their user_token decides them.
        keyed = user_of(request) is not None

        async def stream() -> AsyncIterator[str]:
            async with server.events.listen(only) as events:  # before the snapshot: none lost
                for name in names:
                    now = {
                        "type": "printer",
                        "printer": name,
                        **_printer_json(server.services[name]),
                    }
                    yield _sse(now)
                while True:
                    try:
                        event = await asyncio.wait_for(events.get(), KEEPALIVE)
                    except TimeoutError:
                        yield ": keepalive\n\n"  # proxies keep the stream open
                        continue
                    if keyed or not isinstance(event, AppKeyEvent):
                        yield _sse(event.as_json())

        return StreamingResponse(stream(), media_type="text/event-stream")

    @router.get("/appkeys")
    async def app_keys(request: Request) -> dict[str, Any]:
        """The app keys granted (never the keys themselves) and the requests waiting: with
        a key only, as OctoPrint's list (a request's user_token decides it)."""
        appkeys.user_needed(request)
        access = server_of(request).access
        return {
            "keys": [appkeys.key_json(key) for key in access.app_keys()],
            "pending": [pending.public() for pending in access.pending()],
        }

    @router.post("/appkeys/requests/{user_token}", status_code=204)
    async def decide(request: Request, user_token: str, decision: Decision) -> Response:
        """Allow or deny an application's request for a key."""
        user = user_of(request) or OWNER
        appkeys.decided(server_of(request), user_token, decision.allow, user)
        return Response(status_code=204)

    @router.delete("/appkeys/{app}", status_code=204)
    async def revoke(request: Request, app: str) -> Response:
        """Revoke the key of an application; it is refused from now on."""
        server = server_of(request)
        if not server.access.revoke(app):
            raise HTTPException(404, f"no key for app '{app}'")
        server.events.publish(AppKeyEvent("revoked", app))
        return Response(status_code=204)

    @router.post("/links", status_code=201)
    async def new_link(request: Request, wanted: LinkWanted) -> dict[str, Any]:
        """A one-time link to the page, as ``hyrel-server link`` makes one: for another
        screen, which gets an app key of its own when it opens it."""
        appkeys.user_needed(request)
        server = server_of(request)
        token, made = await asyncio.to_thread(
            make_page_link, server.data_dir, wanted.app and wanted.app.strip(), wanted.seconds
        )
        url = f"{str(request.base_url).rstrip('/')}/#token={token}"
        return {"url": url, "app_id": made.app, "expires": iso(made.expires)}

    @router.post("/links/redeem")
    async def redeem(request: Request, link: LinkToken) -> dict[str, str]:
        """The app key a one-time link grants (``hyrel-server link``), once: open to anyone,
        the link is what lets in. 403 with why for a link unknown, used or expired."""
        server = server_of(request)
        try:  # under the files' locks: off the event loop
            granted = await asyncio.to_thread(redeem_page_link, server.data_dir, link.token)
        except LinkRefused as refused:
            raise HTTPException(403, str(refused)) from None
        server.events.publish(AppKeyEvent("granted", granted.app))
        return {"api_key": granted.key, "app_id": granted.app}

    @router.get("/jobs/{job_id}")
    async def job(request: Request, job_id: JobId) -> dict[str, Any]:
        record = server_of(request).store.job(job_id)
        if record is None:
            raise HTTPException(404, f"no job {job_id}")
        return record.as_json()

    @router.delete("/jobs/{job_id}")
    async def cancel_job(request: Request, job_id: JobId) -> Any:
        server = server_of(request)
        record = server.store.job(job_id)
        if record is None:
            raise HTTPException(404, f"no job {job_id}")
        service = server.service(record.printer)
        if not await service.cancel(job_id):
            raise HTTPException(409, f"job {job_id} is {record.state.value}: nothing to cancel")
        ended = server.store.job(job_id)
        assert ended is not None
        if ended.state in ACTIVE:
            # Still stopping: its safe stop is held up (or slow). Accepted, and why.
            stopping = service.stop_held or "the safe stop is not confirmed yet"
            return JSONResponse({**ended.as_json(), "stopping": stopping}, status_code=202)
        return ended.as_json()

    @router.get("/jobs/{job_id}/resume")
    async def recovery(request: Request, job_id: JobId) -> dict[str, Any]:
        """Where a job that did not complete would be recovered: the first line not acknowledged,
        the start of its layer, and the commands (``hyrel-send``'s, and this API's)."""
        server = server_of(request)
        record = server.store.job(job_id)
        if record is None:
            raise HTTPException(404, f"no job {job_id}")
        return await asyncio.to_thread(jobs.recovery_json, server, record)

    @router.post("/jobs/{job_id}/move")
    async def move(request: Request, job_id: JobId, move: Move) -> list[dict[str, Any]]:
        server = server_of(request)
        record = server.store.job(job_id)
        if record is None or not server.store.move(job_id, move.before):
            where = f" or job {move.before} is not" if move.before is not None else ""
            raise HTTPException(409, f"job {job_id} is not queued{where}")
        return await _jobs_json(server, record.printer)

    @router.get("/printers/{name}/snapshots")
    async def snapshots(request: Request, name: str) -> list[dict[str, Any]]:
        """The printer's camera snapshots, newest first."""
        service = server_of(request).service(name)
        images = service.camera.images() if service.camera is not None else []
        return [{"file": path.name, "url": service.url(path)} for path in images]

    @router.get("/printers/{name}/snapshots/{file}")
    async def snapshot_image(request: Request, name: str, file: str) -> FileResponse:
        """A snapshot by its name; ``latest``: the newest (OctoPrint's snapshot URL)."""
        service = server_of(request).service(name)
        camera = service.camera
        if file == "latest" and camera is not None:
            newest = camera.images()[:1]
            if newest:
                return FileResponse(newest[0], headers={"Cache-Control": "no-cache"})
        path = camera.folder / file if camera is not None else None
        if path is None or not _SNAPSHOT.fullmatch(file) or not path.is_file():
            raise HTTPException(404, f"no snapshot '{file}' of printer {service.name}")
        return FileResponse(path, headers={"Cache-Control": "max-age=86400, immutable"})

    @router.post("/printers/{name}/snapshots", status_code=201)
    async def take_snapshot(request: Request, name: str) -> dict[str, Any]:
        """A snapshot now (the camera's settings, tried out)."""
        service = server_of(request).service(name)
        path = await answered(service.snapshot())
        return {"file": path.name, "url": service.url(path)}

    @router.get("/printers/{name}/timelapses")
    async def timelapses(request: Request, name: str) -> dict[str, Any]:
        """The time-lapse videos made of the printer's layer snapshots, newest first, and
        whether they can be made here (``ffmpeg``: its path, or None and why not)."""
        service = server_of(request).service(name)
        videos = timelapse.videos(service.camera.folder) if service.camera is not None else []
        ffmpeg = timelapse.ffmpeg()
        return {
            "ffmpeg": ffmpeg,
            "missing": None if ffmpeg else timelapse.NO_FFMPEG,
            "videos": [{"file": p.name, "url": service.url(p)} for p in videos],
        }

    @router.post("/printers/{name}/timelapses", status_code=201)
    async def make_timelapse(request: Request, name: str, wanted: Timelapse) -> dict[str, Any]:
        """A video of a job's layer snapshots (ffmpeg, 10 images a second)."""
        service = server_of(request).service(name)
        if service.camera is None:
            raise HTTPException(409, f"printer {service.name} has no camera")
        try:
            path = await timelapse.make(service.camera.folder, wanted.job)
        except timelapse.CannotMake as exc:
            raise HTTPException(exc.status, str(exc)) from None
        return {"file": path.name, "url": service.url(path)}

    @router.post("/printers/{name}/command")
    async def command(request: Request, name: str, body: GcodeCommand) -> dict[str, Any]:
        reply = await answered(server_of(request).service(name).command(body.command))
        return {
            "command": reply.command,
            "lines": reply.lines,
            "ok": reply.ok,
            "ok_line": reply.ok_line,
        }

    @router.post("/printers/{name}/{action}", status_code=204)
    async def control(request: Request, name: str, action: str) -> Response:
        service = server_of(request).service(name)
        await answered(service.control(action))
        return Response(status_code=204)

    return router
