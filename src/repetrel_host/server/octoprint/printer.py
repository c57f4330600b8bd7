"""OctoPrint's printer (``/printer``): its state and temperatures, and its commands (tool,
bed, chamber, print head, G-code lines; no SD card), sent between jobs (a job streams
alone, so they are refused while one does)."""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import Response
from pydantic import BaseModel

from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.common import OctoPrintCommand, Printer, is_true, operational
from repetrel_host.server.octoprint.printer_profiles import AXIS_SPEEDS
from repetrel_host.server.print_server import answered
from repetrel_host.server.printers.service import PrinterService

_TOOL = re.compile(r"tool(\d+)")
_TOOL_OR_CURRENT = re.compile(r"tool(\d*)")


class PrinterCommand(BaseModel):
    command: str | None = None
    commands: list[str] | None = None
    script: str | None = None


def _not_printing(service: PrinterService, what: str) -> None:
    """409 while a job streams (paused, the printer takes commands)."""
    if model.flags(service, operational(service))["printing"]:
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
    """Commands to a printer not streaming a job, each after the last one ran (a heater's
    new target is the session's once the controller acknowledged it: the next read shows
    it)."""
    for command in commands:
        await answered(service.command(command))


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
    """``/printer``: its state, tool, bed, chamber, print head, commands, SD card, error."""
    router = APIRouter()

    @router.get("/printer")
    async def printer_state(
        service: Printer,
        history: Annotated[str, Query()] = "false",
        limit: Annotated[int, Query(ge=0)] = 300,
        exclude: Annotated[str, Query()] = "",
    ) -> dict[str, Any]:
        operational(service)
        excluded = {part.strip() for part in exclude.split(",")}
        answer: dict[str, Any] = {}
        if "temperature" not in excluded:
            answer["temperature"] = _temperature(service, is_true(history), limit)
        if "sd" not in excluded:
            answer["sd"] = {"ready": False}
        if "state" not in excluded:
            answer["state"] = model.state(service)
        return answer

    @router.get("/printer/tool")
    async def tool_state(
        service: Printer, history: str = "false", limit: Annotated[int, Query(ge=0)] = 300
    ) -> dict[str, Any]:
        operational(service)
        return _temperature(service, is_true(history), limit, lambda key: key.startswith("tool"))

    @router.post("/printer/tool", status_code=204)
    async def tool_command(service: Printer, body: OctoPrintCommand) -> Response:
        operational(service)
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
            feed = float(AXIS_SPEEDS["e"])
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
    async def printhead_command(service: Printer, body: OctoPrintCommand) -> Response:
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
                speed = min(AXIS_SPEEDS[axis] for axis in jogged)
            move = "G0 " + " ".join(f"{axis.upper()}{_format(v)}" for axis, v in jogged.items())
            if speed is not False:
                move += f" F{_format(_number(speed, 'speed'))}"
            absolute = is_true(body.get("absolute", False))
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
        operational(service)
        if body.command is not None and body.commands is not None:
            raise HTTPException(400, "'command' and 'commands' are mutually exclusive")
        if body.script is not None:
            raise HTTPException(404, "Unknown script (the server has no G-code scripts)")
        lines = body.commands if body.commands is not None else [body.command or ""]
        lines = [line.strip() for line in lines if line.strip()]
        if not lines:
            raise HTTPException(400, "Need one of 'command', 'commands' or 'script'")
        if not await answered(service.emergency_first(lines)):
            await _send(service, lines)
        return Response(status_code=204)

    @router.get("/printer/command/custom")
    async def custom_controls() -> dict[str, list[Any]]:
        return {"controls": []}

    @router.get("/printer/sd")
    async def sd_state(service: Printer) -> dict[str, bool]:
        operational(service)
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


def _heater_routes(router: APIRouter, key: str, code: str) -> None:
    """``/printer/bed`` or ``/printer/chamber``: its temperature (GET), its target or
    offset (POST, set with ``code``)."""

    @router.get(f"/printer/{key}")
    async def heater_state(
        service: Printer, history: str = "false", limit: Annotated[int, Query(ge=0)] = 300
    ) -> dict[str, Any]:
        operational(service)
        return _temperature(service, is_true(history), limit, lambda name: name == key)

    @router.post(f"/printer/{key}", status_code=204)
    async def heater_command(service: Printer, body: OctoPrintCommand) -> Response:
        return await _heater(service, body, key, code)


async def _heater(service: PrinterService, body: OctoPrintCommand, key: str, code: str) -> Response:
    operational(service)
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
