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

import asyncio
import contextlib
import re
import secrets
import shutil
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel

import repetrel_host as rh
from repetrel_host.server import jobs, uploads
from repetrel_host.server.access import GROUPS, PERMISSIONS
from repetrel_host.server.auth import CSRF_COOKIE, SESSION_COOKIE, session_of, user_of
from repetrel_host.server.octoprint import files, model
from repetrel_host.server.print_server import PrintServer, answered, server_of
from repetrel_host.server.printers.service import PrinterService

# What /api/version says: PrusaSlicer checks that "text" starts with "OctoPrint".
OCTOPRINT_VERSION = "1.11.8"
API_VERSION = "0.1"
_TOOL = re.compile(r"tool(\d+)")
_TOOL_OR_CURRENT = re.compile(r"tool(\d*)")
_TRUE = ("true", "1", "yes", "y")
NOT_OPERATIONAL = "Printer is not operational"
_AXIS_SPEEDS = {"x": 6000, "y": 6000, "z": 200, "e": 300}  # mm/min, the printer profile's


class Command(BaseModel):
    """OctoPrint's command bodies: ``{"command": ..., ...}`` with the command's fields."""

    model_config = {"extra": "allow"}
    command: str

    def get(self, name: str, default: Any = None) -> Any:
        return (self.model_extra or {}).get(name, default)


class PrinterCommand(BaseModel):
    command: str | None = None
    commands: list[str] | None = None
    script: str | None = None


def _user_json(user: str, session: str) -> dict[str, Any]:
    """The user a login answers with (OctoPrint's ``SessionUser.as_dict``)."""
    return {
        "name": user,
        "active": True,
        "permissions": PERMISSIONS,
        "groups": list(GROUPS),
        "needs": {"role": [p.lower() for p in PERMISSIONS], "group": list(GROUPS)},
        "apikey": None,
        "settings": {},
        "has_password": False,
        "session": session,
        "_is_external_client": False,
        "_login_mechanism": "apikey",
        "_credentials_seen": False,
        "_credentials_recheck_supported": False,
    }


def _guest() -> dict[str, Any]:
    """Nobody logged in (OctoPrint's anonymous user)."""
    return {"name": None, "groups": ["guests"], "permissions": [], "needs": {"group": ["guests"]}}


def _true(value: object) -> bool:
    return value is True or str(value).strip().lower() in _TRUE


def _service_for(request: Request) -> PrinterService:
    """The printer in the path (``/printers/NAME/api/...``), else the default one."""
    return server_of(request).service(request.path_params.get("printer"))


Printer = Annotated[PrinterService, Depends(_service_for)]


def _base(request: Request) -> str:
    """Where this printer's OctoPrint face is, for ``refs`` (``http://host/printers/p2``)."""
    base = str(request.base_url).rstrip("/")
    printer = request.path_params.get("printer")
    return f"{base}/printers/{printer}" if printer else base


def _operational(service: PrinterService) -> str:
    text = model.state_text(service)
    if not model.flags(service, text)["operational"]:
        raise HTTPException(409, NOT_OPERATIONAL)
    return text


def _not_printing(service: PrinterService, what: str) -> None:
    """409 while a job streams (paused, the printer takes commands)."""
    if model.flags(service, _operational(service))["printing"]:
        raise HTTPException(409, what)


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise HTTPException(400, f"{what} is invalid")
    return float(value)


def _tool_index(service: PrinterService, key: str, pattern: re.Pattern[str], what: str) -> int:
    match = pattern.fullmatch(key) if isinstance(key, str) else None
    if match is None:
        raise HTTPException(400, f"{what} contains invalid tool")
    index = int(match[1] or 0)
    if index >= model.tool_count(service):
        tools = model.tool_count(service)
        raise HTTPException(409, f"printer {service.name} has no {key} (it has {tools})")
    return index


async def _send(service: PrinterService, commands: list[str]) -> None:
    """Commands to a printer not streaming a job, each after the last one ran; after a
    heater's new target, M105, so that the next read shows it."""
    for command in commands:
        await answered(service.command(command))
    if any(command.startswith(("M104", "M140", "M141")) for command in commands):
        await answered(service.command("M105"))


def _rate(factor: object) -> int:
    """OctoPrint's feed and flow factor: a percentage (an int) or a fraction (a float)."""
    value = _number(factor, "factor")
    percent = int(value * 100) if isinstance(factor, float) else int(value)
    if percent < 1:
        raise HTTPException(400, "factor is invalid")
    return percent


def _format(value: float) -> str:
    return f"{value:g}"


def router() -> APIRouter:
    router = APIRouter(prefix="/api")

    # --- the server -------------------------------------------------------------

    @router.get("/version")
    async def version() -> dict[str, str]:
        return {
            "api": API_VERSION,
            "server": OCTOPRINT_VERSION,
            "text": f"OctoPrint {OCTOPRINT_VERSION} (repetrel-host {rh.__version__})",
        }

    @router.get("/server")
    async def server_info() -> dict[str, Any]:
        return {"version": OCTOPRINT_VERSION, "safemode": None, "online": True}

    @router.post("/login")
    async def login(request: Request) -> JSONResponse:
        """OctoPrint's login: ``passive`` with a key (or the session's cookie) answers as
        the key's user, with a session for the push socket and a cookie."""
        data: Any = None
        if request.headers.get("content-type", "").startswith("application/json"):
            with contextlib.suppress(ValueError):
                data = await request.json()
        else:
            data = dict(await request.form())
        if not isinstance(data, dict):
            data = {}
        if "user" in data and "pass" in data:
            raise HTTPException(403, "the server has no passwords: log in passively with its key")
        if "passive" not in data:
            raise HTTPException(400, "Neither user and pass attributes nor passive flag present")
        user = user_of(request)
        if user is None:
            return JSONResponse(_guest())
        access = server_of(request).access
        session = session_of(request) or access.login(user)
        answer = JSONResponse(_user_json(user, session))
        answer.set_cookie(SESSION_COOKIE, session, httponly=True, samesite="lax")
        answer.set_cookie(CSRF_COOKIE, secrets.token_hex(16), samesite="strict")
        return answer

    @router.post("/logout")
    async def logout(request: Request) -> JSONResponse:
        session = session_of(request)
        if session is not None:
            server_of(request).access.logout(session)
        answer = JSONResponse(_guest())
        answer.delete_cookie(SESSION_COOKIE)
        return answer

    @router.get("/currentuser")
    async def current_user(request: Request) -> dict[str, Any]:
        user = user_of(request)
        if user is None:
            return {"name": None, "permissions": [], "groups": ["guests"]}
        return {"name": user, "permissions": PERMISSIONS, "groups": list(GROUPS)}

    @router.get("/settings")
    async def settings(request: Request, service: Printer) -> dict[str, Any]:
        return _settings(request, server_of(request), service)

    @router.post("/settings")
    async def change_settings(request: Request, service: Printer) -> dict[str, Any]:
        # The server's settings live in its TOML file: nothing here changes them.
        return _settings(request, server_of(request), service)

    @router.get("/printerprofiles")
    async def printer_profiles(request: Request, service: Printer) -> dict[str, Any]:
        profile = _profile(service)
        return {"profiles": {profile["id"]: profile}}

    @router.get("/printerprofiles/{identifier}")
    async def printer_profile(service: Printer, identifier: str) -> dict[str, Any]:
        profile = _profile(service)
        if identifier not in (profile["id"], "_default"):
            raise HTTPException(404, f"no printer profile '{identifier}'")
        return profile

    @router.get("/system/commands")
    async def system_commands() -> dict[str, list[Any]]:
        return {"core": [], "custom": []}

    @router.get("/system/commands/{source}")
    async def system_commands_of(source: str) -> list[Any]:
        if source not in ("core", "custom"):
            raise HTTPException(404, f"no system command source '{source}'")
        return []

    @router.post("/system/commands/{source}/{action}")
    async def system_command(source: str, action: str) -> Response:
        raise HTTPException(404, f"no system command {source}/{action} (the server runs none)")

    # --- connection ------------------------------------------------------------------

    @router.get("/connection")
    async def connection(service: Printer) -> dict[str, Any]:
        printer = service.printer
        baud = printer.settings.baud if printer is not None else None
        profile = _profile(service)["id"]
        return {
            "current": {
                "state": model.state_text(service),
                "port": service.port,
                "baudrate": baud,
                "printerProfile": profile,
            },
            "options": {
                "ports": [service.port],
                "baudrates": [baud] if baud else [],
                "printerProfiles": [{"id": profile, "name": service.name}],
                "portPreference": service.port,
                "baudratePreference": baud,
                "printerProfilePreference": profile,
                "autoconnect": True,
            },
        }

    @router.post("/connection", status_code=204)
    async def connection_command(service: Printer, body: Command) -> Response:
        if body.command == "connect":
            service.connect()
        elif body.command == "disconnect":
            await answered(service.disconnect())
        elif body.command == "fake_ack":
            pass  # the session never waits for an ok it lost (it asks again)
        else:
            raise HTTPException(400, f"command '{body.command}' is not connect or disconnect")
        return Response(status_code=204)

    # --- files -----------------------------------------------------------------------

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
            folder = files.make_folder(server, path, foldername)
            uploads.file_changed(server, folder, "added", "add", folder=True)
            location = folder.relative_to(server.files).as_posix()
            answer: dict[str, Any] = {
                "folder": {
                    "name": folder.name,
                    "path": location,
                    "origin": "local",
                    "refs": {"resource": files.resource_url(base, location)},
                },
                "done": True,
            }
            headers = {"Location": answer["folder"]["refs"]["resource"]}
            return JSONResponse(answer, 201, headers=headers)
        to_print, to_select = _true(print), _true(select)
        stored = await uploads.save_upload(server, service.name, file, path)
        if to_print and service.held:
            # Stored (nothing accepted is lost), but not printed: a slicer shows the reason.
            raise HTTPException(
                409, f"{stored.path.name} is stored, not printed: {model.HELD_REASON}"
            )
        extra: dict[str, Any] = {"findings": stored.findings}
        if stored.note:
            extra["note"] = stored.note
        if to_print:
            # Queued: it runs when the printer is free (OctoPrint answers 409 when it is
            # busy; a queue is what this server is for).
            user = user_of(request)
            record = jobs.queue(server, service.name, stored.path, stored.commands, user)
            extra["job"] = record.as_json()
            service.select(None)
        elif to_select and service.running is None:
            service.select(stored.path)
        location = stored.path.relative_to(server.files).as_posix()
        entry = await asyncio.to_thread(files.file_entry, server, stored.path, base)
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
            return await asyncio.to_thread(files.folder_entry, server, path, base, depth)
        return await asyncio.to_thread(
            files.file_entry, server, uploads.uploaded(server, location), base
        )

    @router.post("/files/local/{location:path}")
    async def file_command(
        request: Request, service: Printer, location: str, body: Command
    ) -> Response:
        server = server_of(request)
        if body.command in ("copy", "move"):
            destination = body.get("destination")
            if not isinstance(destination, str) or not destination:
                raise HTTPException(400, "Mandatory parameter destination missing")
            moving = body.command == "move"
            target = await asyncio.to_thread(
                files.copy_or_move, server, location, destination, moving
            )
            folder = target.is_dir()
            if moving:
                source = server.files / uploads.safe_folder(location)
                uploads.file_changed(server, source, "removed", "move", folder)
            uploads.file_changed(server, target, "added", body.command, folder)
            where = target.relative_to(server.files).as_posix()
            resource = files.resource_url(_base(request), where)
            refs = {"resource": resource}
            if target.is_file():
                refs["download"] = f"{_base(request)}/downloads/files/local/{quote(where)}"
            answer = {"name": target.name, "path": where, "origin": "local", "refs": refs}
            return JSONResponse(answer, 201, headers={"Location": resource})
        if body.command == "select":
            path = uploads.uploaded(server, location)
            if service.running is not None:
                raise HTTPException(409, "Printer is already printing, cannot select a new file")
            if _true(body.get("print", False)):
                _operational(service)
                if service.held:
                    raise HTTPException(409, model.HELD_REASON)
                _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
                jobs.queue(server, service.name, path, commands, user_of(request))
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
            await asyncio.to_thread(files.delete_folder, server, location)
            uploads.file_changed(server, path, "removed", "remove", folder=True)
        else:
            uploads.delete_upload(server, location)
        return Response(status_code=204)

    # --- the job ---------------------------------------------------------------------

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
    async def job_command(request: Request, service: Printer, body: Command) -> Response:
        server = server_of(request)
        text = _operational(service)
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

    # --- the printer -----------------------------------------------------------------

    @router.get("/printer")
    async def printer_state(
        service: Printer,
        history: Annotated[str, Query()] = "false",
        limit: Annotated[int, Query(ge=0)] = 300,
        exclude: Annotated[str, Query()] = "",
    ) -> dict[str, Any]:
        _operational(service)
        excluded = {part.strip() for part in exclude.split(",")}
        answer: dict[str, Any] = {}
        if "temperature" not in excluded:
            answer["temperature"] = _temperature(service, _true(history), limit)
        if "sd" not in excluded:
            answer["sd"] = {"ready": False}
        if "state" not in excluded:
            answer["state"] = model.state(service)
        return answer

    @router.get("/printer/tool")
    async def tool_state(
        service: Printer, history: str = "false", limit: Annotated[int, Query(ge=0)] = 300
    ) -> dict[str, Any]:
        _operational(service)
        return _temperature(service, _true(history), limit, lambda key: key.startswith("tool"))

    @router.post("/printer/tool", status_code=204)
    async def tool_command(service: Printer, body: Command) -> Response:
        _operational(service)
        commands: list[str] = []
        if body.command == "target":
            targets = body.get("targets")
            if not isinstance(targets, dict):
                raise HTTPException(400, "Mandatory parameter targets missing")
            for key, value in targets.items():
                index = _tool_index(service, key, _TOOL_OR_CURRENT, "targets")
                degrees = _number(value, "targets contains invalid value; a target")
                if degrees < 0:
                    raise HTTPException(400, "targets contains invalid value")
                several = _TOOL.fullmatch(key) and model.tool_count(service) > 1
                commands.append(f"M104{f' T{index}' if several else ''} S{_format(degrees)}")
        elif body.command == "offset":
            offsets = body.get("offsets")
            if not isinstance(offsets, dict):
                raise HTTPException(400, "Mandatory parameter offsets missing")
            for key, value in offsets.items():
                _tool_index(service, key, _TOOL, "offsets")
                if not -50 <= _number(value, "offsets contains invalid value; an offset") <= 50:
                    raise HTTPException(400, "offsets contains invalid value")
            service.offsets.update({key: float(value) for key, value in offsets.items()})
            return Response(status_code=204)
        elif body.command == "select":
            index = _tool_index(service, body.get("tool"), _TOOL, "tool is invalid; it")
            commands.append(f"T{index}")
        elif body.command == "extrude":
            amount = _number(body.get("amount"), "amount")
            speed = body.get("speed")
            feed = float(_AXIS_SPEEDS["e"])
            feed = min(_number(speed, "speed"), feed) if speed is not None else feed
            commands += ["G91", "M83", f"G1 E{_format(amount)} F{feed:.0f}", "M82", "G90"]
        elif body.command == "flowrate":
            commands.append(f"M221 S{_rate(body.get('factor'))}")
        else:
            raise HTTPException(
                400, f"command '{body.command}' is not select, target, offset, extrude, flowrate"
            )
        _not_printing(service, "Printer is currently printing: it takes commands when paused")
        await _send(service, commands)
        return Response(status_code=204)

    _heater_routes(router, "bed", "M140")
    _heater_routes(router, "chamber", "M141")

    @router.post("/printer/printhead", status_code=204)
    async def printhead_command(service: Printer, body: Command) -> Response:
        commands: list[str] = []
        if body.command == "jog":
            jogged = {
                axis: _number(body.get(axis), "axis value")
                for axis in ("x", "y", "z")
                if body.get(axis) is not None
            }
            if not jogged:
                raise HTTPException(400, "At least one axis to jog must be provided")
            speed = body.get("speed")
            if speed is None:  # the printer profile's, as OctoPrint
                speed = min(_AXIS_SPEEDS[axis] for axis in jogged)
            move = "G0 " + " ".join(f"{axis.upper()}{_format(v)}" for axis, v in jogged.items())
            if speed is not False:
                move += f" F{_format(_number(speed, 'speed'))}"
            absolute = _true(body.get("absolute", False))
            commands = ["G90", move] if absolute else ["G91", move, "G90"]
        elif body.command == "home":
            axes = body.get("axes")
            if isinstance(axes, str):
                axes = [axes]
            if not isinstance(axes, list) or not axes:
                raise HTTPException(400, "Mandatory parameter axes missing")
            if any(axis not in ("x", "y", "z") for axis in axes):
                raise HTTPException(400, "axis is invalid")
            commands = ["G91", f"G28 {' '.join(f'{axis.upper()}0' for axis in axes)}", "G90"]
        elif body.command == "feedrate":
            commands = [f"M220 S{_rate(body.get('factor'))}"]
        else:
            raise HTTPException(400, f"command '{body.command}' is not jog, home or feedrate")
        _not_printing(service, "Printer is not operational or currently printing")
        await _send(service, commands)
        return Response(status_code=204)

    @router.post("/printer/command", status_code=204)
    async def printer_command(service: Printer, body: PrinterCommand) -> Response:
        _operational(service)
        if body.command is not None and body.commands is not None:
            raise HTTPException(400, "'command' and 'commands' are mutually exclusive")
        if body.script is not None:
            raise HTTPException(404, "Unknown script (the server has no G-code scripts)")
        lines = body.commands if body.commands is not None else [body.command or ""]
        lines = [line.strip() for line in lines if line.strip()]
        if not lines:
            raise HTTPException(400, "Need one of 'command', 'commands' or 'script'")
        await _send(service, lines)
        return Response(status_code=204)

    @router.get("/printer/command/custom")
    async def custom_controls() -> dict[str, list[Any]]:
        return {"controls": []}

    @router.get("/printer/sd")
    async def sd_state(service: Printer) -> dict[str, bool]:
        _operational(service)
        return {"ready": False}

    @router.post("/printer/sd")
    async def sd_command() -> Response:
        raise HTTPException(
            409, "the printer has no SD card here: the server prints from its own storage"
        )

    @router.get("/printer/error")
    async def printer_error(service: Printer) -> dict[str, str]:
        return {"error": service.last_error, "reason": "connection" if service.last_error else ""}

    return router


def downloads() -> APIRouter:
    """``/downloads/files/local/PATH``: an upload's bytes (ranges too, for a resume)."""
    router = APIRouter()

    @router.get("/downloads/files/local/{location:path}")
    async def download(request: Request, location: str) -> FileResponse:
        path = uploads.uploaded(server_of(request), location)
        return FileResponse(path, media_type="text/plain", filename=path.name)

    return router


# --- what the routes share ---------------------------------------------------------


async def _listing(request: Request, folder: Path, recursive: bool) -> dict[str, Any]:
    server = server_of(request)
    found = await asyncio.to_thread(
        files.entries, server, folder, _base(request), None if recursive else 0
    )
    usage = shutil.disk_usage(server.data_dir)
    return {"files": found, "free": usage.free, "total": usage.total}


async def _start(server: PrintServer, service: PrinterService, user: str | None) -> None:
    """OctoPrint's start: the selected file (or the last job's, to print it again)."""
    if service.held:
        raise HTTPException(409, model.HELD_REASON)
    path = service.selected
    if path is None and service.finished is not None:
        path = service.data_dir / service.finished.record.file
    if path is None or not path.is_file():
        raise HTTPException(409, f"printer {service.name}: no file is selected")
    _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    jobs.queue(server, service.name, path, commands, user)
    service.select(None)


async def _restart(server: PrintServer, service: PrinterService, user: str | None) -> None:
    """OctoPrint's restart of a paused job: it is cancelled (its safe stop first), and
    its file goes first in the queue, which runs on (it was asked for)."""
    running = service.running
    assert running is not None
    path = service.data_dir / running.record.file
    await answered(service.control("cancel"))
    _, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    record = jobs.queue(server, service.name, path, commands, user)
    first = server.store.next_queued(service.name)
    if first is not None and first.id != record.id:
        server.store.move(record.id, first.id)
    service.release()


def _heater_routes(router: APIRouter, key: str, code: str) -> None:
    """``/printer/bed`` or ``/printer/chamber``: its temperature (GET), its target or
    offset (POST, set with ``code``)."""

    @router.get(f"/printer/{key}")
    async def heater_state(
        service: Printer, history: str = "false", limit: Annotated[int, Query(ge=0)] = 300
    ) -> dict[str, Any]:
        _operational(service)
        return _temperature(service, _true(history), limit, lambda name: name == key)

    @router.post(f"/printer/{key}", status_code=204)
    async def heater_command(service: Printer, body: Command) -> Response:
        return await _heater(service, body, key, code)


async def _heater(service: PrinterService, body: Command, key: str, code: str) -> Response:
    _operational(service)
    if body.command == "target":
        degrees = _number(body.get("target"), "target")
        _not_printing(service, "Printer is currently printing: it takes commands when paused")
        await _send(service, [f"{code} S{_format(degrees)}"])
    elif body.command == "offset":
        offset = _number(body.get("offset"), "offset")
        if not -50 <= offset <= 50:
            raise HTTPException(400, "offset is invalid")
        service.offsets[key] = offset
    else:
        raise HTTPException(400, f"command '{body.command}' is not target or offset")
    return Response(status_code=204)


def _temperature(
    service: PrinterService, history: bool, limit: int, keep: Any = None
) -> dict[str, Any]:
    """OctoPrint's temperature data, with its history of samples when asked."""
    current = {
        key: {**value, "offset": service.offsets.get(key, 0)}
        for key, value in model.temperatures(service).items()
        if keep is None or keep(key)
    }
    answer: dict[str, Any] = dict(current)
    if history:
        samples = list(service.temperature_history)[-limit:] if limit else []
        answer["history"] = [
            {
                "time": int(when),
                **{
                    model.tool_key(sensor): {"actual": actual, "target": target}
                    for sensor, (actual, target) in readings.items()
                    if keep is None or keep(model.tool_key(sensor))
                },
            }
            for when, readings in samples
        ]
    return answer


def _settings(request: Request, server: PrintServer, service: PrinterService) -> dict[str, Any]:
    """The parts of OctoPrint's settings that clients read."""
    snapshot = None
    if service.camera is not None:
        snapshot = (
            f"{str(request.base_url).rstrip('/')}/v1/printers/{service.name}/snapshots/latest"
        )
    return {
        "api": {"allowCrossOrigin": False},
        "appearance": {"name": service.name, "color": "default", "colorTransparent": False},
        "feature": {"sdSupport": False, "temperatureGraph": True, "pollWatched": False},
        "folder": {"uploads": str(server.files)},
        "serial": {
            "port": service.port,
            "baudrate": service.printer.settings.baud if service.printer else None,
            "autoconnect": True,
        },
        "temperature": {"profiles": _temperature_profiles(server), "cutoff": 30},
        "webcam": {
            "webcamEnabled": service.camera is not None,
            "streamUrl": None,
            "snapshotUrl": snapshot,
            "flipH": False,
            "flipV": False,
            "rotate90": False,
        },
        "plugins": {
            "discovery": {"upnpUuid": server.printer_uuid(service.name)},
            "tracking": {"enabled": False},
        },
    }


def _temperature_profiles(server: PrintServer) -> list[dict[str, Any]]:
    return [
        {"name": "PLA", "extruder": 210, "bed": 60, "chamber": None},
        {"name": "ABS", "extruder": 240, "bed": 100, "chamber": None},
    ]


def _profile(service: PrinterService) -> dict[str, Any]:
    """One printer profile per printer: its machine, heated bed, its tools."""
    tools = model.tool_count(service)
    loadout = service.plan_loadout()
    model_name = loadout.machine_name if loadout is not None else (service.config.machine or "")
    return {
        "id": service.name,
        "name": service.name,
        "model": model_name,
        "color": "default",
        "current": True,
        "default": True,
        "resource": f"/api/printerprofiles/{service.name}",
        "heatedBed": True,
        "heatedChamber": False,
        "volume": {
            "width": 200.0,
            "depth": 200.0,
            "height": 200.0,
            "formFactor": "rectangular",
            "origin": "lowerleft",
            "custom_box": False,
        },
        "axes": {axis: {"speed": speed, "inverted": False} for axis, speed in _AXIS_SPEEDS.items()},
        "extruder": {
            "count": tools,
            "offsets": [[0.0, 0.0] for _ in range(tools)],
            "nozzleDiameter": 0.4,
            "sharedNozzle": False,
            "defaultExtrusionLength": 5,
        },
    }
