"""OctoPrint's version, as ``/api/version`` and ``/api/server`` say it (and the push
socket's ``connected`` message)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

import repetrel_host as rh

# What /api/version says: PrusaSlicer checks that "text" starts with "OctoPrint".
OCTOPRINT_VERSION = "1.11.8"
API_VERSION = "0.1"


def router() -> APIRouter:
    """``/version`` and ``/server``: which OctoPrint this server answers as."""
    router = APIRouter()

    @router.get("/version")
    async def version() -> dict[str, str]:
        return {
            "api": API_VERSION,
            "server": OCTOPRINT_VERSION,
            "text": f"OctoPrint {OCTOPRINT_VERSION} (repetrel-host {rh.__version__})",
        }

    @router.get("/server")
    async def server_info() -> dict[str, Any]:
        # "server" too: Moonraker's OctoPrint-compatible /api/server says it there.
        return {
            "version": OCTOPRINT_VERSION,
            "server": OCTOPRINT_VERSION,
            "safemode": None,
            "online": True,
        }

    return router
