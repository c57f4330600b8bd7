"""Who may do what: every request names a valid key or session (reads too, as on
OctoPrint, unless the server opens reads on purpose), checked before a body is read."""

from __future__ import annotations

import hmac
import re
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qsl

from fastapi import Request
from fastapi.responses import (
    JSONResponse,
)

from repetrel_host.server.print_server import PrintServer

SESSION_COOKIE = "hyrel_session"
CSRF_COOKIE = "hyrel_csrf"
NO_KEY = "a valid API key is needed (the X-Api-Key header)"
# Open to anyone: the page and its files (it asks for the key), asking for an app key (OctoPrint's
# appkeys plugin: an app has no key yet), opening a one-time link (the link lets in),
# logging in, the push socket's SockJS requests (the socket takes its own auth message, as
# OctoPrint's), the API's own description, and Moonraker's face (it answers as Moonraker
# does: 401, or a one-shot token's way in).
_OPEN = re.compile(
    r"/printers/[^/]+|/static/.*|(/printers/[^/]+)?/(printer|server|machine|access)/.*"
    r"|(/printers/[^/]+)?(/|/favicon\.ico|/api/login|/api/logout"
    r"|/plugin/appkeys/(probe|request|request/[^/]+)|/sockjs(/.*)?)"
    r"|/v1/links/redeem|/openapi\.json|/docs|/docs/oauth2-redirect|/redoc"
)
_READS = ("GET", "HEAD", "OPTIONS")
# Moonraker's OctoPrint-compatible endpoints (its components/octoprint_compat.py, with the
# upload it registers): on this face, a Moonraker trusted network opens exactly these, as
# Moonraker lets it in there (FDM Monster's Klipper printers ask /api/version first).
_MOONRAKER_OCTOPRINT = re.compile(
    r"GET (/printers/[^/]+)?/api/(version|server|currentuser|settings|job|printer"
    r"|printerprofiles)|POST (/printers/[^/]+)?/api/(login|printer/command|files/local)"
)
# Set in a request's state when a browser says a page of another site sent it (origins.py).
CROSS_SITE = "cross_site"
# Moonraker's paths, at the root or a printer's: its face refuses in its own shape.
_MOONRAKER = re.compile(r"(/printers/[^/]+)?(/(printer|server|machine|access)/.*|/websocket)")


def refusal(
    path: str, status: int, said: str, headers: dict[str, str] | None = None
) -> JSONResponse:
    """A refusal made before any route, in the shape of the face ``path`` belongs to:
    Moonraker's ``{"error": {"code", "message"}}`` on its paths, else ``error`` (what
    OctoPrint's clients read) and ``detail`` (FastAPI's)."""
    if _MOONRAKER.fullmatch(path):
        moonrakers = {"code": status, "message": said, "traceback": ""}
        return JSONResponse({"error": moonrakers}, status, headers=headers)
    return JSONResponse({"error": said, "detail": said}, status, headers=headers)


def user_of(request: Request) -> str | None:
    """Who made ``request`` (its key's or session's user); None when nobody is named (the
    server opens reads, or the route is open)."""
    user: str | None = request.scope.get("state", {}).get("user")
    return user


def session_of(request: Request) -> str | None:
    """The login session ``request`` came with (its cookie), if any."""
    session: str | None = request.scope.get("state", {}).get("session")
    return session


def identify(server: PrintServer, scope: Any, cookie: bool = True) -> tuple[str | None, str | None]:
    """``(user, session)`` that the request names: a key (``X-Api-Key``, ``apikey`` in the
    query, ``Authorization: Bearer``), else, with ``cookie``, the login's session cookie
    (with the CSRF token a change needs, as OctoPrint asks of a cookie)."""
    given = given_key(scope)
    if given:
        return server.access.user_for_key(given), None
    if not cookie:
        return None, None
    headers = {key.decode("latin-1").lower(): value for key, value in scope["headers"]}
    cookies = SimpleCookie()
    cookies.load(headers.get("cookie", b"").decode("latin-1"))
    session = cookies[SESSION_COOKIE].value if SESSION_COOKIE in cookies else ""
    user = server.access.user_for_session(session)
    if user is None:
        return None, None
    if scope.get("method", "GET") not in _READS:
        csrf = cookies[CSRF_COOKIE].value if CSRF_COOKIE in cookies else ""
        token = headers.get("x-csrf-token", b"").decode("latin-1")
        if not csrf or not hmac.compare_digest(csrf.encode(), token.encode()):
            return None, None
    return user, session


def given_key(scope: Any) -> str:
    """The key a request names (``X-Api-Key``, ``apikey`` in the query, ``Authorization:
    Bearer``), valid or not; "" when it names none."""
    headers = {key.decode("latin-1").lower(): value for key, value in scope["headers"]}
    given: str = headers.get("x-api-key", b"").decode("latin-1")
    if not given:
        query = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))
        given = query.get("apikey", "")
    bearer = headers.get("authorization", b"").decode("latin-1")
    if not given and bearer.lower().startswith("bearer "):
        given = bearer[7:].strip()
    return given


def trusted_octoprint(server: PrintServer, scope: Any) -> bool:
    """``scope`` asks one of Moonraker's OctoPrint-compatible endpoints from a Moonraker
    trusted network (``moonraker_trusted_clients``)."""
    asked = f"{scope.get('method', 'GET')} {scope['path']}"
    return _MOONRAKER_OCTOPRINT.fullmatch(asked) is not None and trusted(server, scope)


def trusted(server: PrintServer, scope: Any) -> bool:
    """``scope`` comes from a trusted network (``moonraker_trusted_clients``), and not from
    a page of another site that a browser there opened: such a page could send G-code with a
    form or an image's address, and a trusted network asks for no key (origins.py marks it;
    ``cors_domains`` lets a page in)."""
    client = scope.get("client")
    if scope.get("state", {}).get(CROSS_SITE):
        return False
    return server.access.trusts(client[0] if client else None)


class RequestGuard:
    """Before any body is read: a request needs a valid key or session (403; reads pass
    without one where the server opens them). FastAPI's own checks come after the body was
    parsed, which would let anyone fill the disk. Who asked goes into the request's state."""

    def __init__(self, app: Any, server: PrintServer) -> None:
        self.app = app
        self.server = server

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)  # the push socket asks for its own auth
            return
        server = self.server
        user, session = identify(server, scope)
        scope["state"] = {**scope.get("state", {}), "user": user, "session": session}
        open_route = _OPEN.fullmatch(scope["path"]) is not None
        reading = scope["method"] in _READS
        if user is None and not open_route and not (reading and server.access.public_read):
            if not trusted_octoprint(server, scope):
                await refusal(scope["path"], 403, NO_KEY)(scope, receive, send)
                return
            if given_key(scope):  # a wrong key: 401 whatever the network, as on Moonraker
                await refusal(scope["path"], 401, NO_KEY)(scope, receive, send)
                return
        await self.app(scope, receive, send)  # its body bounded next (bodies.py)
