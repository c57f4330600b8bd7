"""Moonraker's ``printer.*`` methods: the printer's info, its objects (listed, queried,
subscribed), G-code from a console (Klipper's own commands a client sends, such as
``PAUSE`` or ``SET_HEATER_TEMPERATURE``, done as the server does them), a print started,
paused, resumed and cancelled by the same paths as every other face, the emergency stop and
a reconnect for Klipper's restarts. Klippy's own endpoints (info, the objects, G-code, the
emergency stop) take GET and POST alike, as Moonraker registers them
(``klippy_connection.py``): FDM Monster POSTs ``printer/info`` and GETs
``printer/gcode/script?script=``."""

from __future__ import annotations

import asyncio
import contextlib
import re
import shlex
import socket
from typing import Any, NoReturn

import repetrel_host as rh
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.reports import parse_temperatures
from repetrel_host.server import jobs, uploads
from repetrel_host.server.moonraker.objects import (
    KLIPPER_COMMANDS,
    busy,
    eventtime,
    heater_names,
    klippy_state,
    reading,
    state_message,
)
from repetrel_host.server.moonraker.rpc import Call, Handler, RpcError, method
from repetrel_host.server.printers.heaters import heaters
from repetrel_host.server.printers.service import PrinterService, Refused


@method("/printer/info", "GET", "POST")
async def info(call: Call) -> dict[str, Any]:
    service = call.service
    return {
        "state": klippy_state(service),
        "state_message": state_message(service),
        "hostname": socket.gethostname(),
        "software_version": f"repetrel-host {rh.__version__}",
        "cpu_info": "",
        "klipper_path": "",
        "python_path": "",
        "log_file": "",
        "config_file": "",
        "process_id": 0,
        "user_id": 0,
        "group_id": 0,
    }


@method("/printer/objects/list", "GET", "POST")
async def objects_list(call: Call) -> dict[str, Any]:
    return {"objects": call.face.objects[call.service.name].names()}


def _wanted(call: Call) -> dict[str, list[str] | None]:
    """The objects asked for: ``{"objects": {name: fields or null}}``, or over HTTP's
    query ``?toolhead&extruder=target,temperature``."""
    objects = call.args.get("objects")
    if objects is None:  # GET /printer/objects/query?toolhead&extruder=target
        objects = {k: (v.split(",") if v else None) for k, v in call.args.items()}
    if not isinstance(objects, dict):
        raise RpcError(400, "Invalid argument objects: an object of names is needed")
    wanted: dict[str, list[str] | None] = {}
    for name, fields in objects.items():
        if isinstance(fields, str):
            fields = fields.split(",") if fields else None
        if fields is not None and not isinstance(fields, list):
            raise RpcError(400, f"Invalid fields for object {name}")
        wanted[str(name)] = fields
    return wanted


@method("/printer/objects/query", "GET", "POST")
async def objects_query(call: Call) -> dict[str, Any]:
    status = call.face.objects[call.service.name].status(_wanted(call))
    return {"eventtime": eventtime(), "status": status}


@method("/printer/objects/subscribe", "GET", "POST")
async def objects_subscribe(call: Call) -> dict[str, Any]:
    """A websocket's subscription: made on it, or over HTTP by a request that names it
    (``?connection_id=``, as FDM Monster does); its changes go to that websocket."""
    if call.connection is None:
        raise RpcError(400, "No connection associated with subscription request")
    return {"eventtime": eventtime(), "status": call.connection.subscribe(_wanted(call))}


@method("/printer/gcode/script", "GET", "POST")
async def gcode_script(call: Call) -> str:
    lines = [line.strip() for line in call.string("script").splitlines() if line.strip()]
    if await call.service.emergency_first(lines):
        call.face.gcode_command(call.service.name, "M112")
        return "ok"
    for line in lines:
        await run_line(call, line)
    return "ok"


@method("/printer/gcode/help", "GET", "POST")
async def gcode_help(call: Call) -> dict[str, str]:
    return dict(KLIPPER_COMMANDS)


@method("/printer/print/start", "POST")
async def print_start(call: Call) -> str:
    await start_print(call, call.string("filename"))
    return "ok"


def _print_action(action: str) -> Handler:
    """``printer.print.pause``/``resume``: the server's own action."""

    async def handler(call: Call) -> str:
        await _control(call.service, action)
        return "ok"

    return handler


for _action in ("pause", "resume"):
    method(f"/printer/print/{_action}", "POST")(_print_action(_action))


@method("/printer/print/cancel", "POST")
async def print_cancel(call: Call) -> str:
    await _cancel(call)
    return "ok"


@method("/printer/emergency_stop", "GET", "POST")
async def emergency_stop(call: Call) -> str:
    await call.service.command("M112")
    return "ok"


@method("/printer/restart", "POST")
@method("/printer/firmware_restart", "POST")
async def restart(call: Call) -> str:
    await reconnect(call.service)
    return "ok"


# --- what the methods share ------------------------------------------------------------


async def start_print(call: Call, filename: str, via: str = "printer.print.start") -> None:
    """Klipper's print start: the stored file queued and started now, as OctoPrint's face
    starts one (refused when the printer is busy or the file fails its check). A person's
    start says the bed is clear: a held queue is released (the server's one rule,
    ``jobs.start``), unless every start waits for a release."""
    service, server = call.service, call.server
    if busy(service):
        raise RpcError(400, "Printer is busy: cancel the job running first")
    try:
        path = uploads.uploaded(server, filename)
    except Exception:
        raise RpcError(400, f"File not found: {filename}") from None
    findings, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    uploads.refuse_errors(path.name, findings)
    # First in the queue: it is the print asked for now.
    try:
        jobs.start(server, service, path, commands, call.user, f"Moonraker's {via}", first=True)
    except Refused as exc:
        raise RpcError(400, str(exc)) from None


async def _control(service: PrinterService, action: str) -> None:
    try:
        await service.control(action)
    except Refused as exc:
        raise RpcError(400, str(exc)) from None


async def _cancel(call: Call) -> None:
    """Klipper's CANCEL_PRINT: the job's safe stop. With no job Klipper only says
    ``action:cancel`` and answers ok (klippy/extras/pause_resume.py), so a client's cancel
    at a job's end is no error."""
    try:
        cancelled = await call.service.cancel()
    except rh.UsageError as exc:
        raise RpcError(400, str(exc)) from None
    if not cancelled:
        call.face.gcode_response(call.service.name, "// action:cancel")


def _reset_file(call: Call) -> None:
    """Klipper's SDCARD_RESET_FILE, the clients' "clear" of a print that ended: the last
    job forgotten, as OctoPrint's unselect forgets it, so ``print_stats`` reads standby with
    no file (klippy/extras/virtual_sdcard.py). Klipper would stop a print running; here a
    print stops by its cancel (its safe stop), so the reset waits for one."""
    service = call.service
    if busy(service):
        _fail(call, "SDCARD_RESET_FILE cannot be run while printing: cancel the print first")
    service.select(None)


async def reconnect(service: PrinterService) -> None:
    """Klipper's restarts: the port closed and opened again (refused while a job runs:
    its safe stop needs the port)."""
    await service.disconnect()
    service.connect()


# Klipper's split of a line into words (klippy/gcode.py): a command is G1, M104, T0 (one
# letter, then its number) or an extended one (SET_FAN_SPEED: a longer word).
_ARGS = re.compile(r"([A-Z_]+|[A-Z*])")


def _words(line: str) -> list[str]:
    """The line split as Klipper splits it: "", then each word's letters and its value."""
    parts = _ARGS.split(line.split(";", 1)[0].upper())
    if "".join(parts[:2]) == "N":  # a line number first: N10 G1 is G1
        parts = ["", *parts[3:]]
    return parts


def _command(parts: list[str]) -> tuple[str, bool]:
    """The command of a line's words as Klipper names it, and whether it is an extended
    one."""
    return "".join(parts[:3]).strip(), len(parts) > 1 and len(parts[1]) > 1


async def run_line(call: Call, line: str) -> None:
    """One console line: Klipper's commands done here, any other G-code sent to the
    controller, its reply lines told as responses."""
    face, service = call.face, call.service
    face.gcode_command(service.name, line)
    parts = _words(line)
    name, extended = _command(parts)
    if extended:
        word = name.split()[0]
        rest = line[line.upper().index(word) + len(word) :]
        await _extended(call, name, word, _params(rest))
    elif name in ("M104", "M109"):
        await _set_extruder(call, name, parts)
    else:
        await _send(call, line)


async def _extended(call: Call, name: str, word: str, params: dict[str, str]) -> None:
    """Klipper's extended commands: the ones in KLIPPER_COMMANDS, else Klipper's answer to
    a command it does not have: a response saying so, and ok (klippy/gcode.py cmd_default)."""
    service = call.service
    if word == "PAUSE":
        await _control(service, "pause")
    elif word == "RESUME":
        await _control(service, "resume")
    elif word == "CANCEL_PRINT":
        await _cancel(call)
    elif word == "SDCARD_PRINT_FILE":
        await start_print(call, params.get("FILENAME", ""), "SDCARD_PRINT_FILE")
    elif word == "SDCARD_RESET_FILE":
        _reset_file(call)
    elif word in ("FIRMWARE_RESTART", "RESTART"):
        await reconnect(service)
    elif word == "SET_HEATER_TEMPERATURE":
        await _set_heater(call, params.get("HEATER", ""), params.get("TARGET", "0"))
    elif word == "TURN_OFF_HEATERS":
        for heater in heaters(service):
            await _send(call, heater["command"].format(target=0))
    elif word == "HELP":
        listed = [f"{known:<10}: {text}" for known, text in sorted(KLIPPER_COMMANDS.items())]
        _respond(call, "\n".join(["Available extended commands:", *listed]))
    else:
        _respond(call, f'Unknown command:"{name}"')


def _respond(call: Call, text: str) -> None:
    """Klipper's ``respond_info``: each line a response starting ``// ``."""
    for said in text.splitlines():
        call.face.gcode_response(call.service.name, f"// {said}")


def _fail(call: Call, message: str) -> NoReturn:
    """Klipper's G-code error: ``!!`` and the message as a response, the call refused
    with it (Moonraker's 400)."""
    call.face.gcode_response(call.service.name, f"!! {message}")
    raise RpcError(400, message)


async def _send(call: Call, line: str) -> None:
    """``line`` to the controller, its reply told as Klipper tells one: no ``ok`` (the
    serial console's, not Klipper's: ``gcode/script`` sends none), no Hyrel notice of the
    M-code run, and M105's answer in Klipper's words (``cmd_M105``); the controller's other
    lines as they came. The other faces keep the controller's own reply."""
    try:
        reply = await call.service.command(line)
    except Refused as exc:
        call.face.gcode_response(call.service.name, f"!! {exc}")
        raise RpcError(400, str(exc)) from None
    asked = command_word(line.strip().upper()) == "M105"
    for said in reply.lines:
        if not _klippers_silence(said, asked):
            call.face.gcode_response(call.service.name, said)
    rest = reply.ok_line[2:].strip()  # what came on the ok line after "ok"
    if rest and not parse_temperatures(rest):
        call.face.gcode_response(call.service.name, rest)
    if asked:
        call.face.gcode_response(call.service.name, m105_answer(call.service))


def _klippers_silence(said: str, asked: bool) -> bool:
    """Whether a reply line is one Klipper would not say: Hyrel's notice that an M-code
    ran, and the controller's temperature report where M105's answer is Klipper's own."""
    kind = replies.classify(said)
    if isinstance(kind, replies.HyrelReport) and kind.tag == "MC":
        return True
    return asked and bool(parse_temperatures(said))


def m105_answer(service: PrinterService) -> str:
    """M105's answer as Klipper's ``heaters.py`` (``_get_temp``) gives it: each heater by
    its G-code id (``T0``, ``T1``... for the extruders, ``B`` for the bed, ``C`` for a
    chamber), sorted by that id, as ``ID:current /target`` with one decimal; ``T:0``
    before any reading."""
    printer = service.printer
    readings = dict(printer.temperatures) if printer is not None else {}
    found: dict[str, tuple[float, float | None]] = {}
    for name, sensor in heater_names(service).items():
        read = reading(readings, sensor)
        if read is not None:
            found[_GCODE_IDS.get(name) or f"T{name.removeprefix('extruder')}"] = read
    said = [
        f"{ident}:{cur:.1f} /{target or 0.0:.1f}" for ident, (cur, target) in sorted(found.items())
    ]
    return " ".join(said) or "T:0"


# Klipper's G-code ids of heaters that are not extruders (``gcode_id`` of a chamber's
# ``heater_generic`` section, which ``configfile`` gives).
_GCODE_IDS = {"extruder": "T0", "heater_bed": "B", "heater_generic chamber": "C"}


async def _set_extruder(call: Call, word: str, parts: list[str]) -> None:
    """Klipper's M104/M109 (klippy/kinematics/extruder.py): ``T<n>`` is its extruder n
    (``extruder``, ``extruder1``...), no T the active one (the first here); set as
    SET_HEATER_TEMPERATURE sets it, by the head's own command (on Hyrel's link its
    address), so that a client's ``M104 T1`` sets the head it shows as ``extruder1``."""
    params = {parts[i]: parts[i + 1].strip() for i in range(1, len(parts) - 1, 2)}
    target, index = params.get("S") or "0", params.get("T") or "0"
    if not index.isdigit():
        _fail(call, f"Invalid T {index!r}")
    name = f"extruder{int(index) or ''}"
    if name not in heater_names(call.service):
        with contextlib.suppress(ValueError):
            if float(target) <= 0:
                return  # Klipper lets an extruder it lacks be turned off
        _fail(call, "Extruder not configured")
    await _set_heater(call, name, target, wait=word == "M109")


async def _set_heater(call: Call, name: str, target: str, wait: bool = False) -> None:
    """SET_HEATER_TEMPERATURE: the heater's own command (a Hyrel head by its address);
    ``wait``: a head's M109, which waits for it."""
    sensor = heater_names(call.service).get(name.strip().strip('"'))
    command = next((h["command"] for h in heaters(call.service) if h["sensor"] == sensor), None)
    if command is None:  # before any report named it
        command = {"T0": "M104 S{target}", "B": "M140 S{target}"}.get(sensor or "")
    if command is None:
        raise RpcError(400, f"Unknown heater {name!r}")
    try:
        degrees = float(target)
    except ValueError:
        raise RpcError(400, f"Invalid TARGET {target!r}") from None
    line = command.format(target=f"{degrees:g}")
    if wait and line.startswith("M104"):
        line = "M109" + line[4:]
    await _send(call, line)


def _params(text: str) -> dict[str, str]:
    """Klipper's ``NAME=value`` parameters (values may be quoted)."""
    found: dict[str, str] = {}
    try:
        words = shlex.split(text)
    except ValueError:
        words = text.split()
    for word in words:
        key, _, value = word.partition("=")
        found[key.upper()] = value
    return found
