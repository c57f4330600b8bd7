"""OctoPrint's system commands (``/system/commands``): the server runs none, and says so."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException
from fastapi.responses import Response


def router() -> APIRouter:
    """``/system/commands``: empty lists, and 404 for a command."""
    router = APIRouter()

    @router.get("/system/commands")
    async def system_commands() -> dict[str, list[Any]]:
        return {"core": [], "custom": []}

    @router.get("/system/commands/{source}")
    async def system_commands_of(source: str) -> list[Any]:
        if source not in ("core", "custom"):
            raise HTTPException(404, f"no system command source '{source}'")
        return []

    @router.post("/system/commands/{source}/{action}")
    async def system_command(source: str, action: str) -> Response:
        raise HTTPException(404, f"no system command {source}/{action} (the server runs none)")

    return router
