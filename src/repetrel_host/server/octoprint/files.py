"""OctoPrint's file API (``/files``): the uploads folder as it shows it, file and folder
entries (``refs``, ``hash``, ``typePath``, ``gcodeAnalysis``, ``prints``); uploads (a
print asked for with one is queued); and its commands (select, copy, move, folders).
OctoPrint 1.11: ``octoprint/server/api/files.py``."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import JSONResponse, Response

from repetrel_host.server import jobs, uploads
from repetrel_host.server.auth import user_of
from repetrel_host.server.folders import copy_or_move, delete_folder, make_folder
from repetrel_host.server.octoprint.common import (
    OctoPrintCommand,
    Printer,
    is_true,
    operational,
    start,
)
from repetrel_host.server.print_server import PrintServer, server_of
from repetrel_host.server.printers.service import Refused
from repetrel_host.server.uploads import G_CODE_SUFFIXES


def resource_url(base: str, location: str) -> str:
    """A file's or folder's resource, its name quoted (letters of any script: a header
    such as Location takes ASCII only)."""
    return f"{base}/api/files/local/{quote(location)}"


def file_entry(server: PrintServer, path: Path, base: str) -> dict[str, Any]:
    """One file's entry (call in a thread: a new file is read for its hash, an analysis
    kept on disk is read)."""
    location = path.relative_to(server.files).as_posix()
    stat = path.stat()
    entry: dict[str, Any] = {
        "name": path.name,
        "display": path.name,
        "path": location,
        "origin": "local",
        "type": "machinecode",
        "typePath": ["machinecode", "gcode"],
        "size": stat.st_size,
        "date": int(stat.st_mtime),
        "hash": uploads.file_hash(path),
        "refs": {
            "resource": resource_url(base, location),
            "download": f"{base}/downloads/files/local/{quote(location)}",
        },
        "prints": server.store.prints(uploads.relative(server, path)),
        "statistics": {"averagePrintTime": {}, "lastPrintTime": {}},
    }
    # Made at its upload; until then (a file put there otherwise) none, as OctoPrint
    # lists a file whose analysis is still queued.
    summary = server.analyses.summary(path)
    if summary is not None:
        entry["gcodeAnalysis"] = summary.gcode_analysis(server.file_pace())
    return entry


def folder_entry(server: PrintServer, path: Path, base: str, depth: int | None) -> dict[str, Any]:
    """A folder's entry, with its children down ``depth`` levels (None: all)."""
    location = path.relative_to(server.files).as_posix()
    entry: dict[str, Any] = {
        "name": path.name,
        "display": path.name,
        "path": location,
        "origin": "local",
        "type": "folder",
        "typePath": ["folder"],
        "refs": {"resource": resource_url(base, location)},
    }
    if depth is None or depth > 0:
        children = entries(server, path, base, None if depth is None else depth - 1)
        entry["children"] = children
        entry["size"] = sum(child.get("size", 0) for child in children)
        success = sum(child.get("prints", {}).get("success", 0) for child in children)
        failure = sum(child.get("prints", {}).get("failure", 0) for child in children)
        entry["prints"] = {"success": success, "failure": failure}
    return entry


def entries(
    server: PrintServer, folder: Path, base: str, depth: int | None
) -> list[dict[str, Any]]:
    """The G-code files and folders in ``folder``, folders first, by name."""
    found: list[dict[str, Any]] = []
    for path in sorted(folder.iterdir(), key=lambda p: (p.is_file(), p.name.lower())):
        if path.name.startswith("."):
            continue  # an upload being written, or the server's own
        if path.is_dir():
            found.append(folder_entry(server, path, base, depth))
        elif path.is_file() and path.name.lower().endswith(G_CODE_SUFFIXES):
            found.append(file_entry(server, path, base))
    return found


def router() -> APIRouter:
    """``/files``: listings, uploads, a file's or folder's entry, commands, removal."""
    router = APIRouter()

    @router.post("/files/local", status_code=201)
    async def upload(
        request: Request,
        service: Printer,
        file: Annotated[UploadFile | None, File()] = None,
        path: Annotated[str, Form()] = "",
        foldername: Annotated[str | None, Form()] = None,
        select: Annotated[str, Form()] = "false",
        print: Annotated[str, Form()] = "false",
    ) -> JSONResponse:
        server = server_of(request)
        base = _base(request)
        if file is None:
            if foldername is None:
                raise HTTPException(400, "No file to upload and no folder to create")
            folder = make_folder(server, path, foldername)
            uploads.file_changed(server, folder, "added", "add", folder=True)
            location = folder.relative_to(server.files).as_posix()
            answer: dict[str, Any] = {
                "folder": {
                    "name": folder.name,
                    "path": location,
                    "origin": "local",
                    "refs": {"resource": resource_url(base, location)},
                },
                "done": True,
            }
            headers = {"Location": answer["folder"]["refs"]["resource"]}
            return JSONResponse(answer, 201, headers=headers)
        to_print, to_select = is_true(print), is_true(select)
        stored = await uploads.save_upload(server, service.name, file, path)
        extra: dict[str, Any] = {"findings": stored.findings}
        if stored.note:
            extra["note"] = stored.note
        if to_print:
            # Queued: it runs when the printer is free (OctoPrint answers 409 when it is
            # busy; a queue is what this server is for). A held queue is released (the
            # server's one rule), unless every start waits for a release: then it is
            # stored (nothing accepted is lost), not printed, and a slicer shows why.
            user = user_of(request)
            via = "OctoPrint's upload and print"
            try:
                record = jobs.start(server, service, stored.path, stored.commands, user, via)
            except Refused as exc:
                name = stored.path.name
                raise HTTPException(409, f"{name} is stored, not printed: {exc}") from None
            extra["job"] = record.as_json()
            service.select(None)
        elif to_select and service.running is None:
            service.select(stored.path)
        location = stored.path.relative_to(server.files).as_posix()
        entry = await asyncio.to_thread(file_entry, server, stored.path, base)
        answer = {
            "files": {
                "local": {
                    "name": entry["name"],
                    "display": entry["display"],
                    "path": location,
                    "origin": "local",
                    "refs": entry["refs"],
                }
            },
            "done": True,
            "effectiveSelect": to_select and service.running is None,
            "effectivePrint": to_print,
            **extra,
        }
        return JSONResponse(answer, 201, headers={"Location": entry["refs"]["resource"]})

    @router.get("/files")
    async def all_files(
        request: Request, recursive: bool = False, force: bool = False
    ) -> dict[str, Any]:
        return await _listing(request, server_of(request).files, recursive)

    @router.get("/files/local")
    async def local_files(request: Request, recursive: bool = False) -> dict[str, Any]:
        return await _listing(request, server_of(request).files, recursive)

    @router.get("/files/sdcard")
    async def sd_files() -> Response:
        raise HTTPException(404, "SD support is disabled: the server prints from its own storage")

    @router.get("/files/local/{location:path}")
    async def file_or_folder(
        request: Request, location: str, recursive: bool = False
    ) -> dict[str, Any]:
        server = server_of(request)
        path = server.files / uploads.safe_folder(location)
        base = _base(request)
        if path.is_dir() and path != server.files:
            depth = None if recursive else 1
            return await asyncio.to_thread(folder_entry, server, path, base, depth)
        return await asyncio.to_thread(file_entry, server, uploads.uploaded(server, location), base)

    @router.post("/files/local/{location:path}")
    async def file_command(
        request: Request, service: Printer, location: str, body: OctoPrintCommand
    ) -> Response:
        server = server_of(request)
        if body.command in ("copy", "move"):
            destination = body.get("destination")
            if not isinstance(destination, str) or not destination:
                raise HTTPException(400, "Mandatory parameter destination missing")
            moving = body.command == "move"
            target = await asyncio.to_thread(copy_or_move, server, location, destination, moving)
            folder = target.is_dir()
            if moving:
                source = server.files / uploads.safe_folder(location)
                uploads.file_moved(server, source, target, folder)
            else:
                uploads.file_changed(server, target, "added", "copy", folder)
            where = target.relative_to(server.files).as_posix()
            resource = resource_url(_base(request), where)
            refs = {"resource": resource}
            if target.is_file():
                refs["download"] = f"{_base(request)}/downloads/files/local/{quote(where)}"
            answer = {"name": target.name, "path": where, "origin": "local", "refs": refs}
            return JSONResponse(answer, 201, headers={"Location": resource})
        if body.command == "select":
            path = uploads.uploaded(server, location)
            if service.running is not None:
                raise HTTPException(409, "Printer is already printing, cannot select a new file")
            if is_true(body.get("print", False)):
                operational(service)
                _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
                start(server, service, path, commands, user_of(request), "OctoPrint's select")
                service.select(None)
            else:
                # Its analysis in memory, for /api/job (read from the data folder, or made).
                await asyncio.to_thread(server.analyses.summary, path)
                service.select(path)
            return Response(status_code=204)
        if body.command == "unselect":
            if service.running is not None:
                raise HTTPException(
                    409, "Printer is already printing, cannot unselect current file"
                )
            if service.selected is None:
                raise HTTPException(
                    409, "Cannot unselect current file when there is no file selected"
                )
            if location != "current" and server.files / location != service.selected:
                raise HTTPException(400, "Only the currently selected file can be unselected")
            service.select(None)
            return Response(status_code=204)
        if body.command in ("slice", "analyse", "uploadSd"):
            raise HTTPException(400, f"{body.command} is not supported by this server")
        raise HTTPException(400, f"command '{body.command}' is not select, unselect, copy or move")

    @router.delete("/files/local/{location:path}", status_code=204)
    async def delete_file(request: Request, location: str) -> Response:
        server = server_of(request)
        path = server.files / uploads.safe_folder(location)
        if path.is_dir() and path != server.files:
            await asyncio.to_thread(delete_folder, server, location)
            uploads.file_changed(server, path, "removed", "remove", folder=True)
        else:
            uploads.delete_upload(server, location)
        return Response(status_code=204)

    return router


def _base(request: Request) -> str:
    """Where this printer's OctoPrint face is, for ``refs`` (``http://host/printers/p2``)."""
    base = str(request.base_url).rstrip("/")
    printer = request.path_params.get("printer")
    return f"{base}/printers/{printer}" if printer else base


async def _listing(request: Request, folder: Path, recursive: bool) -> dict[str, Any]:
    server = server_of(request)
    found = await asyncio.to_thread(
        entries, server, folder, _base(request), None if recursive else 0
    )
    usage = shutil.disk_usage(server.data_dir)
    return {"files": found, "free": usage.free, "total": usage.total}
