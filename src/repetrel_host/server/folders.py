"""Folders and moves below the uploads, as every face of the API makes them: a new folder,
a copy or a move (a file's analysis goes with it), a folder removed; none while a job uses
a file in it."""

from __future__ import annotations

import shutil
from pathlib import Path

from fastapi import HTTPException

from repetrel_host.server import uploads
from repetrel_host.server.analyses import stamp
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.uploads import G_CODE_SUFFIXES


def make_folder(server: PrintServer, parent: str, name: str) -> Path:
    """A new folder below the uploads; 409 when the name is taken or looks like a file."""
    cleaned = uploads.listed_folder(name)
    target = server.files / uploads.listed_folder(parent) / cleaned
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
    target = server.files / uploads.listed_folder(destination)
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
