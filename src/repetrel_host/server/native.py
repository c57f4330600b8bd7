"""The native API, under ``/v1``: printers, their queues and jobs, files, snapshots,
commands, and a stream of server-sent events."""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import AsyncIterator, Mapping
from typing import Annotated, Any

from fastapi import (
    APIRouter,
    File,
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

from repetrel_host.server import core, store
from repetrel_host.server.access import OWNER
from repetrel_host.server.auth import user_of
from repetrel_host.server.core import answered, server_of
from repetrel_host.server.octoprint import appkeys
from repetrel_host.server.printers import PrinterService
from repetrel_host.server.store import ACTIVE

MAX_ID = 2**63 - 1  # SQLite's largest integer: a job id beyond it is no job
JobId = Annotated[int, PathParameter(ge=1, le=MAX_ID)]
HISTORY_SHOWN = 1800.0  # s: the temperature reports given without ``since``
KEEPALIVE = 15.0  # seconds of quiet before the event stream says it is alive
_SNAPSHOT = re.compile(r"[A-Za-z0-9_-]+\.(jpg|png|gif|webp)")


def _printer_json(service: PrinterService) -> dict[str, Any]:
    printer = service.printer
    running = service.running
    return {
        "name": service.name,
        "port": service.port,
        "state": service.state,
        "since": service.state_since,  # in that state since (seconds since the epoch)
        "reason": service.state_reason or service.last_error or None,  # why, if said
        "held": service.held,
        "error": service.last_error or None,
        "firmware": printer.firmware.name if printer and printer.firmware else None,
        "protocol": printer.settings.protocol if printer else None,  # the link's: reprap, hyrel
        "temperatures": _readings(printer.temperatures if printer else {}),
        "job": _running_json(service) if running is not None else None,
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
    job = running.job
    record = running.record
    last = job.last
    return {
        **record.as_json(),
        "state": "paused" if service.state == "paused" else "printing",
        "lines": job.lines,
        "last_line": last.source_line if last else 0,
        "bytes": job.offset,
        "size": job.size,
        "layer": running.layer,
        "layers": len(running.layers),
    }


def _sse(event: dict[str, Any]) -> str:
    return f"event: {event['type']}\ndata: {json.dumps(event)}\n\n"


class Move(BaseModel):
    before: Annotated[int, Field(ge=1, le=MAX_ID)] | None = None  # a queued job; None: the end


class Command(BaseModel):
    command: str


class Decision(BaseModel):
    allow: bool


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
        server = server_of(request)
        server.service(name)
        return [r.as_json() for r in server.store.jobs(name)]

    @router.post("/printers/{name}/jobs", status_code=201)
    async def submit(
        request: Request, name: str, file: Annotated[UploadFile, File()]
    ) -> dict[str, Any]:
        server = server_of(request)
        service = server.service(name)
        upload = await core.save_upload(server, service.name, file)
        record = core.queue(server, service.name, upload.path, upload.commands, user_of(request))
        return {**record.as_json(), "findings": upload.findings, "note": upload.note or None}

    @router.get("/files")
    async def files(request: Request) -> list[dict[str, Any]]:
        server = server_of(request)
        return await asyncio.to_thread(core.uploads_json, server)

    @router.get("/files/{location:path}/thumbnail")
    async def file_thumbnail(request: Request, location: str) -> Response:
        """The largest preview image the slicer embedded in the file (PrusaSlicer's,
        OrcaSlicer's, Cura's): PNG or JPEG as it was, QOI made PNG. 404 when it has none."""
        image, media_type = await asyncio.to_thread(core.thumbnail, server_of(request), location)
        return Response(image, media_type=media_type, headers={"Cache-Control": "no-cache"})

    @router.delete("/files/{location:path}", status_code=204)
    async def delete_file(request: Request, location: str) -> Response:
        core.delete_upload(server_of(request), location)
        return Response(status_code=204)

    @router.get("/events")
    async def events(request: Request, printer: str | None = None) -> StreamingResponse:
        """Server-sent events: each printer as it stands first, then printer states, jobs,
        progress, temperatures and controller messages as they come (JSON data)."""
        server = server_of(request)
        names = [server.service(printer).name] if printer else list(server.services)

        async def stream() -> AsyncIterator[str]:
            async with server.events.subscribe() as queue:
                for name in names:
                    now = {
                        "type": "printer",
                        "printer": name,
                        **_printer_json(server.services[name]),
                    }
                    yield _sse(now)
                while True:
                    try:
                        event = await asyncio.wait_for(queue.get(), KEEPALIVE)
                    except TimeoutError:
                        yield ": keepalive\n\n"  # proxies keep the stream open
                        continue
                    if event.get("printer", names[0]) in names:  # none: the server's
                        yield _sse(event)

        return StreamingResponse(stream(), media_type="text/event-stream")

    @router.get("/appkeys")
    async def app_keys(request: Request) -> dict[str, Any]:
        """The app keys granted (never the keys themselves) and the requests waiting."""
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
        appkeys.tell(server, "revoked", app_id=app)
        return Response(status_code=204)

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

    @router.post("/jobs/{job_id}/move")
    async def move(request: Request, job_id: JobId, move: Move) -> list[dict[str, Any]]:
        server = server_of(request)
        record = server.store.job(job_id)
        if record is None or not server.store.move(job_id, move.before):
            where = f" or job {move.before} is not" if move.before is not None else ""
            raise HTTPException(409, f"job {job_id} is not queued{where}")
        return [r.as_json() for r in server.store.jobs(record.printer)]

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

    @router.post("/printers/{name}/command")
    async def command(request: Request, name: str, body: Command) -> dict[str, Any]:
        reply = await answered(server_of(request).service(name).command(body.command))
        return {"command": reply.command, "lines": reply.lines, "ok": reply.ok}

    @router.post("/printers/{name}/{action}", status_code=204)
    async def control(request: Request, name: str, action: str) -> Response:
        service = server_of(request).service(name)
        await answered(service.control(action))
        return Response(status_code=204)

    return router
