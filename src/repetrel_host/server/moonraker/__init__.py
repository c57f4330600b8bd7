"""Moonraker's API (Klipper's API server) for the server's printers: Mainsail, Fluidd,
KlipperScreen, Home Assistant's Moonraker integration and klipperctl drive them unchanged."""

from repetrel_host.server.moonraker import database, files, history, printer, server
from repetrel_host.server.moonraker.face import MoonrakerFace
from repetrel_host.server.moonraker.transport import router
from repetrel_host.server.print_server import PrintServer

__all__ = ["MoonrakerFace", "make_face", "router"]

# Every method module above is read here: reading one fills the method table.
_METHODS = (printer, server, files, history, database)


def make_face(print_server: PrintServer) -> MoonrakerFace:
    """The face of ``print_server``, its notifications of files and jobs wired."""
    face = MoonrakerFace(print_server)
    files.tell_file_changes(face)
    history.tell_job_changes(face)
    return face
