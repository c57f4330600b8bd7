"""A small fake Klippy for a real Moonraker to talk to (the reference test): Klippy's API
server on a unix socket, JSON messages each ended by 0x03, answering what Moonraker asks as
it starts (info, list_endpoints, the objects, G-code help, subscriptions) with an idle
Klipper printer's status.

Live as Klipper is (``klippy/webhooks.py``): a subscription is looked at every 0.25 s
(``QueryStatusHelper``) and sent what changed since, with the reactor's clock
(``CLOCK_MONOTONIC_RAW``) as its eventtime, nothing when nothing changed; the toolhead's
``estimated_print_time`` is that clock from the start (the controller's clock, in Klipper).
``gcode/script`` runs M104/M140 (the target set before the answer) and M105, whose answer
goes to ``gcode/subscribe_output``'s subscribers as ``heaters.py``'s ``cmd_M105`` gives it,
no ``ok``; other G-code says nothing, as a Klipper command that succeeds.

    python tests/support/fake_klippy.py SOCKET_PATH
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import sys
import time
from typing import Any

ENDPOINTS = [
    "info",
    "list_endpoints",
    "emergency_stop",
    "objects/list",
    "objects/query",
    "objects/subscribe",
    "gcode/script",
    "gcode/help",
    "gcode/subscribe_output",
    "pause_resume/pause",
    "pause_resume/resume",
    "pause_resume/cancel",
    "register_remote_method",
]
ZEROS = [0.0, 0.0, 0.0, 0.0]
# An idle Klipper printer's objects (Klipper's status reference).
STATUS: dict[str, dict[str, Any]] = {
    "webhooks": {"state": "ready", "state_message": "Printer is ready"},
    "print_stats": {
        "filename": "",
        "total_duration": 0.0,
        "print_duration": 0.0,
        "filament_used": 0.0,
        "state": "standby",
        "message": "",
        "info": {"total_layer": None, "current_layer": None},
    },
    "virtual_sdcard": {
        "file_path": None,
        "progress": 0.0,
        "is_active": False,
        "file_position": 0,
        "file_size": 0,
    },
    "display_status": {"message": None, "progress": 0.0},
    "pause_resume": {"is_paused": False},
    "idle_timeout": {"state": "Idle", "printing_time": 0.0, "idle_timeout": 600.0},
    "toolhead": {
        "homed_axes": "",
        "axis_minimum": ZEROS,
        "axis_maximum": [200.0, 200.0, 200.0, 0.0],
        "print_time": 0.0,
        "stalls": 0,
        "estimated_print_time": 0.0,
        "extruder": "extruder",
        "position": ZEROS,
        "max_velocity": 300.0,
        "max_accel": 3000.0,
        "minimum_cruise_ratio": 0.5,
        "square_corner_velocity": 5.0,
    },
    "gcode_move": {
        "speed_factor": 1.0,
        "speed": 1500.0,
        "extrude_factor": 1.0,
        "absolute_coordinates": True,
        "absolute_extrude": True,
        "homing_origin": ZEROS,
        "position": ZEROS,
        "gcode_position": ZEROS,
    },
    "extruder": {
        "temperature": 21.0,
        "target": 0.0,
        "power": 0.0,
        "can_extrude": False,
        "pressure_advance": 0.0,
        "smooth_time": 0.04,
        "motion_queue": None,
    },
    "heater_bed": {"temperature": 21.0, "target": 0.0, "power": 0.0},
    "fan": {"speed": 0.0, "rpm": None},
    "heaters": {
        "available_heaters": ["heater_bed", "extruder"],
        "available_sensors": ["heater_bed", "extruder"],
        "available_monitors": [],
    },
}


SUBSCRIPTION_REFRESH_TIME = 0.25  # s: Klipper's
STARTED = time.clock_gettime(time.CLOCK_MONOTONIC_RAW)
_TARGET = re.compile(r"^(M104|M140)\b.*?\bS(\d+(?:\.\d*)?)", re.IGNORECASE)


def eventtime() -> float:
    """Klipper's reactor clock (chelper's get_monotonic)."""
    return time.clock_gettime(time.CLOCK_MONOTONIC_RAW)


def current(gcodes: str, now: float) -> dict[str, dict[str, Any]]:
    """Every object as it is at ``now``: the toolhead's estimated_print_time moves."""
    status = {**STATUS, "configfile": configfile(gcodes)}
    status["toolhead"] = {**STATUS["toolhead"], "estimated_print_time": now - STARTED}
    return status


def script(text: str) -> list[str]:
    """``gcode/script``: its lines run; what Klipper says of them (only M105 says a thing)."""
    said = []
    for line in text.splitlines():
        target = _TARGET.match(line.strip())
        if target is not None:
            name = "extruder" if target.group(1).upper() == "M104" else "heater_bed"
            STATUS[name]["target"] = float(target.group(2))
        elif line.strip().upper() == "M105":
            heaters = {"B": STATUS["heater_bed"], "T0": STATUS["extruder"]}
            said.append(
                " ".join(
                    f"{ident}:{h['temperature']:.1f} /{h['target']:.1f}"
                    for ident, h in sorted(heaters.items())
                )
            )
    return said


def answer(method: str, params: dict[str, Any], gcodes: str) -> Any:
    if method == "info":
        return {
            "state": "ready",
            "state_message": "Printer is ready",
            "hostname": "fake-klippy",
            "software_version": "v0.12.0-fake",
            "cpu_info": "fake",
            # Not a real folder: Moonraker refuses writes below Klipper's own path.
            "klipper_path": "/nonexistent/klipper",
            "python_path": sys.executable,
            "log_file": "/nonexistent/klippy.log",
            "config_file": "/nonexistent/printer.cfg",
            "process_id": os.getpid(),
            "user_id": os.getuid(),
            "group_id": os.getgid(),
        }
    if method == "list_endpoints":
        return {"endpoints": ENDPOINTS}
    if method == "objects/list":
        return {"objects": [*STATUS, "configfile"]}
    if method in ("objects/query", "objects/subscribe"):
        now = eventtime()
        return {"eventtime": now, "status": pick(current(gcodes, now), params.get("objects", {}))}
    if method == "gcode/help":
        return {"G28": "Home", "M104": "Set the extruder's temperature"}
    return {}


def pick(status: dict[str, dict[str, Any]], wanted: dict[str, Any]) -> dict[str, Any]:
    return {
        name: {k: v for k, v in status[name].items() if fields is None or k in fields}
        for name, fields in wanted.items()
        if name in status
    }


def configfile(gcodes: str) -> dict[str, Any]:
    sections = {
        "printer": {"kinematics": "cartesian"},
        "virtual_sdcard": {"path": gcodes},
        "extruder": {},
        "heater_bed": {},
        "pause_resume": {},
        "display_status": {},
    }
    return {
        "config": sections,
        "settings": sections,
        "warnings": [],
        "save_config_pending": False,
        "save_config_pending_items": {},
    }


async def main(path: str, gcodes: str) -> None:
    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        def send(message: dict[str, Any]) -> None:
            writer.write(json.dumps(message).encode() + b"\x03")

        # What this connection subscribed to, and its gcode output's template.
        subscribed: dict[str, Any] = {}
        output: dict[str, Any] = {}
        last: dict[str, dict[str, Any]] = {}  # as the last look found them

        async def tick() -> None:
            while True:
                await asyncio.sleep(SUBSCRIPTION_REFRESH_TIME)
                if not subscribed:
                    continue
                now = eventtime()
                found = pick(current(gcodes, now), subscribed["objects"])
                changed = {}
                for name, values in found.items():
                    before = last.setdefault(name, {})
                    diff = {k: v for k, v in values.items() if before.get(k, ...) != v}
                    before.update(diff)
                    if diff:
                        changed[name] = diff
                if changed:
                    params = {"eventtime": now, "status": changed}
                    send({**subscribed["template"], "params": params})

        ticker = asyncio.create_task(tick())
        try:
            while True:
                request = json.loads((await reader.readuntil(b"\x03"))[:-1])
                method, params = request.get("method", ""), request.get("params", {})
                result = answer(method, params, gcodes)
                if method == "objects/subscribe":
                    subscribed.update(
                        objects=params.get("objects", {}),
                        template=params.get("response_template", {}),
                    )
                    last.clear()
                    last.update({k: dict(v) for k, v in result["status"].items()})
                elif method == "gcode/subscribe_output":
                    output.update(params.get("response_template", {}))
                elif method == "gcode/script":
                    for said in script(params.get("script", "")):
                        if output:
                            send({**output, "params": {"response": said}})
                send({"id": request.get("id"), "result": result})
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            ticker.cancel()

    server = await asyncio.start_unix_server(serve, path)
    print("ready", flush=True)
    async with server:
        await server.serve_forever()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
