"""The print server's HTTP API: native endpoints under ``/v1``, and the part of
OctoPrint's API that slicers and farm tools use, at ``/api`` (the default printer) and
``/printers/NAME/api`` (each printer, so a farm tool sees one OctoPrint per printer).

Every request that changes something needs the API key (``X-Api-Key``, or ``apikey``
in the query, as OctoPrint takes it). Errors are 4xx answers with a JSON body.
Models: OctoPrint's REST API (``/api/files/local``, ``/api/job``, ``/api/printer``) as
PrusaSlicer's ``OctoPrint.cpp`` uses it; Moonraker's queue endpoints.
"""

from __future__ import annotations

import asyncio
import functools
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from typing import Annotated, Any

from fastapi import (
    Depends,
    FastAPI,
    Path,
    Request,
)
from fastapi.exceptions import RequestValidationError
from fastapi.responses import (
    HTMLResponse,
    JSONResponse,
)
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException

import repetrel_host as rh
from repetrel_host.server import native
from repetrel_host.server.auth import RequestGuard, refusal
from repetrel_host.server.bodies import BodyBound
from repetrel_host.server.json_input import TOO_DEEP, JsonTooDeep
from repetrel_host.server.moonraker import make_face
from repetrel_host.server.moonraker import router as moonraker_router
from repetrel_host.server.mqtt.bridge import MqttBridge, MqttSettings
from repetrel_host.server.octoprint import appkeys, rest, sockjs
from repetrel_host.server.octoprint.push import Push
from repetrel_host.server.origins import OriginGuard, Origins, machine_names
from repetrel_host.server.print_server import PrintServer, server_of
from repetrel_host.session.workers import stop_workers

__all__ = ["PrintServer", "create_app"]


def _long_part_headers() -> None:
    """python-multipart refuses a form part whose header is over 4 KB, and Starlette gives
    no way to say otherwise: an upload named with 5,000 characters (OctoPrint takes it,
    and stores it shortened) was "Invalid multipart data.". Its parser, as Starlette makes
    it, takes headers of up to 64 KB."""
    import python_multipart

    module: Any = python_multipart  # its class replaced by a maker of it
    if not isinstance(module.MultipartParser, functools.partial):
        module.MultipartParser = functools.partial(module.MultipartParser, max_header_size=1 << 16)


def create_app(
    server: PrintServer, mqtt: MqttSettings | None = None, origins: Origins | None = None
) -> FastAPI:
    """The app of ``server``: its APIs and page; with ``mqtt``, its bridge to that broker;
    answering to the names of ``origins`` (default: the machine's own and IP addresses)."""
    _long_part_headers()
    push = Push(server)
    moonraker = make_face(server)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await _build_routes(app)
        await server.start()
        moonraker.start()
        bridge = None
        if mqtt is not None:
            bridge = asyncio.create_task(MqttBridge(server, mqtt).run(), name="mqtt")
        try:
            yield
        finally:
            await server.stop()  # SIGTERM: running jobs stop with their safe stop
            if bridge is not None:  # after the printers: their last events go out
                await asyncio.sleep(0.2)
                bridge.cancel()
                await asyncio.gather(bridge, return_exceptions=True)
            await moonraker.stop()
            server.close()
            await push.stop()
            stop_workers()

    app = FastAPI(title="repetrel-host print server", version=rh.__version__, lifespan=lifespan)
    app.state.server = server
    app.state.moonraker = moonraker
    app.add_middleware(RequestGuard, server=server)
    # Outside the key's check: a rebound name or another site's page goes no further.
    app.add_middleware(OriginGuard, server=server, origins=origins or Origins(machine_names()))
    # Around both guards: a body their refusals leave unread is read within its bound.
    app.add_middleware(BodyBound, server=server)
    app.add_middleware(SingleSlashes)

    @app.exception_handler(HTTPException)
    async def refused(request: Request, exc: HTTPException) -> JSONResponse:
        if isinstance(exc.__cause__, RecursionError):  # FastAPI's own read of a body
            return refusal(request.scope["path"], 400, TOO_DEEP)
        # OctoPrint's clients read "error"; FastAPI's read "detail": both say it.
        detail = exc.detail
        error = detail.get("error", detail) if isinstance(detail, dict) else detail
        # A refusal with more to say (a refused file's findings) says it at the top too.
        more: dict[str, Any] = detail if isinstance(detail, dict) else {}
        body = {**more, "error": error, "detail": detail}
        return JSONResponse(body, exc.status_code, headers=exc.headers)

    @app.exception_handler(JsonTooDeep)
    async def too_deep(request: Request, exc: JsonTooDeep) -> JSONResponse:
        return refusal(request.scope["path"], 400, TOO_DEEP)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in error['loc'])}: {error['msg']}" for error in exc.errors()
        )
        said = f"bad request: {problems}"
        return JSONResponse(status_code=400, content={"error": said, "detail": said})

    files = resources.files("repetrel_host.server").joinpath("page")
    page = files.joinpath("index.html").read_text()

    @app.get("/", include_in_schema=False)
    async def farm_page() -> HTMLResponse:
        """The page: every printer at a glance (the farm view)."""
        return HTMLResponse(page, headers={"Cache-Control": "no-cache"})

    @app.get("/printers/{name}", include_in_schema=False)
    async def printer_page(request: Request, name: str) -> HTMLResponse:
        """The page of one printer in full (its panels use only the public API)."""
        server_of(request).service(name)
        return HTMLResponse(page, headers={"Cache-Control": "no-cache"})

    # The page's scripts, styles and libraries: plain files, no build step.
    app.mount("/static", StaticFiles(directory=str(files)), name="static")

    app.include_router(native.router())
    if server.farm is not None:
        from repetrel_host.server.farm import api as farm_api

        app.include_router(farm_api.router())
    # OctoPrint's face, for the first printer and for each under /printers/NAME.
    for router in (appkeys.router(), rest.router(), rest.downloads()):
        app.include_router(router)
        app.include_router(router, prefix="/printers/{printer}", dependencies=[Depends(_printer)])
    sockets = sockjs.router(push)  # its own check of the printer: plain ASGI endpoints
    app.include_router(sockets)
    app.include_router(sockets, prefix="/printers/{printer}")
    # Moonraker's face, the same way (its paths meet none of the others).
    moonraker_routes = moonraker_router()
    app.include_router(moonraker_routes)
    app.include_router(moonraker_routes, prefix="/printers/{printer}")
    return app


async def _build_routes(app: FastAPI) -> None:
    """FastAPI builds a route's handling the first time a request walks past it in the
    route list: the first Moonraker call held the event loop 70 ms (every route before it
    built). A request that matches no route walks past them all, at start."""
    scope = {
        "type": "http",
        "method": "GET",
        "path": "/\0",
        "raw_path": b"/\0",
        "root_path": "",
        "query_string": b"",
        "headers": [],
    }

    async def receive() -> dict[str, Any]:
        return {"type": "http.request", "body": b""}

    async def send(message: Any) -> None:
        pass  # the "Not Found" answer of nobody's request

    await app.router(scope, receive, send)


def _printer(request: Request, printer: Annotated[str, Path()]) -> None:
    """``/printers/NAME/...``: 404 unless NAME is one of the server's printers."""
    server_of(request).service(printer)


class PrinterPorts:
    """A printer's own port (its ``moonraker_port``): a request that came to it is that
    printer's, as if it named ``/printers/NAME`` (for clients that take only a host and a
    port: Home Assistant's Moonraker integration, KlipperScreen)."""

    def __init__(self, app: Any, ports: dict[int, str]) -> None:
        self.app = app
        self.ports = ports

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        server = scope.get("server")
        name = self.ports.get(server[1]) if server and scope["type"] != "lifespan" else None
        if name is not None and not scope["path"].startswith(("/printers/", "/static/")):
            prefix = f"/printers/{name}"
            scope = {
                **scope,
                "path": prefix + scope["path"],
                "raw_path": prefix.encode() + scope.get("raw_path", scope["path"].encode()),
            }
        await self.app(scope, receive, send)


class SingleSlashes:
    """``//api/printer/bed`` is ``/api/printer/bed`` (Home Assistant's client joins its
    base URL and paths with one slash too many), as OctoPrint's server takes it."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket") and "//" in scope["path"]:
            path = re.sub("/{2,}", "/", scope["path"])
            scope = {**scope, "path": path, "raw_path": path.encode()}
        await self.app(scope, receive, send)
