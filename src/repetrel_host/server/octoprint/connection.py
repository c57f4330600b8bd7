"""OctoPrint's connection (``/connection``): the printer's port and baud rate, and its
connect and disconnect."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException
from fastapi.responses import Response

from repetrel_host.server.octoprint import model
from repetrel_host.server.octoprint.common import OctoPrintCommand, Printer
from repetrel_host.server.octoprint.printer_profiles import profile_of
from repetrel_host.server.print_server import answered


def router() -> APIRouter:
    """``/connection``: its state (GET), connect or disconnect (POST)."""
    router = APIRouter()

    @router.get("/connection")
    async def connection(service: Printer) -> dict[str, Any]:
        printer = service.printer
        baud = printer.settings.baud if printer is not None else None
        profile = profile_of(service)["id"]
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
    async def connection_command(service: Printer, body: OctoPrintCommand) -> Response:
        if body.command == "connect":
            service.connect()
        elif body.command == "disconnect":
            await answered(service.disconnect())
        elif body.command == "fake_ack":
            pass  # the session never waits for an ok it lost (it asks again)
        else:
            raise HTTPException(400, f"command '{body.command}' is not connect or disconnect")
        return Response(status_code=204)

    return router
