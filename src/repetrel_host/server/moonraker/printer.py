"""Moonraker's ``printer.*`` methods: the printer's info, its objects (listed, queried,
subscribed), G-code from a console (Klipper's own commands a client sends, such as
``PAUSE`` or ``SET_HEATER_TEMPERATURE``, done as the server does them), a print started,
paused, resumed and cancelled by the same paths as every other face, the emergency stop and
a reconnect for Klipper's restarts."""

from __future__ import annotations

import asyncio
import re
import shlex
import socket
from typing import Any

import repetrel_host as rh
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.reports import parse_temperatures
from repetrel_host.server import jobs, uploads
from repetrel_host.server.moonraker.objects import (
    eventtime,
    heater_names,
    klippy_state,
    reading,
    state_message,
)
from repetrel_host.server.moonraker.rpc import Call, Handler, RpcError, method
from repetrel_host.server.printers.heaters import heaters
from repetrel_host.server.printers.service import PrinterService, Refused

# Klipper's G-code help for the commands the face takes itself; any other line goes to the
# controller as it is.
KLIPPER_COMMANDS = {
    "PAUSE": "Pauses the current print (the job's safe pause)",
    "RESUME": "Resumes the print from a pause",
    "CANCEL_PRINT": "Cancel the current print (its safe stop first)",
    "SDCARD_PRINT_FILE": "Queues and starts a stored file: FILENAME=",
    "SET_HEATER_TEMPERATURE": "Sets a heater's target: HEATER= TARGET=",
    "TURN_OFF_HEATERS": "Turn off all heaters",
    "FIRMWARE_RESTART": "Reconnect to the controller",
    "RESTART": "Reconnect to the controller",
    "M112": "Emergency stop",
}


@method("/printer/info")
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


@method("/printer/objects/list")
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


@method("/printer/objects/subscribe", "POST", http=False)
async def objects_subscribe(call: Call) -> dict[str, Any]:
    if call.connection is None:
        raise RpcError(400, "a subscription needs the websocket")
    return {"eventtime": eventtime(), "status": call.connection.subscribe(_wanted(call))}


@method("/printer/gcode/script", "POST")
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
    """``printer.print.pause``/``resume``/``cancel``: the server's own action."""

    async def handler(call: Call) -> str:
        await _control(call.service, action)
        return "ok"

    return handler


for _action in ("pause", "resume", "cancel"):
    method(f"/printer/print/{_action}", "POST")(_print_action(_action))


@method("/printer/emergency_stop", "POST")
async def emergency_stop(call: Call) -> str:
    await call.service.command("M112")
    return "ok"


@method("/printer/restart", "POST")
@method("/printer/firmware_restart", "POST")
async def restart(call: Call) -> str:
    await reconnect(call.service)
    return "ok"


# --- what the methods share ------------------------------------------------------------


async def start_print(call: Call, filename: str) -> None:
    """Klipper's print start: the stored file queued and started now, as OctoPrint's face
    starts one (refused when the printer is busy, held or the file fails its check)."""
    service, server = call.service, call.server
    if service.running is not None or service.state in ("printing", "paused"):
        raise RpcError(400, "Printer is busy: cancel the job running first")
    if service.held:
        raise RpcError(
            400, f"printer {service.name}'s queue is held: release it (the part on the bed)"
        )
    try:
        path = uploads.uploaded(server, filename)
    except Exception:
        raise RpcError(400, f"File not found: {filename}") from None
    findings, commands = await asyncio.to_thread(uploads.check, server, service.name, path)
    uploads.refuse_errors(path.name, findings)
    # First in the queue: it is the print asked for now.
    jobs.to_front(server, jobs.queue(server, service.name, path, commands, call.user))


async def _control(service: PrinterService, action: str) -> None:
    try:
        await service.control(action)
    except Refused as exc:
        raise RpcError(400, str(exc)) from None


async def reconnect(service: PrinterService) -> None:
    """Klipper's restarts: the port closed and opened again (refused while a job runs:
    its safe stop needs the port)."""
    await service.disconnect()
    service.connect()


_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


async def run_line(call: Call, line: str) -> None:
    """One console line: Klipper's commands done here, any other G-code sent to the
    controller, its reply lines told as responses."""
    face, service = call.face, call.service
    face.gcode_command(service.name, line)
    found = _WORD.match(line)
    word = found.group(0).upper() if found else ""
    params = _params(line[len(word) :]) if word in KLIPPER_COMMANDS else {}
    if word == "PAUSE":
        await _control(service, "pause")
    elif word == "RESUME":
        await _control(service, "resume")
    elif word == "CANCEL_PRINT":
        await _control(service, "cancel")
    elif word == "SDCARD_PRINT_FILE":
        await start_print(call, params.get("FILENAME", ""))
    elif word in ("FIRMWARE_RESTART", "RESTART"):
        await reconnect(service)
    elif word == "SET_HEATER_TEMPERATURE":
        await _set_heater(call, params.get("HEATER", ""), params.get("TARGET", "0"))
    elif word == "TURN_OFF_HEATERS":
        for heater in heaters(service):
            await _send(call, heater["command"].format(target=0))
    else:
        await _send(call, line)


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


async def _set_heater(call: Call, name: str, target: str) -> None:
    """SET_HEATER_TEMPERATURE: the heater's own command (a Hyrel head by its address)."""
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
    await _send(call, command.format(target=f"{degrees:g}"))


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
