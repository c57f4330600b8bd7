"""Moonraker's API (Klipper's API server) for the server's printers: Mainsail, Fluidd,
KlipperScreen, Home Assistant's Moonraker integration and klipperctl drive them unchanged."""

# The method tables fill as their modules are read.
from repetrel_host.server.moonraker import printer, server  # noqa: F401
from repetrel_host.server.moonraker.face import MoonrakerFace
from repetrel_host.server.moonraker.transport import router

__all__ = ["MoonrakerFace", "router"]
