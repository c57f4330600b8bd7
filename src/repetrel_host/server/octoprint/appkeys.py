"""OctoPrint's appkeys plugin (``octoprint/plugins/appkeys``): an application asks for a
key, a person allows or denies it on the status page, the application polls for the
answer. Home Assistant's OctoPrint integration has no other way to set up.

The routes are ``/plugin/appkeys/...`` (the request, open to anyone: an app has no key
yet), ``/api/plugin/appkeys`` (the keys and pending requests, for a user only: a
request's ``user_token`` decides it), both at the
server's root and under ``/printers/NAME``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse, RedirectResponse, Response

from repetrel_host.server.access import OWNER, AppKey
from repetrel_host.server.auth import user_of
from repetrel_host.server.events import AppKeyEvent
from repetrel_host.server.json_input import parse_json
from repetrel_host.server.print_server import PrintServer, server_of


async def _body(request: Request) -> dict[str, Any]:
    """The JSON body, or 400 "Missing data" (OctoPrint's sentence)."""
    try:
        data = parse_json(await request.body())
    except ValueError:
        data = None
    if not isinstance(data, dict):
        raise HTTPException(400, "Missing data")
    return data


def _base(request: Request) -> str:
    base = str(request.base_url).rstrip("/")
    printer = request.path_params.get("printer")
    return f"{base}/printers/{printer}" if printer else base


def _named(app: object) -> str:
    if not isinstance(app, str) or not app.strip():
        raise HTTPException(400, "No app name provided")
    if len(app) > 200:
        raise HTTPException(400, "the app name is over 200 characters")
    return app.strip()


def user_needed(request: Request) -> str:
    """Who asks (a key's or session's user); 403 for nobody: the keys and requests are a
    user's business, even where the server opens reads."""
    user = user_of(request)
    if user is None:  # the server opens reads: a key still decides who may grant keys
        raise HTTPException(403, "a valid API key is needed (the X-Api-Key header)")
    return user


def router() -> APIRouter:
    router = APIRouter()

    @router.get("/plugin/appkeys/probe", status_code=204)
    async def probe() -> Response:
        return Response(status_code=204)

    @router.post("/plugin/appkeys/request", status_code=201)
    async def request_key(request: Request) -> JSONResponse:
        data = await _body(request)
        app = _named(data.get("app"))
        user = data.get("user") or None
        server = server_of(request)
        remote = request.client.host if request.client is not None else ""
        pending = server.access.request(app, remote, user if isinstance(user, str) else None)
        server.events.publish(AppKeyEvent("request", **pending.public()))
        base = _base(request)
        answer = {
            "app_token": pending.app_token,
            "auth_dialog": f"{base}/plugin/appkeys/auth/{pending.app_token}",
        }
        location = f"{base}/plugin/appkeys/request/{pending.app_token}"
        return JSONResponse(answer, 201, headers={"Location": location})

    @router.get("/plugin/appkeys/request/{app_token}")
    async def poll(request: Request, app_token: str) -> JSONResponse:
        pending = server_of(request).access.poll(app_token)
        if pending is None:
            raise HTTPException(404, "no such request: denied, expired or never made")
        if pending.granted is None:
            return JSONResponse({"message": "Awaiting decision"}, 202)
        return JSONResponse({"api_key": pending.granted})

    @router.get("/plugin/appkeys/auth/{app_token}")
    async def auth_dialog(request: Request, app_token: str) -> RedirectResponse:
        # A person decides on the status page, which lists every request.
        return RedirectResponse("/#access", status_code=303)

    @router.post("/plugin/appkeys/decision/{user_token}", status_code=204)
    async def decide(request: Request, user_token: str) -> Response:
        data = await _body(request)
        if "decision" not in data:
            raise HTTPException(400, "No decision provided")
        allow = data["decision"] is True or str(data["decision"]).lower() in ("true", "1", "yes")
        decided(server_of(request), user_token, allow, user_needed(request))
        return Response(status_code=204)

    @router.get("/api/plugin/appkeys")
    async def keys(request: Request) -> dict[str, Any]:
        # OctoPrint answers a named user only, even where reads are open: a pending
        # request's user_token decides it.
        user_needed(request)
        server = server_of(request)
        app = request.query_params.get("app")
        if app:
            found = [k for k in server.access.app_keys() if k.app == app]
            if not found:
                raise HTTPException(404, f"no key for app '{app}'")
            return {"key": key_json(found[0])}
        return {
            "keys": [key_json(k) for k in server.access.app_keys()],
            "pending": {p.user_token: p.public() for p in server.access.pending()},
        }

    @router.post("/api/plugin/appkeys")
    async def key_command(request: Request) -> Response:
        data = await _body(request)
        server = server_of(request)
        user = user_needed(request)
        command = data.get("command")
        if command == "revoke":
            app, key = data.get("app"), data.get("key")
            if isinstance(key, str) and key:
                app = next((k.app for k in server.access.app_keys() if k.key == key), None)
            if not isinstance(app, str) or not server.access.revoke(app):
                raise HTTPException(400, "Need either app or key")
            server.events.publish(AppKeyEvent("revoked", app))
            return Response(status_code=204)
        if command == "generate":
            granted = server.access.grant(_named(data.get("app")), user)
            server.events.publish(AppKeyEvent("granted", granted.app))
            return JSONResponse(
                {"user_id": granted.user, "app_id": granted.app, "api_key": granted.key}
            )
        raise HTTPException(400, f"command '{command}' is not generate or revoke")

    return router


def decided(server: PrintServer, user_token: str, allow: bool, user: str = OWNER) -> None:
    """A person's decision on a request; 404 when there is none (any more)."""
    pending = server.access.decide(user_token, allow, user)
    if pending is None:
        raise HTTPException(404, "no such request: already decided, or the app stopped asking")
    server.events.publish(AppKeyEvent("granted" if allow else "denied", **pending.public()))


def key_json(key: AppKey) -> dict[str, Any]:
    """An app key as OctoPrint lists it: whose and for what, never the key itself."""
    return {"app_id": key.app, "user_id": key.user, "created": int(key.created)}
