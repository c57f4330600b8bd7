"""Moonraker's file manager over the server's uploads: its one root, ``gcodes``, is the
uploads folder. Listings, a file's metadata (from the server's analysis: the slicer, layers,
filament, thumbnails, and the print time from the moves), folders, moves and copies, uploads
(checked for the printer as on every face; ``print=true`` starts it) and downloads, and
``notify_filelist_changed`` from the server's file events."""

from __future__ import annotations

import asyncio
import shutil
import uuid
from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import HTTPException
from fastapi.responses import FileResponse, JSONResponse, Response
from starlette.datastructures import UploadFile

from repetrel_host.gcode.analysis import FileSummary
from repetrel_host.gcode.thumbnails import Thumbnail, ThumbnailError
from repetrel_host.gcode.thumbnails import read as read_thumbnail
from repetrel_host.server import folders, jobs, uploads
from repetrel_host.server.events import FileChanged, ServerEvent
from repetrel_host.server.moonraker.face import MoonrakerFace
from repetrel_host.server.moonraker.objects import busy
from repetrel_host.server.moonraker.printer import start_print
from repetrel_host.server.moonraker.rpc import Call, RpcError, method
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.uploads import G_CODE_SUFFIXES

ROOT = "gcodes"
THUMBS = ".thumbs"  # where Moonraker keeps a file's previews, beside it
_EXTENSIONS = {"PNG": "png", "JPG": "jpg", "QOI": "png"}  # a QOI preview is served as PNG


def _path(server: PrintServer, given: str, root_first: bool = True) -> tuple[Path, str]:
    """A path of the gcodes root (``gcodes/a/b.gcode``, or ``a/b.gcode`` without
    ``root_first``), and its place below the uploads; 400 for another root."""
    location = given.strip("/")
    if root_first:
        root, _, location = location.partition("/")
        if root != ROOT:
            raise RpcError(400, f"Invalid root: {root or given!r}: this server has 'gcodes' only")
    try:
        return server.files / uploads.safe_folder(location), location
    except HTTPException as exc:
        raise RpcError(400, str(exc.detail)) from None


def _item(server: PrintServer, path: Path) -> dict[str, Any]:
    """A file's or folder's item: one that is gone has no time, size or permissions, as
    Moonraker tells a deleted one."""
    where = path.relative_to(server.files).as_posix()
    try:
        stat = path.stat()
    except OSError:
        return {"path": where, "modified": 0, "size": 0, "permissions": ""}
    return {"path": where, "modified": stat.st_mtime, "size": stat.st_size, "permissions": "rw"}


def _gcode(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(G_CODE_SUFFIXES)


def _visible(server: PrintServer, path: Path) -> bool:
    """Not an upload being written, nor the server's own (a leading dot on the way)."""
    return not any(part.startswith(".") for part in path.relative_to(server.files).parts)


@method("/server/files/roots")
async def roots(call: Call) -> list[dict[str, str]]:
    return [{"name": ROOT, "path": str(call.server.files), "permissions": "rw"}]


@method("/server/files/list")
async def file_list(call: Call) -> list[dict[str, Any]]:
    root = call.string("root", ROOT)
    if root != ROOT:
        raise RpcError(400, f"Invalid root: {root!r}: this server has 'gcodes' only")
    server = call.server

    def listing() -> list[dict[str, Any]]:
        found = sorted(p for p in server.files.rglob("*") if _gcode(p) and _visible(server, p))
        return [_item(server, p) for p in found]

    return await asyncio.to_thread(listing)


@method("/server/files/metadata")
async def metadata(call: Call) -> dict[str, Any]:
    filename = call.string("filename")
    path, location = _path(call.server, filename, root_first=False)
    if not _gcode(path):
        raise RpcError(404, f"Metadata not available for {filename}")
    summary = await asyncio.to_thread(call.server.analyses.summary, path)
    return file_metadata(path, location, summary, call.service.pace())


def file_metadata(
    path: Path, location: str, summary: FileSummary | None, pace: float = 1.0
) -> dict[str, Any]:
    """Moonraker's metadata of a file: what the server's analysis knows of it (keys it
    cannot tell are left out, as Moonraker leaves them out); its ``estimated_time`` the
    plan at ``pace`` (the printer's), else the slicer's figure."""
    stat = path.stat()
    found: dict[str, Any] = {
        "size": stat.st_size,
        "modified": stat.st_mtime,
        "uuid": str(uuid.uuid5(uuid.NAMESPACE_URL, f"{location}@{stat.st_mtime_ns}")),
        "file_processors": [],
        "gcode_start_byte": 0,
        "gcode_end_byte": stat.st_size,
        "print_start_time": None,
        "job_id": None,
        "filename": location,
    }
    if summary is None:
        return found
    slicer, _, version = (summary.slicer or "Unknown").partition(" ")
    found.update(slicer=slicer, slicer_version=version or "?")
    planned = summary.planned
    estimate = planned.total(pace) if planned is not None else summary.slicer_seconds
    if estimate is not None:
        found["estimated_time"] = round(estimate, 1)
    if summary.layers:
        found["layer_count"] = summary.layers
    if summary.printing_area is not None:
        found["object_height"] = summary.printing_area.max_z
    if summary.filament:
        found["filament_total"] = round(sum(f.length for f in summary.filament.values()), 2)
    stem = Path(location).stem
    found["thumbnails"] = [
        {
            "width": thumbnail.width,
            "height": thumbnail.height,
            # The image's bytes, near enough: its base64 lines' length, less a quarter.
            "size": (thumbnail.end - thumbnail.start) * 3 // 4,
            "relative_path": f"{THUMBS}/{_thumbnail_name(stem, thumbnail)}",
        }
        for thumbnail in summary.thumbnails
    ]
    return found


def _thumbnail_name(stem: str, thumbnail: Thumbnail) -> str:
    return f"{stem}-{thumbnail.width}x{thumbnail.height}.{_EXTENSIONS.get(thumbnail.format, 'png')}"


@method("/server/files/gcodes/", "GET", name="server.files.get_file", websocket=False)
async def download(call: Call) -> Response:
    """A file's bytes, or one of its previews (``DIR/.thumbs/NAME-WxH.png``)."""
    path, location = _path(call.server, call.string("path"))
    if path.parent.name == THUMBS:
        return await asyncio.to_thread(_preview, call.server, path)
    if not path.is_file() or not _visible(call.server, path):
        raise RpcError(404, f"File does not exist: {location}")
    return FileResponse(path, filename=path.name)


def _preview(server: PrintServer, wanted: Path) -> Response:
    """The preview ``wanted`` names, read from its G-code file beside ``.thumbs``."""
    folder = wanted.parent.parent
    if not folder.is_dir():  # a folder that is not there has no previews either
        raise RpcError(404, f"File does not exist: {wanted.name}")
    for gcode in folder.iterdir():
        if not _gcode(gcode) or not wanted.name.startswith(f"{gcode.stem}-"):
            continue
        summary = server.analyses.cached(gcode)
        for thumbnail in summary.thumbnails if summary is not None else ():
            if _thumbnail_name(gcode.stem, thumbnail) == wanted.name:
                try:
                    image, media = read_thumbnail(gcode, thumbnail)
                except (OSError, ThumbnailError) as exc:
                    raise RpcError(422, f"{wanted.name}: {exc}") from None
                return Response(image, media_type=media)
    raise RpcError(404, f"File does not exist: {wanted.name}")


@method("/server/files/gcodes/", "DELETE", name="server.files.delete_file")
async def delete_file(call: Call) -> dict[str, Any]:
    server = call.server
    path, location = _path(server, call.string("path"))
    if not _gcode(path):
        raise RpcError(404, f"File does not exist: {location}")
    item = {**_item(server, path), "root": ROOT}
    uploads.delete_upload(server, location)
    return {"item": item, "action": "delete_file"}


@method("/server/files/directory", "GET", name="server.files.get_directory")
async def get_directory(call: Call) -> dict[str, Any]:
    server = call.server
    path, location = _path(server, call.string("path", ROOT))
    if not path.is_dir():
        raise RpcError(404, f"Directory does not exist ({location})")
    extended = call.flag("extended")
    pace = call.service.pace()

    def listing() -> dict[str, Any]:
        dirs, files = [], []
        for child in sorted(path.iterdir()):
            if child.name.startswith("."):
                continue
            stat = child.stat()
            if child.is_dir():
                size = sum(p.stat().st_size for p in child.rglob("*") if p.is_file())
                dirs.append(
                    {
                        "dirname": child.name,
                        "modified": stat.st_mtime,
                        "size": size,
                        "permissions": "rw",
                    }
                )
            elif _gcode(child):
                found = {
                    "filename": child.name,
                    "modified": stat.st_mtime,
                    "size": stat.st_size,
                    "permissions": "rw",
                }
                if extended:
                    found = {**_listed_metadata(server, child, pace), **found}
                files.append(found)
        usage = shutil.disk_usage(server.files)
        return {
            "dirs": dirs,
            "files": files,
            "disk_usage": {"total": usage.total, "used": usage.used, "free": usage.free},
            "root_info": {"name": ROOT, "permissions": "rw"},
        }

    return await asyncio.to_thread(listing)


def _listed_metadata(server: PrintServer, path: Path, pace: float) -> dict[str, Any]:
    """A listed file's metadata (``extended=true``), as ``server.files.metadata`` gives it
    but for its ``filename``, which stays the listing's; from the analysis kept on disk,
    one not made yet is made in the background (Moonraker lists a file it has not parsed
    without metadata too)."""
    location = path.relative_to(server.files).as_posix()
    return file_metadata(path, location, server.analyses.summary(path), pace)


@method("/server/files/directory", "POST", name="server.files.post_directory")
async def post_directory(call: Call) -> dict[str, Any]:
    server = call.server
    _, location = _path(server, call.string("path"))
    parent, _, name = location.rpartition("/")
    made = folders.make_folder(server, parent, name)
    uploads.file_changed(server, made, "added", "add", folder=True)
    return {"item": _folder_item(server, made), "action": "create_dir"}


@method("/server/files/directory", "DELETE", name="server.files.delete_directory")
async def delete_directory(call: Call) -> dict[str, Any]:
    server = call.server
    path, location = _path(server, call.string("path"))
    if not path.is_dir() or path == server.files:
        raise RpcError(404, f"Directory does not exist ({location})")
    if any(path.iterdir()) and not call.flag("force"):
        raise RpcError(400, f"Directory {location} is not empty: force=true removes it")
    item = _folder_item(server, path)
    await asyncio.to_thread(folders.delete_folder, server, location)
    uploads.file_changed(server, path, "removed", "remove", folder=True)
    return {"item": item, "action": "delete_dir"}


def _folder_item(server: PrintServer, path: Path) -> dict[str, Any]:
    return {
        "path": path.relative_to(server.files).as_posix(),
        "root": ROOT,
        "modified": path.stat().st_mtime if path.exists() else 0.0,
        "size": 0,
        "permissions": "rw",
    }


async def _move_or_copy(call: Call, move: bool) -> dict[str, Any]:
    server = call.server
    from_path, source = _path(server, call.string("source"))
    _, dest = _path(server, call.string("dest"))
    target = await asyncio.to_thread(folders.copy_or_move, server, source, dest, move)
    what = "dir" if target.is_dir() else "file"
    if move:
        uploads.file_moved(server, from_path, target, target.is_dir())
    else:
        uploads.file_changed(server, target, "added", "copy", target.is_dir())
    item = (
        {**_item(server, target), "root": ROOT} if what == "file" else _folder_item(server, target)
    )
    answer = {"item": item, "action": f"{'move' if move else 'create'}_{what}"}
    if move:
        answer["source_item"] = {"path": source, "root": ROOT}
    return answer


@method("/server/files/move", "POST")
async def move(call: Call) -> dict[str, Any]:
    return await _move_or_copy(call, move=True)


@method("/server/files/copy", "POST")
async def copy(call: Call) -> dict[str, Any]:
    return await _move_or_copy(call, move=False)


@method("/server/files/upload", "POST", websocket=False)
async def upload(call: Call) -> Response:
    """An upload (a form's ``file``, ``root``, ``path``, ``print``): checked for this
    printer, stored, and with ``print=true`` started; 201 with the item itself, not
    wrapped, and where it is (``Location``), as Moonraker answers."""
    file = call.get("file")
    if not isinstance(file, UploadFile):
        raise RpcError(400, "No file to upload: send it as the form's 'file'")
    root = call.string("root", ROOT)
    if root != ROOT:
        raise RpcError(400, f"Invalid root: {root!r}: this server has 'gcodes' only")
    folder = call.string("path", "")
    service = call.service
    stored = await uploads.save_upload(call.server, service.name, file, folder)
    location = stored.path.relative_to(call.server.files).as_posix()
    started = queued = False
    if call.flag("print"):
        if busy(service):
            # Busy: queued to run after the job (Moonraker with queue_gcode_uploads; the
            # OctoPrint face queues it too). 201 still: the upload is done, and a client's
            # retry would store it again. A file the job prints is never replaced: the
            # upload got another name (NAME-2), the item tells it.
            jobs.queue(call.server, service.name, stored.path, stored.commands, call.user)
            queued = True
        else:
            await start_print(call, location, "upload with print=true")
            started = True
    answer = {
        "item": {**_item(call.server, stored.path), "root": ROOT},
        "action": "create_file",  # over a file of the same name too, as Moonraker says
        "print_started": started,
        "print_queued": queued,
    }
    where = f"{call.base_url}server/files/{ROOT}/{quote(location)}"
    return JSONResponse(answer, 201, headers={"Location": where})


def tell_file_changes(face: MoonrakerFace) -> None:
    """``notify_filelist_changed`` for each file event of the server, to every websocket."""

    def heard(event: ServerEvent) -> None:
        if not isinstance(event, FileChanged):
            return
        kind = "dir" if event.folder else "file"
        verb = {"added": "create", "removed": "delete", "moved": "move"}.get(event.what)
        if verb is None:  # an analysis made: Moonraker tells a file once, when it is parsed
            return
        told: dict[str, Any] = {
            "action": f"{verb}_{kind}",
            "item": {**_item(face.server, face.server.files / event.path), "root": ROOT},
        }
        if event.source is not None:  # a move: where it was (file_manager's source_item)
            told["source_item"] = {"path": event.source, "root": ROOT}
        face.notify(None, "notify_filelist_changed", [told])

    face.listeners.append(heard)
