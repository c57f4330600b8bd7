"""How much of a request's body the server reads: each route's need, decided from its path
before a byte of the body is read, with a key or without. An upload may be as big as the
server's upload limit; a route open to anyone (a login, an app asking for a key, a
one-time link, the push socket's messages) takes a few KB; every other body (JSON, a
form's fields, a Moonraker database value, a G-code script) takes 2 MB. A body announced
bigger is refused at once; a body sent without its length (chunked) is cut where it passes
its bound, and the rest is never read: the refusal (413, in the face's own shape) closes
the connection."""

from __future__ import annotations

import re
from typing import Any

from fastapi.responses import JSONResponse

from repetrel_host.server.auth import refusal
from repetrel_host.server.print_server import PrintServer

# A form's own bytes around an upload's file: its boundaries, its part headers (a name of
# up to 64 KB, see app.py's _long_part_headers), its other fields.
FORM_BYTES = 65536
# A route open to anyone: a login's or an app key request's JSON, the SockJS messages of
# the push socket (OctoPrint's own bound on a client's message is 64 KB too).
OPEN_BODY = 64 * 1024
# Every other body, and a websocket's message: Moonraker's database takes values of up
# to 1 MB, a G-code script a few KB.
SMALL_BODY = 2 * 1024 * 1024

_PRINTER = r"(?:/printers/[^/]+)?"  # each printer's faces under /printers/NAME
# Where files are uploaded: OctoPrint's, Moonraker's, the native API's and the farm's.
_UPLOADS = re.compile(
    _PRINTER + r"/(?:api/files/local|server/files/upload)/?"
    r"|/v1/files|/v1/printers/[^/]+/jobs|/v1/farm/jobs|/farm/api/files/local"
)
_OPEN = re.compile(
    _PRINTER + r"/(?:api/login|api/logout|plugin/appkeys/(?:probe|request(?:/[^/]+)?)|sockjs/.*)"
    r"|/v1/links/redeem"
)


def body_bound(path: str, max_upload: int) -> tuple[int, str]:
    """The most bytes a body to ``path`` may have, and the sentence that refuses more."""
    if _UPLOADS.fullmatch(path):
        return max_upload + FORM_BYTES, f"the upload is over {max_upload} bytes"
    bound = OPEN_BODY if _OPEN.fullmatch(path) else SMALL_BODY
    return bound, f"the request's body is over {bound} bytes, the most {path} takes"


def too_big(path: str, said: str) -> JSONResponse:
    """413 in the shape of the face ``path`` belongs to; the connection is closed after it
    (the rest of the body is not read)."""
    return refusal(path, 413, said, {"Connection": "close"})


class BodyBound:
    """Every HTTP request's body bounded by its route's need (:func:`body_bound`), before
    anything reads it: over it, 413 instead of the app's answer. An answer given before
    the body was read (a refusal, a route that takes none) waits for the rest of it within
    the bound, so that the connection is kept and the client reads the answer; past the
    bound, the answer closes the connection (uvicorn would read any length for nothing)."""

    def __init__(self, app: Any, server: PrintServer) -> None:
        self.app = app
        self.server = server

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)  # a websocket's messages: uvicorn's ws_max_size
            return
        path = scope["path"]
        limit, said = body_bound(path, self.server.max_upload)
        headers = dict(scope["headers"])  # uvicorn's names are lower case
        length = headers.get(b"content-length", b"")
        if length.isdigit() and int(length) > limit:
            await too_big(path, said)(scope, receive, send)
            return
        received, over, started = 0, False, False
        ended = length in (b"", b"0") and b"transfer-encoding" not in headers  # no body
        # A client that waits for "100 Continue" before its body sends none unasked.
        unsent = headers.get(b"expect", b"").lower() == b"100-continue"

        async def counted() -> Any:
            nonlocal received, over, ended
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                ended = not message.get("more_body", False)
                if received > limit:
                    over = True
                    return {"type": "http.disconnect"}  # the app stops reading
            return message

        async def watched(message: Any) -> None:
            nonlocal started
            if over and not started:
                return  # the app's answer to a body cut short: ours goes instead
            if message["type"] == "http.response.start":
                started = True
                while not (ended or over or unsent):  # the rest of it, for nothing
                    if (await counted())["type"] == "http.disconnect":
                        break
                if not ended:
                    message = {**message, "headers": [*message.get("headers", []), CLOSE]}
            await send(message)

        try:
            await self.app(scope, counted, watched)
        except Exception:
            if not over:
                raise
        if over and not started:
            await too_big(path, said)(scope, receive, send)


CLOSE = (b"connection", b"close")
