"""OctoPrint's job (``/job``): the job shown and its progress, and its commands (start,
restart, pause, cancel); a print asked for goes through the server's queue."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response

from repetrel_host.server import uploads
from repetrel_host.server.auth import user_of
from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.common import OctoPrintCommand, Printer, operational, start
from repetrel_host.server.print_server import PrintServer, answered, server_of
from repetrel_host.server.printers.service import PrinterService


def router() -> APIRouter:
    """``/job``: its state (GET), its commands (POST)."""
    router = APIRouter()

    @router.get("/job")
    async def job(service: Printer) -> dict[str, Any]:
        state = model.state(service)
        answer = {
            "job": model.job(service),
            "progress": model.progress(service),
            "state": state["text"],
        }
        if state["error"]:
            answer["error"] = state["error"]
        return answer

    @router.post("/job", status_code=204)
    async def job_command(request: Request, service: Printer, body: OctoPrintCommand) -> Response:
        server = server_of(request)
        text = operational(service)
        active = text not in ("Operational", model.HELD_TEXT)
        if body.command == "start":
            if active:
                raise HTTPException(
                    409, "Printer already has an active print job, did you mean 'restart'?"
                )
            await _start(server, service, user_of(request))
        elif body.command == "restart":
            if text != "Paused":
                raise HTTPException(
                    409, "Printer does not have an active print job or is not paused"
                )
            await _restart(server, service, user_of(request))
        elif body.command == "pause":
            if not active:
                raise HTTPException(
                    409,
                    "Printer is neither printing nor paused, 'pause' command cannot be performed",
                )
            action = body.get("action", "toggle")
            if action == "toggle":
                action = "resume" if text == "Paused" else "pause"
            if action not in ("pause", "resume"):
                raise HTTPException(400, "Unknown action")
            await answered(service.control(action))
        elif body.command == "cancel":
            if not active:
                raise HTTPException(
                    409,
                    "Printer is neither printing nor paused, 'cancel' command cannot be performed",
                )
            await answered(service.control("cancel"))
        else:
            raise HTTPException(
                400, f"command '{body.command}' is not start, restart, pause or cancel"
            )
        return Response(status_code=204)

    return router


async def _start(server: PrintServer, service: PrinterService, user: str | None) -> None:
    """OctoPrint's start: the selected file (or the last job's, to print it again)."""
    path = service.selected
    if path is None and service.finished is not None:
        path = service.data_dir / service.finished.record.file
    if path is None or not path.is_file():
        raise HTTPException(409, f"printer {service.name}: no file is selected")
    _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    start(server, service, path, commands, user, "OctoPrint's job start")
    service.select(None)


async def _restart(server: PrintServer, service: PrinterService, user: str | None) -> None:
    """OctoPrint's restart of a paused job: it is cancelled (its safe stop first), and
    its file goes first in the queue, which runs on (it was asked for)."""
    running = service.running
    assert running is not None
    path = service.data_dir / running.record.file
    await answered(service.control("cancel"))
    _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    # Started as on every face: the hold its cancel left is released, unless every start
    # waits for a release (then 409, with why: the job was cancelled).
    start(server, service, path, commands, user, "OctoPrint's restart", first=True)
