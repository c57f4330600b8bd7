"""OctoPrint's settings (``/settings``): the parts that clients read, from the server's
own configuration (which lives in its TOML file: nothing here changes it)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from repetrel_host.server.octoprint.common import Printer
from repetrel_host.server.print_server import PrintServer, server_of
from repetrel_host.server.printers.service import PrinterService


def router() -> APIRouter:
    """``/settings``: read, and (changing nothing) written."""
    router = APIRouter()

    @router.get("/settings")
    async def settings(request: Request, service: Printer) -> dict[str, Any]:
        return _settings(request, server_of(request), service)

    @router.post("/settings")
    async def change_settings(request: Request, service: Printer) -> dict[str, Any]:
        # The server's settings live in its TOML file: nothing here changes them.
        return _settings(request, server_of(request), service)

    return router


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
