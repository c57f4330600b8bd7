"""What OctoPrint's REST routes share: the printer a request is for, OctoPrint's command
bodies and flags, and the check that the printer is operational (with OctoPrint's sentence
when it is not)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from pydantic import BaseModel

from repetrel_host.server import jobs
from repetrel_host.server.octoprint import model
from repetrel_host.server.print_server import PrintServer, server_of
from repetrel_host.server.printers.service import PrinterService, Refused
from repetrel_host.server.store import JobRecord

_TRUE = ("true", "1", "yes", "y")
NOT_OPERATIONAL = "Printer is not operational"


class OctoPrintCommand(BaseModel):
    """OctoPrint's command bodies: ``{"command": ..., ...}`` with the command's fields."""

    model_config = {"extra": "allow"}
    command: str

    def get(self, name: str, default: Any = None) -> Any:
        return (self.model_extra or {}).get(name, default)


def is_true(value: object) -> bool:
    """An OctoPrint flag (a form's or body's): true, or a string such as "true" or "yes"."""
    return value is True or str(value).strip().lower() in _TRUE


def _service_for(request: Request) -> PrinterService:
    """The printer in the path (``/printers/NAME/api/...``), else the default one."""
    return server_of(request).service(request.path_params.get("printer"))


Printer = Annotated[PrinterService, Depends(_service_for)]


def operational(service: PrinterService) -> str:
    """The printer's state text; 409 (OctoPrint's sentence) unless it is operational."""
    text = model.state_text(service)
    if not model.flags(service, text)["operational"]:
        raise HTTPException(409, NOT_OPERATIONAL)
    return text


def start(
    server: PrintServer,
    service: PrinterService,
    path: Path,
    commands: int,
    user: str | None,
    via: str,
    first: bool = False,
) -> JobRecord:
    """OctoPrint's start of a file (select's print, the job's start, a restart): the
    server's one rule (:func:`jobs.start`: a held queue is released); 409 with why when
    every start waits for a release."""
    try:
        return jobs.start(server, service, path, commands, user, via, first)
    except Refused as exc:
        raise HTTPException(409, str(exc)) from None
