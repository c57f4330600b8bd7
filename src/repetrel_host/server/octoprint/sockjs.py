"""The push socket's transports, as OctoPrint 1.11 serves them (its vendored SockJS server,
``octoprint/server/util/sockjs.py``): ``/sockjs`` speaks SockJS (``/sockjs/info``; the
websocket, xhr-streaming and xhr-polling transports at ``/sockjs/SERVER/SESSION/...``);
``/sockjs/websocket`` is the raw websocket, one JSON object a message.
``/printers/NAME/sockjs...`` is printer NAME's, and the root the default printer's, as the
REST face. What goes through them is :mod:`.push`'s.

No SockJS server library fits Starlette (those on PyPI serve aiohttp, Tornado, Sanic or
Django), and SockJS's framing is small: it is written here.
"""

from __future__ import annotations

import asyncio
import json
import random
import re
from collections.abc import Callable, Iterable
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from starlette.routing import WebSocketRoute
from starlette.types import Receive, Scope, Send

from repetrel_host.server.json_input import JsonTooDeep, parse_json
from repetrel_host.server.octoprint.messages import Frame
from repetrel_host.server.octoprint.push import INCOMING_MOST, Client, Push

HEARTBEAT = 25.0  # SockJS: an "h" frame after this long without one
DISCONNECT_DELAY = 5.0  # SockJS: an xhr session no request waits on this long is closed
RESPONSE_LIMIT = 128 * 1024  # SockJS: an xhr-streaming response ends after this many bytes
_SESSION_ID = re.compile(r"[^/.]+")


def _sockjs_messages(text: str) -> Iterable[Any]:
    """The messages of one SockJS frame from a client: a JSON list of strings, or one
    string; octorest's ``send`` writes a bare object, taken as one message."""
    try:
        data = parse_json(text)
    except (ValueError, JsonTooDeep):
        return ()
    return data if isinstance(data, list) else (data,)


def _array(frames: list[Frame]) -> str:
    """A SockJS message frame. OctoPrint's holds the messages themselves, JSON objects
    (its session wrapper skips SockJS's quoting them as strings): clients expect that."""
    return "a[" + ",".join(frame.text for frame in frames) + "]"


def _close_frame(code: int, reason: str) -> str:
    return f"c[{code},{json.dumps(reason)}]"


GO_AWAY = _close_frame(3000, "Go away!")
ANOTHER = _close_frame(2010, "Another connection still open")


def _cors(request: Request, methods: str | None = None) -> dict[str, str]:
    """SockJS's CORS headers: the origin that asked, with credentials (as sockjs-tornado)."""
    headers = {
        "Access-Control-Allow-Origin": request.headers.get("origin", "*"),
        "Access-Control-Allow-Credentials": "true",
    }
    asked = request.headers.get("access-control-request-headers")
    if asked:
        headers["Access-Control-Allow-Headers"] = asked
    if methods is not None:
        headers["Access-Control-Allow-Methods"] = methods
        headers["Allow"] = methods
        headers["Cache-Control"] = "max-age=31536000, public"
        headers["Access-Control-Max-Age"] = "31536000"
    return headers


NO_CACHE = {"Cache-Control": "no-store, no-cache, must-revalidate, max-age=0"}


class XhrSession:
    """A SockJS session of the xhr transports: its client outlives each request, and is
    closed once no request waited on it for :data:`DISCONNECT_DELAY` seconds."""

    def __init__(
        self, sessions: dict[tuple[str, str], XhrSession], key: tuple[str, str], client: Client
    ) -> None:
        self.sessions = sessions  # the sessions it is one of
        self.key = key
        self.client = client
        self.attached = False
        self.opened = False  # its "o" frame went
        self._expiry: asyncio.TimerHandle | None = None
        self._detached()

    def attach(self) -> None:
        self.attached = True
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def detach(self) -> None:
        self.attached = False
        self._detached()

    def _detached(self) -> None:
        loop = asyncio.get_running_loop()
        self._expiry = loop.call_later(DISCONNECT_DELAY, self.end)

    def end(self) -> None:
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        self.client.close("the SockJS session ended")
        if self.sessions.get(self.key) is self:
            del self.sessions[self.key]


class XhrResponse(Response):
    """An xhr-streaming (``streaming``) or xhr-polling response of a SockJS session."""

    media_type = "application/javascript; charset=UTF-8"

    def __init__(self, session: XhrSession, streaming: bool, headers: dict[str, str]) -> None:
        super().__init__(headers=headers)
        self.session = session
        self.streaming = streaming

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        session, client = self.session, self.session.client
        headers = [(k, v) for k, v in self.raw_headers if k != b"content-length"]
        await send({"type": "http.response.start", "status": 200, "headers": headers})

        async def body(text: str, more: bool = True) -> None:
            await send({"type": "http.response.body", "body": text.encode(), "more_body": more})

        if self.streaming:
            await body("h" * 2048 + "\n")
        if client.closed:
            await body(GO_AWAY + "\n", False)
            return
        if session.attached:
            await body(ANOTHER + "\n", False)
            return
        session.attach()
        writer = asyncio.ensure_future(self._write(body))
        client.writer = writer
        gone = asyncio.ensure_future(_disconnected(receive))
        try:
            await asyncio.wait({writer, gone}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            writer.cancel()
            gone.cancel()
            client.writer = None
            if (gone.done() and not gone.cancelled()) or client.closed:
                session.end()  # the client went (or was dropped): as sockjs-tornado
            else:
                session.detach()
        if writer.done() and not writer.cancelled() and writer.exception() is None:
            await body("", False)

    async def _write(self, body: Callable[[str, bool], Any]) -> None:
        session, client = self.session, self.session.client
        if not session.opened:
            session.opened = True
            await body("o\n", True)
            if not self.streaming:
                return
        sent = 0
        while sent < RESPONSE_LIMIT:
            frames = await client.take(HEARTBEAT)
            if client.closed:
                await body(GO_AWAY + "\n", True)
                return
            chunk = (_array(frames) if frames else "h") + "\n"
            await body(chunk, True)
            if not self.streaming:
                return
            sent += len(chunk)


async def _disconnected(receive: Receive) -> None:
    while (await receive())["type"] != "http.disconnect":
        pass


class SocketEndpoint:
    """A websocket: SockJS framed (``o``, ``h``, ``a[...]``, ``c[...]``) or raw (one JSON
    object a message). A plain ASGI app: each message goes out in one ASGI send."""

    def __init__(self, push: Push, sockjs: bool) -> None:
        self.push = push
        self.sockjs = sockjs

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (await receive())["type"] != "websocket.connect":
            return
        try:
            feed = self.push.feed(scope.get("path_params", {}).get("printer"))
        except HTTPException:
            await send({"type": "websocket.close", "code": 1008})  # no such printer
            return
        await send({"type": "websocket.accept"})
        sockjs = self.sockjs
        address = scope["client"][0] if scope.get("client") else ""
        client = Client(feed, f"{address} ({'SockJS' if sockjs else 'raw'} websocket)")

        async def text(message: str) -> None:
            await send({"type": "websocket.send", "text": message})

        async def write() -> None:
            if sockjs:
                await text("o")
            while True:
                frames = await client.take(HEARTBEAT if sockjs else None)
                if client.closed:
                    if sockjs:
                        await text(GO_AWAY)
                    await send({"type": "websocket.close", "code": 3000, "reason": "Go away!"})
                    return
                if sockjs:
                    await text(_array(frames) if frames else "h")
                else:
                    for frame in frames:
                        await text(frame.text)

        async def read() -> None:
            while True:
                message = await receive()
                if message["type"] == "websocket.disconnect":
                    client.close(f"the client went (code {message.get('code')})")
                    return
                data = message.get("text")
                if data is None:
                    data = (message.get("bytes") or b"").decode("utf-8", "replace")
                if not data or len(data) > INCOMING_MOST:
                    continue  # SockJS: an empty message is ignored
                for each in _sockjs_messages(data) if sockjs else (data,):
                    client.receive(each)

        writer = asyncio.ensure_future(write())
        reader = asyncio.ensure_future(read())
        client.writer = writer
        feed.add(client)
        try:
            await asyncio.wait({writer, reader}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            client.close("the connection ended")
            for task in (writer, reader):
                task.cancel()
            await asyncio.gather(writer, reader, return_exceptions=True)


def router(push: Push) -> APIRouter:
    """The push socket's routes: include at the root and under ``/printers/{printer}``."""
    router = APIRouter(include_in_schema=False)
    sessions: dict[tuple[str, str], XhrSession] = {}  # by printer and session id

    def end_sessions() -> None:
        for session in list(sessions.values()):
            session.end()

    push.on_stop.append(end_sessions)

    @router.get("/sockjs")
    @router.get("/sockjs/")
    async def greeting() -> PlainTextResponse:
        return PlainTextResponse("Welcome to SockJS!\n")

    @router.get("/sockjs/info")
    async def info(request: Request) -> JSONResponse:
        push.server.service(request.path_params.get("printer"))  # 404: no such printer
        return JSONResponse(
            {
                "websocket": True,
                "cookie_needed": False,
                "origins": ["*:*"],
                "entropy": random.randint(0, 2**31 - 1),
            },
            headers={**_cors(request), **NO_CACHE},
        )

    @router.options("/sockjs/info")
    async def info_options(request: Request) -> Response:
        return Response(status_code=204, headers=_cors(request, "OPTIONS, GET"))

    router.routes.append(WebSocketRoute("/sockjs/websocket", SocketEndpoint(push, False)))
    sockjs = SocketEndpoint(push, True)
    router.routes.append(WebSocketRoute("/sockjs/{server_id}/{session_id}/websocket", sockjs))

    def session_of(request: Request, session_id: str, create: bool) -> XhrSession | None:
        if _SESSION_ID.fullmatch(session_id) is None:
            raise HTTPException(404, "not a SockJS session id")
        feed = push.feed(request.path_params.get("printer"))
        key = (feed.name, session_id)
        session = sessions.get(key)
        if session is None and create:
            address = request.client.host if request.client is not None else ""
            client = Client(feed, f"{address} (SockJS xhr)")
            session = sessions[key] = XhrSession(sessions, key, client)
            feed.add(client)
        return session

    async def xhr(request: Request, session_id: str, streaming: bool) -> XhrResponse:
        session = session_of(request, session_id, create=True)
        assert session is not None
        return XhrResponse(session, streaming, {**_cors(request), **NO_CACHE})

    @router.post("/sockjs/{server_id}/{session_id}/xhr_streaming")
    async def xhr_streaming(request: Request, server_id: str, session_id: str) -> XhrResponse:
        return await xhr(request, session_id, streaming=True)

    @router.post("/sockjs/{server_id}/{session_id}/xhr")
    async def xhr_polling(request: Request, server_id: str, session_id: str) -> XhrResponse:
        return await xhr(request, session_id, streaming=False)

    @router.post("/sockjs/{server_id}/{session_id}/xhr_send")
    async def xhr_send(request: Request, server_id: str, session_id: str) -> Response:
        session = session_of(request, session_id, create=False)
        headers = {**_cors(request), **NO_CACHE}
        if session is None or session.client.closed:
            return PlainTextResponse("no such SockJS session", 404, headers=headers)
        body = await request.body()
        if not body:
            return PlainTextResponse("Payload expected.", 400, headers=headers)
        if len(body) > INCOMING_MOST:
            return PlainTextResponse("the message is too long", 413, headers=headers)
        try:
            messages = parse_json(body)
        except ValueError:
            return PlainTextResponse("Broken JSON encoding.", 400, headers=headers)
        except JsonTooDeep as exc:
            return PlainTextResponse(str(exc), 400, headers=headers)
        for message in messages if isinstance(messages, list) else (messages,):
            session.client.receive(message)
        return Response(status_code=204, headers={**headers, "Content-Type": "text/plain"})

    for transport in ("xhr", "xhr_streaming", "xhr_send"):

        @router.options(f"/sockjs/{{server_id}}/{{session_id}}/{transport}")
        async def xhr_options(request: Request, server_id: str, session_id: str) -> Response:
            return Response(status_code=204, headers=_cors(request, "OPTIONS, POST"))

    return router
