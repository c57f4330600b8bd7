"""Who may do what: the API key on every request that changes something, checked before
a body is read."""

from __future__ import annotations

import hmac
from typing import Annotated, Any
from urllib.parse import parse_qsl

from fastapi import (
    Depends,
    Header,
    HTTPException,
    Query,
    Request,
)
from fastapi.responses import (
    JSONResponse,
)

from repetrel_host.server.core import PrintServer, server_of


def require_key(
    request: Request,
    x_api_key: Annotated[str | None, Header()] = None,
    apikey: Annotated[str | None, Query()] = None,
) -> None:
    """State-changing requests carry the API key."""
    given = x_api_key or apikey or ""
    if not hmac.compare_digest(given.encode(), server_of(request).api_key.encode()):
        raise HTTPException(403, "a valid API key is needed (the X-Api-Key header)")


Keyed = Depends(require_key)


class RequestGuard:
    """Before any body is read: a request that changes something needs the key (403), and
    a body over the upload limit is refused (413), chunked or not. FastAPI's own checks
    come after the body was parsed, which would let anyone fill the disk."""

    def __init__(self, app: Any, server: PrintServer) -> None:
        self.app = app
        self.server = server

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        server = self.server
        limit = server.max_upload + 65536  # the form's own bytes
        headers = {key.decode("latin-1").lower(): value for key, value in scope["headers"]}
        query = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))
        given = headers.get("x-api-key", b"").decode("latin-1") or query.get("apikey", "")
        if not hmac.compare_digest(given.encode(), server.api_key.encode()):
            detail = "a valid API key is needed (the X-Api-Key header)"
            await JSONResponse({"detail": detail}, 403)(scope, receive, send)
            return
        length = headers.get("content-length", b"")
        too_big = {"detail": f"the upload is over {server.max_upload} bytes"}
        if length.isdigit() and int(length) > limit:
            await JSONResponse(too_big, 413)(scope, receive, send)
            return
        received, over, started = 0, False, False

        async def counted() -> Any:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    over = True
                    return {"type": "http.disconnect"}  # the app stops reading
            return message

        async def watched(message: Any) -> None:
            nonlocal started
            if over:
                return  # the app's answer to a body cut short: ours goes instead
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, watched)
        except Exception:
            if not over:
                raise
        if over and not started:
            await JSONResponse(too_big, 413)(scope, receive, send)
