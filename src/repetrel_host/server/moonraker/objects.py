"""Klipper's printer objects, as Moonraker's clients read them, made from a printer of the
server: its session (state, temperatures), its running or last job (progress, layers,
filament) and its loadout (one ``extruder``, ``extruder1``... per heated head). The keys
are Klipper's (its status reference); what a Hyrel host cannot know (the toolhead's live
position, a fan's speed, a heater's power) has Klipper's idle value, and
``docs/moonraker-clients.md`` says which."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from repetrel_host.gcode.estimate import DEFAULT_LIMITS
from repetrel_host.server.moonraker.host import meminfo
from repetrel_host.server.printers.heaters import heaters
from repetrel_host.server.printers.service import PrinterService
from repetrel_host.server.store import JobState
from repetrel_host.session.motion_state import MotionState

# The session's states as Klippy's: ready, startup, shutdown (what a lost link is to
# Klipper), disconnected (the port closed on purpose: no Klippy to talk to).
_KLIPPY = {
    "ready": "ready",
    "printing": "ready",
    "paused": "ready",
    "connecting": "startup",
    "disconnected": "shutdown",
    "closed": "disconnected",
}
# How the server's ended jobs are to print_stats.
_ENDED = {
    JobState.COMPLETED: "complete",
    JobState.CANCELLED: "cancelled",
    JobState.FAILED: "error",
    JobState.INTERRUPTED: "error",
}
_ZEROS = [0.0, 0.0, 0.0, 0.0]

# Klipper's G-code help for its extended commands the face does itself (what HELP,
# printer.gcode.help and the gcode object list). G-code (G1, T0, Hyrel's M-codes: a letter
# and a number) goes to the controller, but M104/M109, whose T is Klipper's extruder
# number here, and M112, which goes at once; an extended command not here is answered as
# Klipper answers one it does not have.
KLIPPER_COMMANDS = {
    "PAUSE": "Pauses the current print (the job's safe pause)",
    "RESUME": "Resumes the print from a pause",
    "CANCEL_PRINT": "Cancel the current print (its safe stop first)",
    "SDCARD_PRINT_FILE": "Queues and starts a stored file: FILENAME=",
    "SDCARD_RESET_FILE": "Clears the last print's file (not while printing)",
    "SET_HEATER_TEMPERATURE": "Sets a heater's target: HEATER= TARGET=",
    "TURN_OFF_HEATERS": "Turn off all heaters",
    "FIRMWARE_RESTART": "Reconnect to the controller",
    "RESTART": "Reconnect to the controller",
    "HELP": "Report the list of available extended G-Code commands",
}

# A heater's limits as Klipper's clients read them: the head library's ``max_temp``, else
# Marlin's default maxima (its Configuration.h: HEATER_0_MAXTEMP, BED_MAXTEMP,
# CHAMBER_MAXTEMP, HEATER_0_MINTEMP, EXTRUDE_MINTEMP). The controller keeps its own limits
# whatever a client offers.
MAX_TEMP = {"head": 275.0, "bed": 150.0, "chamber": 60.0}
MIN_TEMP = 5.0
MIN_EXTRUDE_TEMP = 170.0
FILAMENT = 1.75  # mm: Hyrel's thermoplastic heads take 1.75 mm filament
NOZZLE = 0.4  # mm, where the loadout gives none


def eventtime() -> float:
    """Klippy's clock: its reactor's ``monotonic()`` (``chelper``'s ``get_monotonic``,
    ``CLOCK_MONOTONIC_RAW``), what its status updates and queries give as ``eventtime``."""
    return time.clock_gettime(_CLOCK) if _CLOCK is not None else time.monotonic()


_CLOCK = getattr(time, "CLOCK_MONOTONIC_RAW", None)


def klippy_state(service: PrinterService) -> str:
    """``ready``, ``startup`` (connecting, or the server starting), ``shutdown`` (the
    controller's link is lost) or ``disconnected`` (its port was closed on purpose)."""
    if service.printer is None:
        return "startup"
    return _KLIPPY.get(service.state, "shutdown")


def state_message(service: PrinterService) -> str:
    """Klippy's ``state_message``: why the printer is not ready, in our words."""
    state = klippy_state(service)
    if state == "ready":
        return "Printer is ready"
    if state == "startup":
        return f"Printer {service.name} is connecting on {service.port}"
    reason = service.state_reason or service.last_error
    if service.state == "closed":
        return f"The port of printer {service.name} is closed: FIRMWARE_RESTART opens it"
    return reason or f"Printer {service.name} is not connected ({service.port})"


def heater_names(service: PrinterService) -> dict[str, str]:
    """The printer's heaters by Klipper's names: its heads in order as ``extruder``,
    ``extruder1``... (a Hyrel loadout's first head is ``extruder`` whatever its tool
    number: Klipper's clients expect that one), ``heater_bed``, ``heater_generic
    chamber``; the session's sensor of each."""
    names: dict[str, str] = {}
    heads = 0
    for heater in heaters(service):
        kind = heater["kind"]
        if kind == "head":
            names[f"extruder{heads or ''}"] = heater["sensor"]
            heads += 1
        elif kind == "bed":
            names["heater_bed"] = heater["sensor"]
        else:
            names["heater_generic chamber"] = heater["sensor"]
    # Klipper always has these, and clients read them: before a report names them too.
    names.setdefault("extruder", "T0")
    names.setdefault("heater_bed", "B")
    return names


def busy(service: PrinterService) -> bool:
    """A job runs, or the session streams one the server has yet to take on."""
    return service.running is not None or service.state in ("printing", "paused")


def _shown_state(service: PrinterService) -> str:
    if busy(service):
        if service.state == "paused" or service.phase == "pausing":
            return "paused"
        return "printing"
    if service.finished is not None and service.finished_state is not None:
        return _ENDED.get(service.finished_state, "standby")
    return "standby"


def _completed(service: PrinterService) -> bool:
    """The job shown is the last one, and it completed."""
    return service.running is None and service.finished_state is JobState.COMPLETED


class Objects:
    """The objects of one printer: each a function of it, queried by name."""

    def __init__(self, service: PrinterService) -> None:
        self.service = service
        # Klipper's print time runs on its controller's clock from the controller's start:
        # here from the face's (toolhead's estimated_print_time, which always moves).
        self.started = eventtime()
        self._print_time = 0.0  # the toolhead's print_time: where the last job's moves got
        self.makers: dict[str, Callable[[], dict[str, Any]]] = {
            "webhooks": self.webhooks,
            "print_stats": self.print_stats,
            "virtual_sdcard": self.virtual_sdcard,
            "display_status": self.display_status,
            "pause_resume": self.pause_resume,
            "idle_timeout": self.idle_timeout,
            "toolhead": self.toolhead,
            "gcode_move": self.gcode_move,
            "motion_report": self.motion_report,
            "fan": self.fan,
            "heaters": self.heaters,
            "configfile": self.configfile,
            "system_stats": self.system_stats,
            "gcode": self.gcode,
        }

    def names(self) -> list[str]:
        """Every object's name, the heaters' as the loadout and reports have them."""
        return [*self.makers, *heater_names(self.service)]

    def status(self, wanted: dict[str, list[str] | None]) -> dict[str, dict[str, Any]]:
        """The objects ``wanted`` (name: its fields, or None for all); unknown objects and
        fields are left out, as Klipper does."""
        heated = heater_names(self.service)
        readings = self._readings()
        found: dict[str, dict[str, Any]] = {}
        for name, fields in wanted.items():
            if name in self.makers:
                values = self.makers[name]()
            elif name in heated:
                values = self._heater(name, heated[name], readings)
            else:
                continue
            found[name] = values if fields is None else pick(values, fields)
        return found

    # --- the objects ----------------------------------------------------------------

    def webhooks(self) -> dict[str, Any]:
        service = self.service
        return {"state": klippy_state(service), "state_message": state_message(service)}

    def print_stats(self) -> dict[str, Any]:
        service = self.service
        shown = service.running or service.finished
        state = _shown_state(service)
        stats: dict[str, Any] = {
            "filename": "",
            "total_duration": 0.0,
            "print_duration": 0.0,
            "filament_used": 0.0,
            "state": state,
            "message": service.last_error if state == "error" else "",
            "info": {"total_layer": None, "current_layer": None},
        }
        if state != "error" and service.running is None:
            # Klipper's message says what went wrong; here also why nothing starts by itself.
            stats["message"] = service.hold_note()
        if shown is None:
            return stats
        record = shown.record
        started = record.started or time.time()
        ended = service.finished_at if service.running is None else None
        duration = max((ended or time.time()) - started, 0.0)
        used = 0.0
        if shown.summary is not None and shown.summary.filament:
            whole = sum(tool.length for tool in shown.summary.filament.values())
            used = whole * (1.0 if _completed(service) else shown.fraction)
        layers = len(shown.layers)
        stats.update(
            filename=record.location,
            total_duration=round(duration, 3),
            print_duration=round(duration, 3),
            filament_used=round(used, 2),
            info={
                "total_layer": layers or None,
                "current_layer": min(shown.layer, layers) if layers else None,
            },
        )
        if state == "error":  # why, as the job's record says it once ended
            ended_record = service.store.job(record.id)
            why = ended_record.error if ended_record else None
            stats["message"] = why or service.finished_error or stats["message"]
        return stats

    def virtual_sdcard(self) -> dict[str, Any]:
        service = self.service
        shown = service.running or service.finished
        if shown is None:
            return {
                "file_path": None,
                "progress": 0.0,
                "is_active": False,
                "file_position": 0,
                "file_size": 0,
            }
        done = _completed(service)
        return {
            "file_path": str(service.data_dir / shown.record.file),
            "progress": round(1.0 if done else shown.fraction, 4),
            "is_active": service.running is not None and service.state == "printing",
            "file_position": shown.job.size if done else shown.job.offset,
            "file_size": shown.job.size,
        }

    def display_status(self) -> dict[str, Any]:
        return {"message": None, "progress": self.virtual_sdcard()["progress"]}

    def pause_resume(self) -> dict[str, Any]:
        return {"is_paused": _shown_state(self.service) == "paused"}

    def idle_timeout(self) -> dict[str, Any]:
        service = self.service
        printing = service.running is not None
        since = service.running.record.started if service.running is not None else None
        return {
            "state": "Printing" if printing else "Ready" if service.state == "ready" else "Idle",
            # Klipper's moves with its clock while it prints (extras/idle_timeout.py).
            "printing_time": max(time.time() - since, 0.0) if since else 0.0,
            "idle_timeout": 600.0,
        }

    def toolhead(self) -> dict[str, Any]:
        """Klipper's toolhead (toolhead.py ``get_status``): its estimated_print_time is the
        controller's clock, which moves while idle too; its print_time where the queued
        moves end (here: with the clock while a job runs, then where that job left it)."""
        estimated = eventtime() - self.started
        if self.service.running is not None:
            self._print_time = estimated
        limits = _printer_section(self.service)
        return {
            "homed_axes": self._motion().homed,
            "axis_minimum": _ZEROS,
            "axis_maximum": _ZEROS,
            "print_time": self._print_time,
            "stalls": 0,
            "estimated_print_time": estimated,
            "extruder": "extruder",
            "position": _ZEROS,
            "max_velocity": limits["max_velocity"],
            "max_accel": limits["max_accel"],
            "minimum_cruise_ratio": 0.5,
            "square_corner_velocity": 5.0,
        }

    def gcode_move(self) -> dict[str, Any]:
        motion = self._motion()
        return {
            "speed_factor": motion.speed_factor,
            "speed": 0.0,
            "extrude_factor": motion.extrude_factor,
            "absolute_coordinates": True,
            "absolute_extrude": True,
            "homing_origin": _ZEROS,
            "position": _ZEROS,
            "gcode_position": _ZEROS,
        }

    def motion_report(self) -> dict[str, Any]:
        return {
            "live_position": _ZEROS,
            "live_velocity": 0.0,
            "live_extruder_velocity": 0.0,
            "steppers": [],
            "trapq": [],
        }

    def fan(self) -> dict[str, Any]:
        return {"speed": 0.0, "rpm": None}

    def heaters(self) -> dict[str, Any]:
        names = list(heater_names(self.service))
        return {"available_heaters": names, "available_sensors": names, "available_monitors": []}

    def configfile(self) -> dict[str, Any]:
        """What a client reads of the machine: its limits and each heater's, the kinematics,
        where the files are (as text, Klipper's ``config``, and parsed, its ``settings``)."""
        service = self.service
        sections: dict[str, dict[str, Any]] = {
            "printer": _printer_section(service),
            "virtual_sdcard": {"path": str(service.data_dir / "files")},
            "pause_resume": {},
            "display_status": {},
        }
        sections.update(_heater_sections(service, sections["printer"]))
        return {
            "config": {name: {k: str(v) for k, v in s.items()} for name, s in sections.items()},
            "settings": sections,
            "warnings": [],
            "save_config_pending": False,
            "save_config_pending_items": {},
        }

    def gcode(self) -> dict[str, Any]:
        """The extended commands the face does, with their help (Mainsail's console
        completes them), as Klipper's ``gcode`` object lists its commands."""
        return {"commands": {name: {"help": text} for name, text in KLIPPER_COMMANDS.items()}}

    def system_stats(self) -> dict[str, Any]:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
        return {
            "sysload": round(load, 2),
            "cputime": round(time.process_time(), 3),
            "memavail": meminfo("MemAvailable"),
        }

    def _motion(self) -> MotionState:
        """The axes homed and the factors, as the session keeps them."""
        printer = self.service.printer
        return printer.motion if printer is not None else MotionState()

    # --- heaters --------------------------------------------------------------------

    def _readings(self) -> dict[str, tuple[float, float | None]]:
        printer = self.service.printer
        return dict(printer.temperatures) if printer is not None else {}

    def _heater(
        self, name: str, sensor: str, readings: dict[str, tuple[float, float | None]]
    ) -> dict[str, Any]:
        found = reading(readings, sensor)
        actual, target = found if found is not None else (0.0, 0.0)
        values: dict[str, Any] = {
            "temperature": round(actual, 2),
            "target": float(target or 0.0),
            "power": 0.0,
        }
        if name.startswith("extruder"):
            values.update(
                can_extrude=True, pressure_advance=0.0, smooth_time=0.04, motion_queue=None
            )
        return values


def _printer_section(service: PrinterService) -> dict[str, Any]:
    """Klipper's ``[printer]``: the planner's limits the print time uses (the loadout's
    machine profile's, else Marlin's defaults)."""
    loadout = service.plan_loadout()
    limits = loadout.machine.planner_limits() if loadout is not None else DEFAULT_LIMITS
    return {
        "kinematics": "cartesian",
        "max_velocity": limits.max_feedrate["X"],
        "max_accel": limits.print_acceleration,
        "max_z_velocity": limits.max_feedrate["Z"],
        "max_z_accel": limits.max_acceleration["Z"],
        "square_corner_velocity": 5.0,
        "minimum_cruise_ratio": 0.5,
    }


def _heater_sections(service: PrinterService, limits: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A section per heater, with the keys Klipper's clients read before they offer a
    target (Mainsail refuses one above ``max_temp``; KlipperScreen and Mobileraker fail
    without ``max_temp``, ``control``, ``filament_diameter``...)."""
    loadout = service.plan_loadout()
    heads = {head.tool: head for head in loadout.heads} if loadout is not None else {}
    sections: dict[str, dict[str, Any]] = {}
    tools: dict[str, int] = {h["sensor"]: h["tool"] for h in heaters(service) if "tool" in h}
    for name, sensor in heater_names(service).items():
        kind = "head" if name.startswith("extruder") else "bed" if name == "heater_bed" else ""
        kind = kind or "chamber"
        head = heads.get(tools.get(sensor, -1)) if kind == "head" else None
        limit = head.head.max_temp if head is not None else None
        section: dict[str, Any] = {
            "control": "pid",
            "max_power": 1.0,
            "min_temp": MIN_TEMP,
            "max_temp": float(limit or MAX_TEMP[kind]),
        }
        if kind == "chamber":
            section["gcode_id"] = "C"  # M105 tells it as C, as a heater_generic with it
        if kind == "head":
            nozzle = (head.nozzle if head is not None else None) or NOZZLE
            cross_section = 4.0 * nozzle**2  # Klipper's default max_extrude_cross_section
            area = math.pi * (FILAMENT / 2) ** 2
            section.update(
                min_extrude_temp=MIN_EXTRUDE_TEMP,
                nozzle_diameter=nozzle,
                filament_diameter=FILAMENT,
                max_extrude_cross_section=round(cross_section, 4),
                max_extrude_only_distance=50.0,
                max_extrude_only_velocity=round(limits["max_velocity"] * cross_section / area, 3),
                max_extrude_only_accel=round(limits["max_accel"] * cross_section / area, 3),
                pressure_advance=0.0,
                pressure_advance_smooth_time=0.04,
            )
        sections[name] = section
    return sections


def reading(
    readings: Mapping[str, tuple[float, float | None]], sensor: str
) -> tuple[float, float | None] | None:
    """``sensor``'s (temperature, target) in a report; T0's is T's where one hotend is
    reported as T."""
    found = readings.get(sensor)
    return readings.get("T") if found is None and sensor == "T0" else found


def pick(values: dict[str, Any], fields: Iterable[str]) -> dict[str, Any]:
    """The ``fields`` of ``values`` that it has."""
    return {field: values[field] for field in fields if field in values}
