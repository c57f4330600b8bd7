"""OctoPrint's REST API, at ``/api`` (the default printer) and ``/printers/NAME/api``
(each printer, so that a farm tool sees one OctoPrint per printer), as OctoPrint 1.11
answers (``octoprint/server/api/*.py``): the same paths, fields and status codes, and
the same sentences where a client shows them.

Where this server differs on purpose: a print asked for while the printer is busy is
queued, not refused (a queue is what the server is for); commands and heater changes
are refused while a job streams (the session streams the job alone); after a job the
queue is held until the bed is cleared, and a print asked for meanwhile answers 409
with that reason."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse

from repetrel_host.server import uploads
from repetrel_host.server.octoprint import (
    connection,
    files,
    job,
    login,
    printer,
    printer_profiles,
    settings,
    system,
    version,
)
from repetrel_host.server.print_server import server_of

# Its resources, each a module as OctoPrint's (octoprint/server/api/), in OctoPrint's order.
RESOURCES = (version, login, settings, printer_profiles, system, connection, files, job, printer)


def router() -> APIRouter:
    """OctoPrint's ``/api``: the routes of each of its resources."""
    router = APIRouter(prefix="/api")
    for resource in RESOURCES:
        router.include_router(resource.router())
    return router


def downloads() -> APIRouter:
    """``/downloads/files/local/PATH``: an upload's bytes (ranges too, for a resume)."""
    router = APIRouter()

    @router.get("/downloads/files/local/{location:path}")
    async def download(request: Request, location: str) -> FileResponse:
        path = uploads.uploaded(server_of(request), location)
        return FileResponse(path, media_type="text/plain", filename=path.name)

    return router
