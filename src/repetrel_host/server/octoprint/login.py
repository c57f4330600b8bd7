"""OctoPrint's login (``/login``, ``/logout``, ``/currentuser``): a client logs in
passively with its key and gets a session, for the push socket and the cookie."""

from __future__ import annotations

import contextlib
import secrets
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse

from repetrel_host.server.access import GROUPS, PERMISSIONS
from repetrel_host.server.auth import CSRF_COOKIE, SESSION_COOKIE, session_of, user_of
from repetrel_host.server.json_input import parse_json
from repetrel_host.server.print_server import server_of


def _user_json(user: str, session: str) -> dict[str, Any]:
    """The user a login answers with (OctoPrint's ``SessionUser.as_dict``)."""
    return {
        "name": user,
        "active": True,
        "permissions": PERMISSIONS,
        "groups": list(GROUPS),
        "needs": {"role": [p.lower() for p in PERMISSIONS], "group": list(GROUPS)},
        "apikey": None,
        "settings": {},
        "has_password": False,
        "session": session,
        "_is_external_client": False,
        "_login_mechanism": "apikey",
        "_credentials_seen": False,
        "_credentials_recheck_supported": False,
    }


def _guest() -> dict[str, Any]:
    """Nobody logged in (OctoPrint's anonymous user)."""
    return {"name": None, "groups": ["guests"], "permissions": [], "needs": {"group": ["guests"]}}


def router() -> APIRouter:
    """``/login``, ``/logout`` and ``/currentuser``."""
    router = APIRouter()

    @router.post("/login")
    async def login(request: Request) -> JSONResponse:
        """OctoPrint's login: ``passive`` with a key (or the session's cookie) answers as
        the key's user, with a session for the push socket and a cookie."""
        data: Any = None
        if request.headers.get("content-type", "").startswith("application/json"):
            with contextlib.suppress(ValueError):
                data = parse_json(await request.body())
        else:
            data = dict(await request.form())
        if not isinstance(data, dict):
            data = {}
        if "user" in data and "pass" in data:
            raise HTTPException(403, "the server has no passwords: log in passively with its key")
        if "passive" not in data:
            raise HTTPException(400, "Neither user and pass attributes nor passive flag present")
        user = user_of(request)
        if user is None:
            return JSONResponse(_guest())
        access = server_of(request).access
        session = session_of(request) or access.login(user)
        answer = JSONResponse(_user_json(user, session))
        answer.set_cookie(SESSION_COOKIE, session, httponly=True, samesite="lax")
        answer.set_cookie(CSRF_COOKIE, secrets.token_hex(16), samesite="strict")
        return answer

    @router.post("/logout")
    async def logout(request: Request) -> JSONResponse:
        session = session_of(request)
        if session is not None:
            server_of(request).access.logout(session)
        answer = JSONResponse(_guest())
        answer.delete_cookie(SESSION_COOKIE)
        return answer

    @router.get("/currentuser")
    async def current_user(request: Request) -> dict[str, Any]:
        user = user_of(request)
        if user is None:
            return {"name": None, "permissions": [], "groups": ["guests"]}
        return {"name": user, "permissions": PERMISSIONS, "groups": list(GROUPS)}

    return router
