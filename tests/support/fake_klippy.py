"""A small fake Klippy for a real Moonraker to talk to (the reference test): Klippy's API
server on a unix socket, JSON messages each ended by 0x03, answering what Moonraker asks as
it starts (info, list_endpoints, the objects, G-code help, subscriptions) with a
Klipper printer's status, and Klipper's G-code responses and errors to a few calls
(:func:`output`). A print (``SDCARD_PRINT_FILE``) runs for ``PRINT_SECONDS`` of printing
time, pauses, resumes and is cancelled as Klipper's ``print_stats`` says it, and each change
is pushed to Moonraker's subscription as Klippy pushes it (``process_status_update``).

Live as Klipper is (``klippy/webhooks.py``): a subscription is looked at every 0.25 s
(``QueryStatusHelper``) and sent what changed since, with the reactor's clock
(``CLOCK_MONOTONIC_RAW``) as its eventtime, nothing when nothing changed; the toolhead's
``estimated_print_time`` is that clock from the start (the controller's clock, in Klipper).
``gcode/script`` runs M104/M140 (the target set before the answer) and M105, whose answer
goes to ``gcode/subscribe_output``'s subscribers as ``heaters.py``'s ``cmd_M105`` gives it,
no ``ok``; other G-code says nothing, as a Klipper command that succeeds.

    python tests/support/fake_klippy.py SOCKET_PATH GCODES_FOLDER
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shlex
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
PRINT_SECONDS = 4.0  # a print's printing time, pauses left out
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
    if method == "gcode/script":
        script = str(params.get("script", ""))
        for line in script.splitlines():
            command = line.strip().split(" ", 1)[0].upper()
            if command == "SDCARD_PRINT_FILE":
                found = re.search(r"FILENAME=(.*)", line)
                PRINT.start(shlex.split(found.group(1))[0] if found else "")
            elif command in ("PAUSE", "RESUME", "CANCEL_PRINT"):
                PRINT.button(command)
        return {}
    if method.startswith("pause_resume/"):
        PRINT.button({"pause": "PAUSE", "resume": "RESUME"}.get(method[13:], "CANCEL_PRINT"))
        return {}
    if method == "gcode/help":
        return {"G28": "Home", "M104": "Set the extruder's temperature"}
    return {}


# Klipper's split of a line into words (klippy/gcode.py).
ARGS = re.compile(r"([A-Z_]+|[A-Z*])")


def output(method: str, params: dict[str, Any]) -> tuple[list[str], str | None]:
    """What Klipper says as G-code responses to a call, and its error if it fails: an
    extended command it lacks is a response, not an error (klippy/gcode.py cmd_default);
    M104 for an extruder it lacks is an error (klippy/kinematics/extruder.py); a cancel
    with no print says action:cancel (klippy/extras/pause_resume.py)."""
    if method == "pause_resume/cancel":
        return ["// action:cancel"], None
    said: list[str] = []
    for line in str(params.get("script", "")).split("\n") if method == "gcode/script" else ():
        parts = ARGS.split(line.split(";", 1)[0].strip().upper())
        command = "".join(parts[:3]).strip()
        words = {parts[i]: parts[i + 1].strip() for i in range(1, len(parts) - 1, 2)}
        if command in ("M104", "M109") and int(words.get("T") or 0) > 0:
            if float(words.get("S") or 0) > 0:  # this printer has one extruder
                return [*said, "!! Extruder not configured"], "Extruder not configured"
        elif len(parts) > 1 and len(parts[1]) > 1 and command not in EXTENDED:
            said.append(f'// Unknown command:"{command}"')
    return said, None


EXTENDED = {"PAUSE", "RESUME", "CANCEL_PRINT", "SDCARD_PRINT_FILE", "SDCARD_RESET_FILE"}


class Print:
    """The one print: its state in ``STATUS``, each change sent to the subscribers."""

    def __init__(self) -> None:
        self.printed = 0.0  # seconds printed
        self.since: float | None = None  # printing since (monotonic), None unless printing

    def start(self, filename: str) -> None:
        if STATUS["print_stats"]["state"] in ("printing", "paused"):
            return
        self.printed, self.since = 0.0, time.monotonic()
        self.change(filename, "printing", active=True)

    def button(self, command: str) -> None:
        state = STATUS["print_stats"]["state"]
        if command == "PAUSE" and state == "printing":
            self.tick()
            self.since = None
            self.change(STATUS["print_stats"]["filename"], "paused", active=False)
        elif command == "RESUME" and state == "paused":
            self.since = time.monotonic()
            self.change(STATUS["print_stats"]["filename"], "printing", active=True)
        elif command == "CANCEL_PRINT" and state in ("printing", "paused"):
            self.since = None
            self.change(STATUS["print_stats"]["filename"], "cancelled", active=False)

    def tick(self) -> None:
        """Count the time printed; the print completes after ``PRINT_SECONDS`` of it."""
        if self.since is None:
            return
        now = time.monotonic()
        self.printed, self.since = self.printed + now - self.since, now
        if self.printed >= PRINT_SECONDS:
            self.since = None
            self.change(STATUS["print_stats"]["filename"], "complete", active=False)

    def change(self, filename: str, state: str, *, active: bool) -> None:
        progress = min(self.printed / PRINT_SECONDS, 1.0)
        diff = {
            "print_stats": {"filename": filename, "state": state, "print_duration": self.printed},
            "virtual_sdcard": {"is_active": active, "progress": progress},
            "display_status": {"progress": progress},
            "pause_resume": {"is_paused": state == "paused"},
            "idle_timeout": {"state": "Printing" if active else "Ready"},
        }
        for name, fields in diff.items():  # told by each subscription's next look
            STATUS[name].update(fields)


PRINT = Print()


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
        responses: dict[str, Any] = {}
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
                said, error = output(method, params)
                result = answer(method, params, gcodes) if error is None else None
                if method == "objects/subscribe":
                    subscribed.update(
                        objects=params.get("objects", {}),
                        template=params.get("response_template", {}),
                    )
                    last.clear()
                    last.update({k: dict(v) for k, v in result["status"].items()})
                elif method == "gcode/subscribe_output":
                    responses.update(params.get("response_template", {}))
                elif method == "gcode/script" and error is None:
                    said += script(params.get("script", ""))
                for line in said if responses else ():
                    send({**responses, "params": {"response": line}})
                if error is None:
                    send({"id": request.get("id"), "result": result})
                else:
                    failed = {"error": "WebRequestError", "message": error}
                    send({"id": request.get("id"), "error": failed})
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            ticker.cancel()

    async def clock() -> None:
        while True:
            await asyncio.sleep(0.1)
            PRINT.tick()

    server = await asyncio.start_unix_server(serve, path)
    print("ready", flush=True)
    ticking = asyncio.create_task(clock())
    async with server:
        await server.serve_forever()
    ticking.cancel()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
