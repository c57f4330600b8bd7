"""The uploads folder as OctoPrint's file API shows it: file and folder entries (``refs``,
``hash``, ``typePath``, ``gcodeAnalysis``, ``prints``), and its commands (copy, move,
folders). OctoPrint 1.11: ``octoprint/server/api/files.py``."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import HTTPException

from repetrel_host.server import uploads
from repetrel_host.server.analyses import stamp
from repetrel_host.server.print_server import PrintServer
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
        entry["gcodeAnalysis"] = summary.gcode_analysis()
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


def make_folder(server: PrintServer, parent: str, name: str) -> Path:
    """A new folder below the uploads; 409 when the name is taken or looks like a file."""
    cleaned = uploads.safe_folder(name)
    target = server.files / uploads.safe_folder(parent) / cleaned
    if not cleaned.parts:
        raise HTTPException(400, "the folder name is empty")
    if target.name.lower().endswith(G_CODE_SUFFIXES):
        raise HTTPException(409, f"'{name}' is a file name: give the folder another one")
    if target.exists():
        raise HTTPException(409, f"'{target.relative_to(server.files).as_posix()}' exists")
    target.mkdir(parents=True)
    return target


def in_use(server: PrintServer, path: Path) -> list[int]:
    """Jobs queued, printing or paused on ``path`` or (a folder) on a file below it."""
    if path.is_file():
        return server.store.jobs_using(uploads.relative(server, path))
    users: list[int] = []
    for child in path.rglob("*"):
        if child.is_file():
            users += server.store.jobs_using(uploads.relative(server, child))
    return users


def copy_or_move(server: PrintServer, location: str, destination: str, move: bool) -> Path:
    """OctoPrint's copy and move: ``destination`` is a new path, or an existing folder
    to put it in under its own name. 409 when the target exists or (a move) it is in use."""
    source = server.files / uploads.safe_folder(location)
    if not source.exists() or source == server.files:
        raise HTTPException(404, f"no file or folder '{location}'")
    target = server.files / uploads.safe_folder(destination)
    if target.is_dir() and target != source:
        target = target / source.name
    if target.exists():
        raise HTTPException(409, f"'{target.relative_to(server.files).as_posix()}' exists")
    if source.is_file() and not target.name.lower().endswith(G_CODE_SUFFIXES):
        raise HTTPException(415, f"'{destination}' is not a G-code file name")
    if source.is_dir() and target.is_relative_to(source):
        raise HTTPException(400, f"'{location}' cannot go inside itself")
    if move:
        users = in_use(server, source)
        if users:
            jobs = ", ".join(map(str, users))
            raise HTTPException(409, f"'{location}' is used by job {jobs}: it cannot move")
    target.parent.mkdir(parents=True, exist_ok=True)
    # A file's analysis goes with it (a copy keeps its time: the analysis holds for it).
    summary = server.analyses.cached(source) if source.is_file() else None
    if move:
        source.rename(target)
        server.analyses.forget(source)
        for service in server.services.values():
            service.forget(source)
            if service.selected is not None and service.selected.is_relative_to(source):
                service.select(None)
    elif source.is_dir():
        shutil.copytree(source, target)
    else:
        shutil.copy2(source, target)
    if summary is not None:
        server.analyses.keep(target, summary, stamp(target))
    return target


def delete_folder(server: PrintServer, location: str) -> None:
    """Remove a folder and what is in it; 409 while a job uses a file in it."""
    path = server.files / uploads.safe_folder(location)
    users = in_use(server, path)
    if users:
        jobs = ", ".join(map(str, users))
        raise HTTPException(409, f"'{location}' holds a file used by job {jobs}: cancel it first")
    shutil.rmtree(path)
