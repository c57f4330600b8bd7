"""The uploads folder: an upload's safe name and place, written to disk as it comes and
checked for a printer; a file's hash, its entry in a listing, its thumbnail and its layers;
a file deleted. What every face of the API (native, OctoPrint's, a farm's) does with files."""

from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import secrets
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import HTTPException
from starlette.datastructures import UploadFile  # FastAPI's, and a form's as Starlette reads it

import repetrel_host as rh
from repetrel_host.gcode.analysis import Analysis, FileSummary, analyse
from repetrel_host.gcode.layer_moves import layer_moves
from repetrel_host.gcode.thumbnails import ThumbnailError
from repetrel_host.gcode.thumbnails import read as read_thumbnail
from repetrel_host.server.analyses import Stamp, describe, stamp
from repetrel_host.server.events import FileChanged
from repetrel_host.server.print_server import PrintServer
from repetrel_host.session.workers import in_worker

log = logging.getLogger("repetrel_host.server")

G_CODE_SUFFIXES = (".gcode", ".gco", ".g")
# An upload's name: the filesystem takes 255 bytes; room is left for "-2" and its kin.
MAX_NAME = 200
# A file name's bytes (UTF-8): filesystems take 255; room is left for a "-12" after it.
MAX_NAME_BYTES = 240
# Made ``_`` in a name, besides control characters: what Windows takes in no name
# (\\ / : * ? " < > |: a share or a copy to a stick would fail) and what a shell reads as
# its own (; & $, as OctoPrint removes them, and the backquote).
_UNSAFE_MARKS = frozenset('\\/:*?"<>|;&$`')
# Format characters a name keeps: the joiners emoji sequences and some scripts are made of.
_JOINERS = frozenset("\u200c\u200d")
MAX_PATH = 1024
# An upload goes to disk as it comes, this many bytes at a time: one fsync of a gigabyte at
# its end would hold up every other fsync on the disk meanwhile, the store's commits on the
# event loop among them (measured: a SQLite commit waited 110-180 ms behind a 1 GB fsync,
# under 10 ms behind flushes of 16 MB).
FLUSH_EVERY = 16 << 20
_HASHES: dict[tuple[Path, int, int], str] = {}


def upload_name(name: str) -> str:
    """The name an upload was given, without its folders."""
    return name.replace("\\", "/").rsplit("/", 1)[-1].strip()


def _cleaned(name: str) -> str:
    """``name`` in NFC with every character a filesystem holds safely kept (letters of
    any script, emoji, combining marks, punctuation); control and format characters (a
    bidirectional override can disguise a name's end) and :data:`_UNSAFE_MARKS` ``_``."""
    return "".join("_" if _unsafe(c) else c for c in unicodedata.normalize("NFC", name))


def _unsafe(character: str) -> bool:
    if character in _UNSAFE_MARKS:
        return True
    category = unicodedata.category(character)
    # Cc: controls (NUL, line ends); Cs: a lone surrogate (no UTF-8 for it); Zl, Zp: line
    # and paragraph separators; Cf: format characters, but for the joiners.
    return category in ("Cc", "Cs", "Zl", "Zp") or (category == "Cf" and character not in _JOINERS)


def safe_file_name(name: str) -> tuple[str, str]:
    """The upload's own name, without folders, in safe characters (see :func:`_cleaned`),
    without a leading dot, and a note when it was shortened to fit the filesystem (at most
    :data:`MAX_NAME` characters and :data:`MAX_NAME_BYTES` bytes); 400 if nothing is left
    or it is not a G-code file."""
    cleaned = _cleaned(upload_name(name)).lstrip(".")
    if not cleaned or not cleaned.lower().endswith(G_CODE_SUFFIXES):
        raise HTTPException(400, f"'{_shown(name)}' is not a G-code file name (.gcode, .gco, .g)")
    if len(cleaned) <= MAX_NAME and len(cleaned.encode()) <= MAX_NAME_BYTES:
        return cleaned, ""
    stem, dot, suffix = cleaned.rpartition(".")
    stem = stem[: MAX_NAME - len(suffix) - 1]
    while len(f"{stem}.{suffix}".encode()) > MAX_NAME_BYTES:
        stem = stem[:-1]
    short = f"{stem}{dot}{suffix}"
    return short, f"the name was over {MAX_NAME} characters: shortened to {short}"


def _shown(text: str, most: int = 80) -> str:
    """``text`` as an error quotes it: a long one cut, so the sentence stays one line."""
    return text if len(text) <= most else f"{text[: most - 3]}..."


def safe_folder(path: str) -> Path:
    """OctoPrint's ``path`` field: a folder below the uploads; no '..', no absolute path,
    no name too long for the filesystem."""
    parts = [part for part in path.replace("\\", "/").split("/") if part not in ("", ".")]
    if any(part == ".." for part in parts) or path.startswith(("/", "\\")):
        raise HTTPException(400, f"path '{_shown(path)}' leaves the upload folder")
    if len(path) > MAX_PATH or any(len(part) > MAX_NAME + 20 for part in parts):
        raise HTTPException(
            400, f"path '{_shown(path)}' is too long (names of at most {MAX_NAME} characters)"
        )
    return Path(*(_cleaned(part) for part in parts)) if parts else Path()


def listed_folder(path: str) -> Path:
    """:func:`safe_folder` for a place a file or folder is put (an upload, a new folder, a
    move): 400 when a name in it starts with '.' (Moonraker's ``.thumbs``, the server's own
    folders), which every listing hides: what went there would never be seen."""
    folder = safe_folder(path)
    if any(part.startswith(".") for part in folder.parts):
        said = f"'{_shown(path)}' is hidden (a name in it starts with '.'): nothing there is listed"
        raise HTTPException(400, said)
    return folder


@dataclass(frozen=True)
class Upload:
    """A stored upload: where, the lint's findings, its commands, and what became of a
    file of the same name (``note``)."""

    path: Path
    findings: list[str]
    commands: int
    note: str = ""


async def save_upload(
    server: PrintServer, printer: str, upload: UploadFile, folder: str = ""
) -> Upload:
    """Write the upload into the data folder and check it. A file of the same name is
    replaced, as OctoPrint does, unless a queued or running job prints it: then the upload
    gets a new name (``part-2.gcode``). A file with errors is refused (400, with the
    findings), and one of the same name stays as it was."""
    name, shortened = safe_file_name(upload.filename or "")
    target_dir = server.files / listed_folder(folder)
    target_dir.mkdir(parents=True, exist_ok=True)
    # Written beside it under a hidden name first: a failed upload replaces nothing.
    partial = target_dir / f".upload-{secrets.token_hex(8)}.part"
    digest = hashlib.sha1(usedforsecurity=False)
    try:
        await receive(server, upload, partial, digest)
        # Checked in a thread: a big file must not hold the event loop (and every
        # printer's stream) up.
        findings, commands = await asyncio.to_thread(check, server, printer, partial)
        findings = [f.replace(partial.name, name) for f in findings]
        refuse_errors(name, findings)
        # Analysed now, in a thread (OctoPrint's gcodeAnalysis): a listing need not read it.
        summary = await asyncio.to_thread(_analysed, partial)
        made_from = stamp(partial)
        given = upload_name(upload.filename or "")
        target, note = _free_name(server, _own_place(server, target_dir / name, given))
        partial.replace(target)
        server.store.keep_upload_name(relative(server, target), given)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    for service in server.services.values():
        service.renamed(partial, target)
    _HASHES[_stat_key(target)] = digest.hexdigest()
    if summary is not None:
        server.analyses.keep(target, summary, made_from)  # a rename keeps size and time
    file_changed(server, target, "added", "add")
    return Upload(target, findings, commands, "; ".join(filter(None, (shortened, note))))


async def receive(server: PrintServer, upload: UploadFile, partial: Path, digest: Any) -> int:
    """Write ``upload`` to the new file ``partial`` a megabyte at a time, feeding
    ``digest``; on disk (fsync) before the client hears it is there. Its size; 413 past
    the server's largest upload (the caller removes ``partial``)."""
    size = unflushed = 0
    with partial.open("xb") as out:
        while chunk := await upload.read(1 << 20):
            size += len(chunk)
            if size > server.max_upload:
                raise HTTPException(413, f"the upload is over {server.max_upload} bytes")
            out.write(chunk)
            digest.update(chunk)
            unflushed += len(chunk)
            if unflushed >= FLUSH_EVERY:
                out.flush()
                await asyncio.to_thread(os.fdatasync, out.fileno())
                unflushed = 0
        out.flush()
        await asyncio.to_thread(os.fsync, out.fileno())
    return size


def _analysed(path: Path) -> FileSummary | None:
    """The upload's analysis; None (and logged) when it fails: the upload is kept."""
    try:
        return in_worker(analyse, path).summary
    except Exception:
        log.exception("the analysis of the upload %s failed", path.name)
        return None


def _stat_key(path: Path) -> tuple[Path, int, int]:
    stat = path.stat()
    return path, stat.st_size, stat.st_mtime_ns


def file_hash(path: Path) -> str:
    """The file's SHA-1 (OctoPrint's ``hash``), remembered while the file is unchanged;
    an upload's is computed as it is written."""
    key = _stat_key(path)
    known = _HASHES.get(key)
    if known is None:
        digest = hashlib.sha1(usedforsecurity=False)
        with path.open("rb") as handle:
            while chunk := handle.read(1 << 20):
                digest.update(chunk)
        known = _HASHES[key] = digest.hexdigest()
    return known


def _own_place(server: PrintServer, target: Path, given: str) -> Path:
    """Where an upload first named ``given`` goes: its cleaned name ``target``, unless a
    file there came under another name (two names that clean or shorten alike): then
    ``-1``, ``-2``... after the stem, as OctoPrint does. The same name replaces."""
    stem, suffix = target.stem, target.suffix
    chosen, number = target, 0
    while chosen.exists():
        came_as = server.store.upload_name(relative(server, chosen)) or chosen.name
        if came_as == given:
            break
        number += 1
        chosen = target.with_name(f"{stem}-{number}{suffix}")
    return chosen


def _free_name(server: PrintServer, target: Path) -> tuple[Path, str]:
    """Where an upload named ``target`` goes: there, unless a job uses the file there."""
    users = server.store.jobs_using(relative(server, target)) if target.exists() else []
    if not users:
        return target, f"replaced the earlier {target.name}" if target.exists() else ""
    stem, suffix = target.stem, target.suffix
    number = 1
    chosen = target
    while chosen.exists():
        number += 1
        chosen = target.with_name(f"{stem}-{number}{suffix}")
    jobs = ", ".join(map(str, users))
    return chosen, f"{target.name} is used by job {jobs}: stored as {chosen.name}"


def relative(server: PrintServer, path: Path) -> str:
    return path.relative_to(server.data_dir).as_posix()


def uploaded(server: PrintServer, location: str) -> Path:
    """An uploaded file by its place below the uploads; 404 when there is none."""
    path = server.files / safe_folder(location)
    if not path.is_file():
        raise HTTPException(404, f"no file '{location}'")
    return path


def delete_upload(server: PrintServer, location: str) -> None:
    """Remove an uploaded file; 409 while a queued or running job prints it."""
    path = uploaded(server, location)
    users = server.store.jobs_using(relative(server, path))
    if users:
        jobs = ", ".join(str(job) for job in users)
        raise HTTPException(409, f"'{location}' is used by job {jobs}: cancel it first")
    path.unlink()
    server.analyses.forget(path)
    for service in server.services.values():
        service.forget(path)
        if service.selected == path:
            service.selected = None
    log.info("file %s deleted", location)
    file_changed(server, path, "removed", "remove")


def file_changed(
    server: PrintServer, path: Path, what: str, operation: str, folder: bool = False
) -> None:
    """An upload (or a folder: ``folder``) was ``added`` or ``removed`` by ``operation``
    (add, copy, move, remove): on the server's events (OctoPrint's FileAdded...)."""
    where = path.relative_to(server.files).as_posix()
    server.events.publish(FileChanged(what, where, path.name, folder, operation))


def file_moved(server: PrintServer, source: Path, target: Path, folder: bool = False) -> None:
    """An upload (or a folder: ``folder``) moved from ``source`` to ``target``: one event
    with both places, so each face tells the move its own way (Moonraker's ``move_file``
    with its ``source_item``, OctoPrint's FileRemoved, FileAdded and FileMoved)."""
    where, came_from = (p.relative_to(server.files).as_posix() for p in (target, source))
    server.events.publish(FileChanged("moved", where, target.name, folder, "move", came_from))


def refuse_errors(name: str, findings: list[str]) -> None:
    """400 with the job lint's ``findings`` when they hold errors: file ``name`` is refused."""
    errors = [f for f in findings if f.startswith("error")]
    if errors:
        raise HTTPException(
            400, {"error": f"{name}: refused ({len(errors)} errors)", "findings": findings}
        )


def check(server: PrintServer, printer: str, path: Path) -> tuple[list[str], int]:
    """The job lint's findings (``error: file:line: ...``) and the number of lines to send."""
    try:
        _, findings, commands = server.services[printer].check(path)
    except rh.HostError as exc:  # named by the file's name, not its place on the server
        return [f"error: {str(exc).replace(str(path), path.name)}"], 0
    return [f"{f.severity}: {path.name}:{f.line}: {f.message}" for f in findings], commands


def file_json(server: PrintServer, path: Path) -> dict[str, Any]:
    """A file of the native listing, with its analysis (None until it is made: a file
    that was not uploaded is analysed in the background)."""
    summary = None
    if path.name.lower().endswith(G_CODE_SUFFIXES) and not path.name.startswith("."):
        summary = server.analyses.summary(path)
    where = path.relative_to(server.files).as_posix()
    largest = summary.largest_thumbnail() if summary is not None else None
    return {
        "name": path.name,
        "display": path.name,
        "path": where,
        "origin": "local",
        "type": "machinecode",
        "size": path.stat().st_size,
        "date": int(path.stat().st_mtime),
        "analysis": describe(summary, server.file_pace()),
        # The slicer's largest preview, as PNG or JPEG (a QOI one made PNG).
        "thumbnail": f"/v1/files/{quote(where)}/thumbnail" if largest is not None else None,
    }


def thumbnail(server: PrintServer, location: str) -> tuple[bytes, str]:
    """The largest image the slicer embedded in an uploaded file, and its media type
    (call in a thread: it may analyse the file); 404 when it has none."""
    path = uploaded(server, location)
    summary = server.analyses.cached(path) or server.analyses.analyse(path).summary
    largest = summary.largest_thumbnail() if summary is not None else None
    if largest is None:
        raise HTTPException(404, f"'{location}' has no thumbnail (its slicer embedded none)")
    try:
        return read_thumbnail(path, largest)
    except ThumbnailError as exc:
        raise HTTPException(422, f"'{location}': {exc}") from None


def uploads_json(server: PrintServer) -> list[dict[str, Any]]:
    """The native listing (call in a thread: it reads the analyses kept on disk)."""
    return [file_json(server, p) for p in sorted(server.files.rglob("*")) if p.is_file()]


_LAYERS: dict[Path, tuple[Stamp, Analysis]] = {}  # a file's layers, while it is unchanged


def layer_json(
    server: PrintServer, location: str, number: int, moves: bool = True
) -> dict[str, Any]:
    """Layer ``number`` of an uploaded file, for the layer view (in a thread); without its
    moves (None, not read) unless ``moves``."""
    path = uploaded(server, location)
    now = stamp(path)
    known = _LAYERS.get(path)
    if known is None or known[0] != now:
        if len(_LAYERS) > 64:
            _LAYERS.clear()
        known = _LAYERS[path] = (now, analyse(path, moves=False))
    found = known[1]
    layers, offsets = found.marks.layers, found.layer_offsets
    if number > len(layers):
        raise HTTPException(
            404, f"'{location}' has {len(layers)} layers: there is no layer {number}"
        )
    layer = layers[number - 1]
    end = offsets[number] if number < len(offsets) else None
    drawn: list[list[float]] | None = None  # not read when the moves are not asked for
    if moves:
        drawn = [
            [line, round(x0, 3), round(y0, 3), round(x1, 3), round(y1, 3), int(extrudes)]
            for line, x0, y0, x1, y1, extrudes in layer_moves(
                path, offsets[number - 1], end, layer.line
            )
        ]
    summary = server.analyses.cached(path)
    area = summary.as_json().get("printingArea") if summary is not None else None
    return {
        "file": location,
        "layer": number,
        "layers": len(layers),
        "z": layer.z,
        "first_line": layer.line,
        "last_line": layers[number].line - 1 if number < len(layers) else None,
        "area": area,
        "moves": drawn,
    }
