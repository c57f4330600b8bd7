"""The print server's HTTP API: native endpoints under ``/v1``, and the part of
OctoPrint's API that slicers and farm tools use, at ``/api`` (the default printer) and
``/printers/NAME/api`` (each printer, so a farm tool sees one OctoPrint per printer).

Every request that changes something needs the API key (``X-Api-Key``, or ``apikey``
in the query, as OctoPrint takes it). Errors are 4xx answers with a JSON body.
Models: OctoPrint's REST API (``/api/files/local``, ``/api/job``, ``/api/printer``) as
PrusaSlicer's ``OctoPrint.cpp`` uses it; Moonraker's queue endpoints.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import os
import re
import shutil
import time
from collections.abc import AsyncIterator, Awaitable
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, TypeVar
from urllib.parse import parse_qsl

from fastapi import (
    APIRouter,
    Depends,
    FastAPI,
    File,
    Form,
    Header,
    HTTPException,
    Query,
    Request,
    UploadFile,
)
from fastapi.exceptions import RequestValidationError
from fastapi.responses import (
    FileResponse,
    HTMLResponse,
    JSONResponse,
    Response,
    StreamingResponse,
)
from pydantic import BaseModel

import repetrel_host as rh
from repetrel_host.config import UserConfig
from repetrel_host.server.events import EventHub
from repetrel_host.server.mqtt import MqttSettings
from repetrel_host.server.printers import PrinterConfig, PrinterService, Refused
from repetrel_host.server.store import ACTIVE, JobRecord, JobState, Store

log = logging.getLogger("repetrel_host.server")

# What /api/version says: PrusaSlicer checks that "text" starts with "OctoPrint".
OCTOPRINT_VERSION = "1.10.0"
G_CODE_SUFFIXES = (".gcode", ".gco", ".g")
KEEPALIVE = 15.0  # seconds of quiet before the event stream says it is alive
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._ ()+-]")
T = TypeVar("T")
_SNAPSHOT = re.compile(r"[A-Za-z0-9_-]+\.(jpg|png|gif|webp)")


class PrintServer:
    """The printers, their store and the data folder; started and stopped with the app."""

    def __init__(
        self,
        data_dir: Path,
        printers: dict[str, PrinterConfig],
        api_key: str,
        max_upload: int,
        user: UserConfig | None = None,
        mqtt: MqttSettings | None = None,
        automatic_transition: bool = False,
    ) -> None:
        self.data_dir = data_dir
        self.files = data_dir / "files"
        self.files.mkdir(parents=True, exist_ok=True)
        self.api_key = api_key
        self.max_upload = max_upload
        self.user = user or UserConfig()
        self.store = Store(data_dir / "jobs.sqlite")
        self.events = EventHub()
        self.mqtt = mqtt
        self._bridge: asyncio.Task[None] | None = None
        self.services = {
            name: PrinterService(name, config, self.store, data_dir, self.user, self.events.publish)
            for name, config in printers.items()
        }
        for service in self.services.values():
            service.automatic_transition = automatic_transition
        self.default = next(iter(self.services))
        for record in self.store.interrupt_active():
            log.warning(
                "job %d (%s) on printer %s was interrupted: acknowledged through at least "
                "line %d; its safe stop goes first",
                record.id,
                record.name,
                record.printer,
                record.last_line,
            )
        for service in self.services.values():
            owing = self.store.owing(service.name)
            if owing:  # interrupted, or ended without its safe stop confirmed
                service.owed_safe_stop = True
                log.warning(
                    "printer %s: the safe stop of job %s is owed: it goes as soon as the "
                    "printer answers",
                    service.name,
                    ", ".join(map(str, owing)),
                )
        # After an interrupted job nothing starts by itself: a part may be on the bed.
        for service in self.services.values():
            last = self.store.last_started(service.name)
            if last is not None and last.state is JobState.INTERRUPTED:
                service.held = True
                log.warning(
                    "printer %s: the queue is held after interrupted job %d "
                    "(POST /v1/printers/%s/release, or OctoPrint's job start, releases it)",
                    service.name,
                    last.id,
                    service.name,
                )

    async def start(self) -> None:
        for service in self.services.values():
            service.start()
        if self.mqtt is not None:
            from repetrel_host.server.mqtt import MqttBridge

            bridge = MqttBridge(self, self.mqtt)
            self._bridge = asyncio.get_running_loop().create_task(bridge.run(), name="mqtt")

    async def stop(self) -> None:
        await asyncio.gather(*(service.stop() for service in self.services.values()))
        if self._bridge is not None:  # after the printers: their last events go out
            await asyncio.sleep(0.2)
            self._bridge.cancel()
            await asyncio.gather(self._bridge, return_exceptions=True)
        self.store.close()

    def service(self, name: str | None) -> PrinterService:
        service = self.services.get(name or self.default)
        if service is None:
            raise HTTPException(404, f"no printer '{name}' (printers: {', '.join(self.services)})")
        return service


# --- helpers ------------------------------------------------------------------------


def _server(request: Request) -> PrintServer:
    server: PrintServer = request.app.state.server
    return server


def require_key(
    request: Request,
    x_api_key: Annotated[str | None, Header()] = None,
    apikey: Annotated[str | None, Query()] = None,
) -> None:
    """State-changing requests carry the API key."""
    given = x_api_key or apikey or ""
    if not hmac.compare_digest(given.encode(), _server(request).api_key.encode()):
        raise HTTPException(403, "a valid API key is needed (the X-Api-Key header)")


Keyed = Depends(require_key)


def _printer_json(service: PrinterService) -> dict[str, Any]:
    printer = service.printer
    running = service.running
    return {
        "name": service.name,
        "port": service.port,
        "state": service.state,
        "held": service.held,
        "error": service.last_error or None,
        "firmware": printer.firmware.name if printer and printer.firmware else None,
        "protocol": printer.settings.protocol if printer else None,  # the link's: reprap, hyrel
        "temperatures": {
            sensor: {"actual": actual, "target": target}
            for sensor, (actual, target) in (printer.temperatures if printer else {}).items()
        },
        "job": _running_json(service) if running is not None else None,
        "camera": service.camera is not None,
        "snapshot": _latest_snapshot(service),
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


def safe_file_name(name: str) -> str:
    """The upload's own name, without folders, in safe characters; 400 if nothing is left
    or it is not a G-code file."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1].strip()
    cleaned = _SAFE_NAME.sub("_", base).lstrip(".")
    if not cleaned or not cleaned.lower().endswith(G_CODE_SUFFIXES):
        raise HTTPException(400, f"'{name}' is not a G-code file name (.gcode, .gco, .g)")
    return cleaned


def _safe_folder(path: str) -> Path:
    """OctoPrint's ``path`` field: a folder below the uploads; no '..', no absolute path."""
    parts = [part for part in path.replace("\\", "/").split("/") if part not in ("", ".")]
    if any(part == ".." for part in parts) or path.startswith(("/", "\\")):
        raise HTTPException(400, f"path '{path}' leaves the upload folder")
    return Path(*(_SAFE_NAME.sub("_", part) for part in parts)) if parts else Path()


async def _save_upload(
    server: PrintServer, printer: str, upload: UploadFile, folder: str = ""
) -> tuple[Path, list[str], int]:
    """Write the upload into the data folder (a new name if taken, never over another
    file), and check it: the stored path, the lint's findings, its number of commands.
    A file with errors is removed and refused (400, with the findings)."""
    name = safe_file_name(upload.filename or "")
    target_dir = server.files / _safe_folder(folder)
    target_dir.mkdir(parents=True, exist_ok=True)
    target = target_dir / name
    stem, suffix = target.stem, target.suffix
    number = 1
    while target.exists():  # a queued job may point at it
        number += 1
        target = target_dir / f"{stem}-{number}{suffix}"
    size = 0
    try:
        with target.open("xb") as out:
            while chunk := await upload.read(1 << 20):
                size += len(chunk)
                if size > server.max_upload:
                    raise HTTPException(413, f"the upload is over {server.max_upload} bytes")
                out.write(chunk)
            out.flush()
            # On disk before the client hears it is there; checked in a thread: a big file
            # must not hold the event loop (and every printer's stream) up.
            await asyncio.to_thread(os.fsync, out.fileno())
        findings, commands = await asyncio.to_thread(_check, server, printer, target)
        errors = [f for f in findings if f.startswith("error")]
        if errors:
            raise HTTPException(
                400, {"error": f"{name}: refused ({len(errors)} errors)", "findings": findings}
            )
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return target, findings, commands


def _queue(server: PrintServer, printer: str, path: Path, commands: int) -> JobRecord:
    record = server.store.submit(printer, path.name, _relative(server, path), commands)
    log.info("job %d (%s) queued on printer %s", record.id, path.name, printer)
    service = server.services[printer]
    service.job_changed(record.id)
    service.wake()
    return record


def _relative(server: PrintServer, path: Path) -> str:
    return path.relative_to(server.data_dir).as_posix()


def _uploaded(server: PrintServer, location: str) -> Path:
    """An uploaded file by its place below the uploads; 404 when there is none."""
    path = server.files / _safe_folder(location)
    if not path.is_file():
        raise HTTPException(404, f"no file '{location}'")
    return path


def _delete_upload(server: PrintServer, location: str) -> None:
    """Remove an uploaded file; 409 while a queued or running job prints it."""
    path = _uploaded(server, location)
    users = server.store.jobs_using(_relative(server, path))
    if users:
        jobs = ", ".join(str(job) for job in users)
        raise HTTPException(409, f"'{location}' is used by job {jobs}: cancel it first")
    path.unlink()
    for service in server.services.values():
        service.forget(path)
        if service.selected == path:
            service.selected = None
    log.info("file %s deleted", location)


def _check(server: PrintServer, printer: str, path: Path) -> tuple[list[str], int]:
    """The job lint's findings (``error: file:line: ...``) and the number of lines to send."""
    try:
        plan, findings = server.services[printer].check(path)
    except rh.HostError as exc:  # named by the file's name, not its place on the server
        return [f"error: {str(exc).replace(str(path), path.name)}"], 0
    commands = sum(1 for _ in plan.job.lines())  # what goes on the wire: host codes do not
    return [f"{f.severity}: {f.format(path.name)}" for f in findings], commands


class RequestGuard:
    """Before any body is read: a request that changes something needs the key (403), and
    a body over the upload limit is refused (413), chunked or not. FastAPI's own checks
    come after the body was parsed, which would let anyone fill the disk."""

    def __init__(self, app: Any, server: PrintServer) -> None:
        self.app = app
        self.server = server

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        server = self.server
        limit = server.max_upload + 65536  # the form's own bytes
        headers = {key.decode("latin-1").lower(): value for key, value in scope["headers"]}
        query = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))
        given = headers.get("x-api-key", b"").decode("latin-1") or query.get("apikey", "")
        if not hmac.compare_digest(given.encode(), server.api_key.encode()):
            detail = "a valid API key is needed (the X-Api-Key header)"
            await JSONResponse({"detail": detail}, 403)(scope, receive, send)
            return
        length = headers.get("content-length", b"")
        too_big = {"detail": f"the upload is over {server.max_upload} bytes"}
        if length.isdigit() and int(length) > limit:
            await JSONResponse(too_big, 413)(scope, receive, send)
            return
        received, over, started = 0, False, False

        async def counted() -> Any:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    over = True
                    return {"type": "http.disconnect"}  # the app stops reading
            return message

        async def watched(message: Any) -> None:
            nonlocal started
            if over:
                return  # the app's answer to a body cut short: ours goes instead
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, watched)
        except Exception:
            if not over:
                raise
        if over and not started:
            await JSONResponse(too_big, 413)(scope, receive, send)


# --- request bodies -----------------------------------------------------------------


class Move(BaseModel):
    before: int | None = None  # a queued job's id; None: to the end


class Command(BaseModel):
    command: str


class JobCommand(BaseModel):
    command: str
    action: str | None = None


class PrinterCommand(BaseModel):
    command: str | None = None
    commands: list[str] | None = None


class ConnectionCommand(BaseModel):
    command: str


# --- the app --------------------------------------------------------------------------


def create_app(server: PrintServer) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await server.start()
        try:
            yield
        finally:
            await server.stop()  # SIGTERM: running jobs stop with their safe stop

    app = FastAPI(title="repetrel-host print server", version=rh.__version__, lifespan=lifespan)
    app.state.server = server
    app.add_middleware(RequestGuard, server=server)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in error['loc'])}: {error['msg']}" for error in exc.errors()
        )
        return JSONResponse(status_code=400, content={"detail": f"bad request: {problems}"})

    page = resources.files("repetrel_host.server").joinpath("page.html").read_text()

    @app.get("/", include_in_schema=False)
    async def status_page() -> HTMLResponse:
        """The status page: printers, queues, progress, temperatures, live."""
        return HTMLResponse(page)

    app.include_router(_native_router())
    octoprint = _octoprint_router()
    app.include_router(octoprint)
    app.include_router(octoprint, prefix="/printers/{printer}")
    return app


def _native_router() -> APIRouter:
    router = APIRouter(prefix="/v1")

    @router.get("/printers")
    async def printers(request: Request) -> list[dict[str, Any]]:
        return [_printer_json(s) for s in _server(request).services.values()]

    @router.get("/printers/{name}")
    async def printer(request: Request, name: str) -> dict[str, Any]:
        return _printer_json(_server(request).service(name))

    @router.get("/printers/{name}/jobs")
    async def printer_jobs(request: Request, name: str) -> list[dict[str, Any]]:
        server = _server(request)
        server.service(name)
        return [r.as_json() for r in server.store.jobs(name)]

    @router.post("/printers/{name}/jobs", status_code=201, dependencies=[Keyed])
    async def submit(
        request: Request, name: str, file: Annotated[UploadFile, File()]
    ) -> dict[str, Any]:
        server = _server(request)
        service = server.service(name)
        path, findings, commands = await _save_upload(server, service.name, file)
        return {**_queue(server, service.name, path, commands).as_json(), "findings": findings}

    @router.get("/files")
    async def files(request: Request) -> list[dict[str, Any]]:
        server = _server(request)
        return _uploads_json(server)

    @router.delete("/files/{location:path}", status_code=204, dependencies=[Keyed])
    async def delete_file(request: Request, location: str) -> Response:
        _delete_upload(_server(request), location)
        return Response(status_code=204)

    @router.get("/events")
    async def events(request: Request, printer: str | None = None) -> StreamingResponse:
        """Server-sent events: each printer as it stands first, then printer states, jobs,
        progress, temperatures and controller messages as they come (JSON data)."""
        server = _server(request)
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
                    if event.get("printer") in names:
                        yield _sse(event)

        return StreamingResponse(stream(), media_type="text/event-stream")

    @router.get("/jobs/{job_id}")
    async def job(request: Request, job_id: int) -> dict[str, Any]:
        record = _server(request).store.job(job_id)
        if record is None:
            raise HTTPException(404, f"no job {job_id}")
        return record.as_json()

    @router.delete("/jobs/{job_id}", dependencies=[Keyed])
    async def cancel_job(request: Request, job_id: int) -> Any:
        server = _server(request)
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

    @router.post("/jobs/{job_id}/move", dependencies=[Keyed])
    async def move(request: Request, job_id: int, move: Move) -> list[dict[str, Any]]:
        server = _server(request)
        record = server.store.job(job_id)
        if record is None or not server.store.move(job_id, move.before):
            where = f" or job {move.before} is not" if move.before is not None else ""
            raise HTTPException(409, f"job {job_id} is not queued{where}")
        return [r.as_json() for r in server.store.jobs(record.printer)]

    @router.get("/printers/{name}/snapshots")
    async def snapshots(request: Request, name: str) -> list[dict[str, Any]]:
        """The printer's camera snapshots, newest first."""
        service = _server(request).service(name)
        images = service.camera.images() if service.camera is not None else []
        return [{"file": path.name, "url": service.url(path)} for path in images]

    @router.get("/printers/{name}/snapshots/{file}")
    async def snapshot_image(request: Request, name: str, file: str) -> FileResponse:
        service = _server(request).service(name)
        camera = service.camera
        path = camera.folder / file if camera is not None else None
        if path is None or not _SNAPSHOT.fullmatch(file) or not path.is_file():
            raise HTTPException(404, f"no snapshot '{file}' of printer {service.name}")
        return FileResponse(path, headers={"Cache-Control": "max-age=86400, immutable"})

    @router.post("/printers/{name}/snapshots", status_code=201, dependencies=[Keyed])
    async def take_snapshot(request: Request, name: str) -> dict[str, Any]:
        """A snapshot now (the camera's settings, tried out)."""
        service = _server(request).service(name)
        path = await _answered(service.snapshot())
        return {"file": path.name, "url": service.url(path)}

    @router.post("/printers/{name}/command", dependencies=[Keyed])
    async def command(request: Request, name: str, body: Command) -> dict[str, Any]:
        reply = await _answered(_server(request).service(name).command(body.command))
        return {"command": reply.command, "lines": reply.lines, "ok": reply.ok}

    @router.post("/printers/{name}/{action}", status_code=204, dependencies=[Keyed])
    async def control(request: Request, name: str, action: str) -> Response:
        service = _server(request).service(name)
        await _answered(service.control(action))
        return Response(status_code=204)

    return router


async def _answered(call: Awaitable[T]) -> T:
    """What the printer's ``call`` gives; its :class:`Refused` as an HTTP error."""
    try:
        return await call
    except Refused as exc:
        raise HTTPException(exc.status, str(exc)) from None


# --- OctoPrint -------------------------------------------------------------------------


def _file_json(server: PrintServer, path: Path) -> dict[str, Any]:
    return {
        "name": path.name,
        "display": path.name,
        "path": path.relative_to(server.files).as_posix(),
        "origin": "local",
        "type": "machinecode",
        "size": path.stat().st_size,
        "date": int(path.stat().st_mtime),
    }


def _uploads_json(server: PrintServer) -> list[dict[str, Any]]:
    return [_file_json(server, p) for p in sorted(server.files.rglob("*")) if p.is_file()]


def _true(value: str) -> bool:
    return value.strip().lower() in ("true", "1", "yes")


def _octoprint_state(service: PrinterService) -> str:
    return {
        "ready": "Operational",
        "printing": "Printing",
        "paused": "Paused",
        "connecting": "Connecting",
    }.get(service.state, "Offline")


def _service_for(request: Request) -> PrinterService:
    """The printer in the path (``/printers/NAME/api/...``), else the default one."""
    return _server(request).service(request.path_params.get("printer"))


Printer = Annotated[PrinterService, Depends(_service_for)]


def _octoprint_router() -> APIRouter:
    router = APIRouter(prefix="/api")

    @router.get("/version")
    async def version() -> dict[str, str]:
        return {
            "api": "0.1",
            "server": OCTOPRINT_VERSION,
            "text": f"OctoPrint {OCTOPRINT_VERSION} (repetrel-host {rh.__version__})",
        }

    @router.get("/server")
    async def server_info() -> dict[str, Any]:
        return {"version": OCTOPRINT_VERSION, "safemode": None}

    @router.post("/files/local", status_code=201, dependencies=[Keyed])
    async def upload(
        request: Request,
        service: Printer,
        file: Annotated[UploadFile, File()],
        path: Annotated[str, Form()] = "",
        select: Annotated[str, Form()] = "false",
        print: Annotated[str, Form()] = "false",
    ) -> dict[str, Any]:
        server = _server(request)
        stored, findings, commands = await _save_upload(server, service.name, file, path)
        answer: dict[str, Any] = {"findings": findings}
        if _true(print):
            # Queued: it runs when the printer is free (OctoPrint answers 409 when it is
            # busy; a queue is what this server is for).
            answer["job"] = _queue(server, service.name, stored, commands).as_json()
        elif _true(select):
            service.selected = stored
        location = stored.relative_to(server.files).as_posix()
        base = str(request.base_url).rstrip("/")
        return {
            "done": True,
            "files": {
                "local": {
                    "name": stored.name,
                    "display": stored.name,
                    "path": location,
                    "origin": "local",
                    "refs": {"resource": f"{base}/api/files/local/{location}"},
                }
            },
            **answer,
        }

    @router.get("/files")
    async def files(request: Request) -> dict[str, Any]:
        server = _server(request)
        return {"files": _uploads_json(server), "free": shutil.disk_usage(server.data_dir).free}

    @router.get("/files/local/{location:path}")
    async def file(request: Request, location: str) -> dict[str, Any]:
        server = _server(request)
        return _file_json(server, _uploaded(server, location))

    @router.delete("/files/local/{location:path}", status_code=204, dependencies=[Keyed])
    async def delete_file(request: Request, location: str) -> Response:
        _delete_upload(_server(request), location)
        return Response(status_code=204)

    @router.get("/job")
    async def job(service: Printer) -> dict[str, Any]:
        running = service.running
        if running is None:
            selected = service.selected
            file: dict[str, Any] = {"name": None, "path": None, "origin": None, "size": None}
            if selected is not None and selected.exists():
                name = selected.name
                file = {
                    "name": name,
                    "path": name,
                    "origin": "local",
                    "size": selected.stat().st_size,
                }
            return {
                "job": {"file": file},
                "progress": {"completion": None, "filepos": None, "printTime": None},
                "state": _octoprint_state(service),
            }
        job = running.job
        elapsed = time.time() - (running.record.started or time.time())
        return {
            "job": {
                "file": {
                    "name": running.record.name,
                    "path": Path(running.record.file).relative_to("files").as_posix(),
                    "display": running.record.name,
                    "origin": "local",
                    "size": job.size,
                    "date": int(running.record.submitted),
                },
                "estimatedPrintTime": None,
                "user": None,
            },
            "progress": {
                "completion": 100.0 * job.offset / job.size if job.size else None,
                "filepos": job.offset,
                "printTime": int(elapsed),
                "printTimeLeft": None,
            },
            "state": _octoprint_state(service),
        }

    @router.post("/job", status_code=204, dependencies=[Keyed])
    async def job_command(request: Request, service: Printer, body: JobCommand) -> Response:
        server = _server(request)
        if body.command == "start":
            selected, service.selected = service.selected, None
            if selected is None and service.store.next_queued(service.name) is None:
                raise HTTPException(409, f"printer {service.name}: no file selected, none queued")
            if selected is not None:
                _, commands = await asyncio.to_thread(_check, server, service.name, selected)
                _queue(server, service.name, selected, commands)
            service.release()  # a held queue goes on too
        elif body.command == "cancel":
            await _answered(service.control("cancel"))
        elif body.command == "pause":
            action = body.action or "toggle"
            if action == "toggle":
                action = "resume" if service.state == "paused" else "pause"
            if action not in ("pause", "resume"):
                raise HTTPException(400, f"action '{action}' is not pause, resume or toggle")
            if service.running is None:
                raise HTTPException(409, f"printer {service.name} is not printing")
            await _answered(service.control(action))
        else:
            raise HTTPException(400, f"command '{body.command}' is not start, cancel or pause")
        return Response(status_code=204)

    @router.get("/printer")
    async def printer_state(service: Printer) -> dict[str, Any]:
        state = _octoprint_state(service)
        if state in ("Offline", "Connecting"):
            raise HTTPException(409, "Printer is not operational")
        printer = service.printer
        assert printer is not None
        temperatures = {}
        for sensor, (actual, target) in printer.temperatures.items():
            key = (
                "bed"
                if sensor == "B"
                else f"tool{sensor[1:] or '0'}"
                if sensor[0] == "T"
                else sensor
            )
            temperatures[key] = {"actual": actual, "target": target, "offset": 0}
        return {
            "state": {
                "text": state,
                "flags": {
                    "operational": True,
                    "printing": state == "Printing",
                    "paused": state == "Paused",
                    "pausing": False,
                    "cancelling": False,
                    "ready": state == "Operational",
                    "error": False,
                    "closedOrError": False,
                    "sdReady": False,
                },
            },
            "temperature": temperatures,
        }

    @router.post("/printer/command", status_code=204, dependencies=[Keyed])
    async def printer_command(service: Printer, body: PrinterCommand) -> Response:
        lines = body.commands or ([body.command] if body.command else [])
        if not lines:
            raise HTTPException(400, "give 'command' or 'commands'")
        for line in lines:
            await _answered(service.command(line))
        return Response(status_code=204)

    @router.get("/connection")
    async def connection(request: Request, service: Printer) -> dict[str, Any]:
        return {
            "current": {
                "state": _octoprint_state(service),
                "port": service.port,
                "baudrate": service.printer.settings.baud if service.printer else None,
                "printerProfile": "_default",
            },
            "options": {
                "ports": [service.port],
                "baudrates": [],
                "printerProfiles": [{"id": "_default", "name": service.name}],
                "portPreference": service.port,
                "baudratePreference": None,
                "printerProfilePreference": "_default",
                "autoconnect": True,
            },
        }

    @router.post("/connection", status_code=204, dependencies=[Keyed])
    async def connection_command(service: Printer, body: ConnectionCommand) -> Response:
        # The server keeps every printer connected (and reconnects by itself).
        if body.command not in ("connect", "disconnect", "fake_ack"):
            raise HTTPException(400, f"command '{body.command}' is not connect or disconnect")
        if body.command == "disconnect":
            raise HTTPException(409, "the server keeps its printers connected")
        return Response(status_code=204)

    return router
