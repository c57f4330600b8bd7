"""OctoPrint's REST API, at ``/api`` (the default printer) and ``/printers/NAME/api``
(each printer, so that a farm tool sees one OctoPrint per printer)."""

from __future__ import annotations

import asyncio
import shutil
import time
from pathlib import Path
from typing import Annotated, Any

from fastapi import (
    APIRouter,
    Depends,
    File,
    Form,
    HTTPException,
    Request,
    UploadFile,
)
from fastapi.responses import (
    Response,
)
from pydantic import BaseModel

import repetrel_host as rh
from repetrel_host.server import core
from repetrel_host.server.auth import Keyed
from repetrel_host.server.core import answered, server_of
from repetrel_host.server.printers import PrinterService

# What /api/version says: PrusaSlicer checks that "text" starts with "OctoPrint".
OCTOPRINT_VERSION = "1.10.0"


class JobCommand(BaseModel):
    command: str
    action: str | None = None


class PrinterCommand(BaseModel):
    command: str | None = None
    commands: list[str] | None = None


class ConnectionCommand(BaseModel):
    command: str


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
    return server_of(request).service(request.path_params.get("printer"))


Printer = Annotated[PrinterService, Depends(_service_for)]


def router() -> APIRouter:
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
        server = server_of(request)
        stored, findings, commands = await core.save_upload(server, service.name, file, path)
        answer: dict[str, Any] = {"findings": findings}
        if _true(print):
            # Queued: it runs when the printer is free (OctoPrint answers 409 when it is
            # busy; a queue is what this server is for).
            answer["job"] = core.queue(server, service.name, stored, commands).as_json()
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
        server = server_of(request)
        return {"files": core.uploads_json(server), "free": shutil.disk_usage(server.data_dir).free}

    @router.get("/files/local/{location:path}")
    async def file(request: Request, location: str) -> dict[str, Any]:
        server = server_of(request)
        return core.file_json(server, core.uploaded(server, location))

    @router.delete("/files/local/{location:path}", status_code=204, dependencies=[Keyed])
    async def delete_file(request: Request, location: str) -> Response:
        core.delete_upload(server_of(request), location)
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
        server = server_of(request)
        if body.command == "start":
            selected, service.selected = service.selected, None
            if selected is None and service.store.next_queued(service.name) is None:
                raise HTTPException(409, f"printer {service.name}: no file selected, none queued")
            if selected is not None:
                _, commands = await asyncio.to_thread(core.check, server, service.name, selected)
                core.queue(server, service.name, selected, commands)
            service.release()  # a held queue goes on too
        elif body.command == "cancel":
            await answered(service.control("cancel"))
        elif body.command == "pause":
            action = body.action or "toggle"
            if action == "toggle":
                action = "resume" if service.state == "paused" else "pause"
            if action not in ("pause", "resume"):
                raise HTTPException(400, f"action '{action}' is not pause, resume or toggle")
            if service.running is None:
                raise HTTPException(409, f"printer {service.name} is not printing")
            await answered(service.control(action))
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
            await answered(service.command(line))
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
