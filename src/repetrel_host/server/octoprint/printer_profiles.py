"""OctoPrint's printer profiles (``/printerprofiles``): one a printer, its machine, heated
bed and tools; its axes' speeds are the ones jogs and extrusions take."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request

from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.common import Printer
from repetrel_host.server.printers.service import PrinterService

AXIS_SPEEDS = {"x": 6000, "y": 6000, "z": 200, "e": 300}  # mm/min, the printer profile's


def router() -> APIRouter:
    """``/printerprofiles``: the printer's one profile."""
    router = APIRouter()

    @router.get("/printerprofiles")
    async def printer_profiles(request: Request, service: Printer) -> dict[str, Any]:
        profile = profile_of(service)
        return {"profiles": {profile["id"]: profile}}

    @router.get("/printerprofiles/{identifier}")
    async def printer_profile(service: Printer, identifier: str) -> dict[str, Any]:
        profile = profile_of(service)
        if identifier not in (profile["id"], "_default"):
            raise HTTPException(404, f"no printer profile '{identifier}'")
        return profile

    return router


def profile_of(service: PrinterService) -> dict[str, Any]:
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
        "axes": {axis: {"speed": speed, "inverted": False} for axis, speed in AXIS_SPEEDS.items()},
        "extruder": {
            "count": tools,
            "offsets": [[0.0, 0.0] for _ in range(tools)],
            "nozzleDiameter": 0.4,
            "sharedNozzle": False,
            "defaultExtrusionLength": 5,
        },
    }
