"""Moonraker's transports: its methods over HTTP (``/printer/...``, ``/server/...``,
``/machine/...``, ``/access/...``, answered as ``{"result": ...}``) and over JSON-RPC 2.0 at
``/websocket`` (batches, notifications, the subscription's changes), for the first printer
at the root and for each at ``/printers/NAME/...``.

Model: Moonraker 0.11 (``moonraker/common.py``'s ``APIDefinition``, ``application.py``'s
``DynamicRequestHandler`` and ``websockets.py``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from typing import Any
from urllib.parse import parse_qsl

from fastapi import APIRouter, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import Headers, UploadFile
from starlette.exceptions import HTTPException

from repetrel_host.server.auth import identify, trusted
from repetrel_host.server.events import PrinterState, ServerEvent
from repetrel_host.server.json_input import JsonTooDeep, parse_json
from repetrel_host.server.moonraker import rpc
from repetrel_host.server.moonraker.face import MoonrakerFace
from repetrel_host.server.moonraker.objects import eventtime, klippy_state
from repetrel_host.server.printers.service import PrinterService

log = logging.getLogger("repetrel_host.server.moonraker")

AREAS = ("printer", "server", "machine", "access")
STATUS_EVERY = 0.25  # s: a subscription's changes go out this often (Klipper's)
PROC_STAT_EVERY = 1.0  # s: Moonraker's; Mainsail drops a socket silent for 10 s
OUTBOX = 2000  # messages a websocket may have unsent before it is closed
OUTBOX_BYTES = 32 << 20  # or bytes (a client that asks for big answers and reads none)
# A JSON-RPC batch: at most this many calls, answered in at most this many bytes (a batch
# is one message: the calls run one after the other, its answer waits for them all).
BATCH_CALLS = 100
BATCH_ANSWER_BYTES = 4 << 20


def _query(scope: Any) -> list[tuple[str, str]]:
    return parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)


def _service(face: MoonrakerFace, printer: str | None) -> PrinterService:
    service = face.server.services.get(printer or face.server.default)
    if service is None:
        raise rpc.RpcError(404, f"no printer '{printer}'")
    return service


def who(face: MoonrakerFace, scope: Any) -> str | None:
    """Who made the request (None: a trusted network's client), in Moonraker's order
    (``authorization.py``): a live one-shot ``?token=`` (an unknown one is ignored:
    KlipperScreen sends ``token=False``), else a key, else a trusted network; 401
    "Unauthorized" when none. A wrong key is refused whatever the network, as Moonraker
    refuses it (its log says "Invalid API Key"; the answer, Tornado's "Unauthorized").
    The server's open reads (``public_read``) do not open this face: a read here (a
    one-shot token, a websocket) leads to everything. Nor does the page's session cookie:
    Moonraker takes none, and a browser sends it with another site's websocket or request
    too."""
    for name, value in _query(scope):
        if name == "token":
            valid, owner = face.redeem(value)
            if valid:
                return owner
    key = _key(scope)
    if key:
        user = face.server.access.user_for_key(key)
        if user is None:
            raise rpc.RpcError(401, rpc.UNAUTHORIZED.message)
        return user
    user, _ = identify(face.server, scope, cookie=False)  # OctoPrint's ?apikey= too
    if user is not None:
        return user
    if trusted(face.server, scope):
        return None
    raise rpc.RpcError(401, rpc.UNAUTHORIZED.message)


def _key(scope: Any) -> str:
    """The key a request names where Moonraker reads one: ``X-Api-Key``, ``Authorization:
    Bearer``, ``X-Access-Token`` or ``?access_token=`` (Moonraker's login tokens: this
    server makes none, so such a token is one of its keys or wrong)."""
    headers = Headers(scope=scope)
    bearer = headers.get("authorization", "")
    key = headers.get("x-api-key") or headers.get("x-access-token")
    if not key and bearer[:7].lower() == "bearer ":  # as auth.given_key reads it
        key = bearer[7:].strip()
    if not key:
        key = dict(_query(scope)).get("access_token", "")
    return key


def face_of(request: Request | WebSocket) -> MoonrakerFace:
    face: MoonrakerFace = request.app.state.moonraker
    return face


def error_body(refused: rpc.RpcError) -> JSONResponse:
    """Moonraker's error answer: its status, and ``{"error": {"code", "message"}}``."""
    status, message = refused.status, refused.message
    return JSONResponse({"error": {"code": status, "message": message, "traceback": ""}}, status)


# --- HTTP ----------------------------------------------------------------------------------


def router() -> APIRouter:
    """Moonraker's HTTP paths and ``/websocket``."""
    router = APIRouter(include_in_schema=False)
    for area in AREAS:
        router.add_api_route(
            f"/{area}/{{rest:path}}", _http, methods=["GET", "POST", "DELETE"], name=area
        )
    router.add_api_websocket_route("/websocket", _websocket)
    return router


async def _http(request: Request, rest: str) -> Response:
    face = face_of(request)
    try:
        user = who(face, request.scope)
    except rpc.RpcError as exc:
        return error_body(exc)
    path = request.url.path
    if "printer" in request.path_params:  # /printers/NAME/server/info
        path = "/" + path.split("/", 3)[3]
    verb = request.method
    if (path, verb) == ("/server/jsonrpc", "POST"):  # JSON-RPC over HTTP
        try:
            service = _service(face, request.path_params.get("printer"))
        except rpc.RpcError as exc:
            return error_body(exc)
        answer = await answer_rpc(face, service, user, await request.body())
        return Response("null" if answer is None else answer, media_type="application/json")
    found, given = rpc.METHODS.route(path, verb)
    if found is None:
        known = rpc.METHODS.knows(path)
        missing = (
            rpc.RpcError(405, "Method Not Allowed") if known else rpc.RpcError(404, "Not Found")
        )
        return error_body(missing)
    try:
        args = rpc.query_args(_query(request.scope))
        args.update(await _body(request))
        args.update(given)
        service = _service(face, request.path_params.get("printer"))
        connection = _named_websocket(face, service, args.get("connection_id"))
        args = {k: v for k, v in args.items() if k not in rpc.EXCLUDED}
        call = rpc.Call(face, service, user, args, connection, base_url=str(request.base_url))
        result = await rpc.call(found, call)
    except rpc.RpcError as exc:
        return error_body(exc)
    if isinstance(result, Response):
        return result  # an upload's 201, a file's bytes
    return JSONResponse({"result": result})


def _named_websocket(face: MoonrakerFace, service: PrinterService, named: Any) -> Connection | None:
    """The websocket an HTTP request names by its ``connection_id`` (what
    ``server.connection.identify`` and ``server.websocket.id`` gave it), as Moonraker's
    ``get_associated_websocket``: a subscription made over HTTP is that websocket's, its
    changes go there. None for an id that is no websocket of this printer's."""
    try:
        found = face.connections.get(int(named)) if named is not None else None
    except (TypeError, ValueError):
        return None
    if isinstance(found, Connection) and found.printer == service.name:
        return found
    return None


async def _body(request: Request) -> dict[str, Any]:
    """The arguments in a body: a JSON object, or a form's fields (its files too). An empty
    (or blank) body is no arguments whatever its type, as Moonraker takes it: FDM Monster
    sends ``Content-Type: application/json`` with no body on its GETs and POSTs."""
    kind = request.headers.get("content-type", "")
    if kind.startswith("application/json"):
        text = await request.body()
        if not text.strip():
            return {}
        try:
            body = parse_json(text)
        except ValueError:
            raise rpc.RpcError(400, "the body is not JSON") from None
        except JsonTooDeep as exc:
            raise rpc.RpcError(400, str(exc)) from None
        if not isinstance(body, dict):
            raise rpc.RpcError(400, "the body is not a JSON object")
        return body
    if kind.startswith(("multipart/form-data", "application/x-www-form-urlencoded")):
        try:
            form = await request.form()
        except HTTPException as exc:  # Starlette's word on a broken form, in Moonraker's shape
            raise rpc.RpcError(exc.status_code, str(exc.detail)) from None
        return {k: v for k, v in form.multi_items() if isinstance(v, (str, UploadFile))}
    return {}


async def answer_rpc(
    face: MoonrakerFace,
    service: PrinterService,
    user: str | None,
    text: str | bytes,
    connection: Connection | None = None,
) -> str | None:
    """The answer to a JSON-RPC request (or batch) ``text``, as JSON: a response, a list of
    them, or None for a notification."""
    try:
        request = parse_json(text)
    except ValueError:
        return json.dumps(_error(None, -32700, "Parse error"))
    except JsonTooDeep as exc:
        return json.dumps(_error(None, -32700, f"Parse error: {exc}"))
    if isinstance(request, list):
        return await _batch(face, service, user, request, connection)
    answer = await _one(face, service, user, request, connection)
    return None if answer is None else json.dumps(answer)


async def _batch(
    face: MoonrakerFace,
    service: PrinterService,
    user: str | None,
    requests: list[Any],
    connection: Connection | None,
) -> str:
    """A batch's answers as JSON, within :data:`BATCH_CALLS` and :data:`BATCH_ANSWER_BYTES`:
    past that many calls the batch is refused whole (none runs); an answer that would take
    the batch's past its bytes is replaced by an error that says so (its call ran). Each
    answer is encoded as its call ends, not all at once on the loop at the end."""
    if len(requests) > BATCH_CALLS:
        message = f"Invalid Request: a batch of {len(requests)} calls, at most {BATCH_CALLS}"
        return json.dumps(_error(None, -32600, message))
    answers: list[str] = []
    size = 0
    for request in requests:
        answer = await _one(face, service, user, request, connection)
        if answer is not None:
            text = json.dumps(answer)
            if size + len(text) > BATCH_ANSWER_BYTES:
                limit = BATCH_ANSWER_BYTES >> 20
                message = f"the batch's answer would pass {limit} MB: this call ran, its "
                message += "answer is left out"
                text = json.dumps(_error(answer.get("id"), 413, message))
            size += len(text)
            answers.append(text)
        await asyncio.sleep(0)  # the loop's other work between the calls
    return "[" + ",".join(answers) + "]"


async def _one(
    face: MoonrakerFace,
    service: PrinterService,
    user: str | None,
    request: Any,
    connection: Connection | None,
) -> dict[str, Any] | None:
    if not isinstance(request, dict) or request.get("jsonrpc") != "2.0":
        return _error(None, -32600, "Invalid Request")
    ident = request.get("id")
    name = request.get("method")
    params = request.get("params", {})
    if not isinstance(name, str):
        return _error(ident, -32600, "Invalid Request")
    if not isinstance(params, dict):
        return _error(ident, -32602, "Invalid params:")
    found = rpc.METHODS.by_name.get(name)
    if found is None:
        return _error(ident, -32601, "Method not found") if "id" in request else None
    if connection is not None and connection.refused and name != "server.connection.identify":
        return _error(ident, -32602, rpc.UNAUTHORIZED.message)  # a wrong key in its identify
    call = rpc.Call(face, service, user, dict(params), connection)
    try:
        result = await rpc.call(found, call)
    except rpc.RpcError as exc:
        return _error(ident, exc.code, exc.message)
    except Exception as exc:  # a bug: said, and the socket goes on
        log.exception("moonraker %s failed", name)
        return _error(ident, 500, f"{type(exc).__name__}: {exc}")
    if "id" not in request:
        return None  # a notification from the client: no answer
    return {"jsonrpc": "2.0", "result": result, "id": ident}


# --- the websocket -------------------------------------------------------------------------


async def _websocket(websocket: WebSocket) -> None:
    face = face_of(websocket)
    try:
        user = who(face, websocket.scope)
    except rpc.RpcError as exc:
        await websocket.send_denial_response(error_body(exc))
        return
    try:
        service = _service(face, websocket.path_params.get("printer"))
    except rpc.RpcError as exc:
        await websocket.send_denial_response(error_body(exc))
        return
    await websocket.accept()
    connection = Connection(face, websocket, service, user)
    await connection.run()


class Connection:
    """One websocket: its requests (each in its own task: a heat wait's G-code does not
    hold up the rest), its subscription, and what it was sent of it."""

    def __init__(
        self, face: MoonrakerFace, websocket: WebSocket, service: PrinterService, user: str | None
    ) -> None:
        self.face = face
        self.websocket = websocket
        self.service = service
        self.printer = service.name
        self.user = user
        self.id = id(self)
        self.client: dict[str, Any] = {}  # what server.connection.identify said
        self.refused = False  # its identify named a wrong key: it gets nothing more
        self.subscribed: dict[str, list[str] | None] = {}
        self.sent: dict[str, dict[str, Any]] = {}  # the subscribed objects, as last sent
        self.klippy = klippy_state(service)
        self._outbox: asyncio.Queue[str] = asyncio.Queue(OUTBOX)
        self._unsent = 0  # bytes in the outbox
        self._dropped = False  # it read too little: closed, told nothing more
        self._tasks: set[asyncio.Task[None]] = set()
        self._state_changed = asyncio.Event()  # a look now: a state is not missed between two

    async def run(self) -> None:
        face = self.face
        face.connections[self.id] = self
        writer = asyncio.create_task(self._write())
        ticker = asyncio.create_task(self._tick())
        try:
            while True:
                text = await self.websocket.receive_text()
                task = asyncio.create_task(self._answer(text))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            face.connections.pop(self.id, None)
            # Its calls run to their end (a print start or a cancel half done would be
            # worse than an answer nobody reads); only the sending stops.
            for task in (writer, ticker):
                task.cancel()
            await asyncio.gather(writer, ticker, return_exceptions=True)

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await self.websocket.close(1001)

    # --- requests --------------------------------------------------------------------

    async def _answer(self, text: str) -> None:
        answer = await answer_rpc(self.face, self.service, self.user, text, self)
        if answer is not None:
            self._put_text(answer)

    # --- subscriptions ----------------------------------------------------------------

    def subscribe(self, wanted: dict[str, list[str] | None]) -> dict[str, Any]:
        """The objects ``wanted`` from now on (replacing what was), as they are now."""
        self.subscribed = dict(wanted)
        status = self.face.objects[self.printer].status(self.subscribed)
        self.sent = {name: dict(values) for name, values in status.items()}
        return status

    def heard(self, event: ServerEvent) -> None:
        """A server event of this printer: the klippy notifications; a state's change is
        looked for at once (a restart's states would fall between two looks), the rest at
        the next look."""
        if isinstance(event, PrinterState):
            state = klippy_state(self.service)
            if state != self.klippy:
                self.klippy = state
                if state in ("ready", "shutdown", "disconnected"):
                    self.send_later(f"notify_klippy_{state}")
            self._state_changed.set()

    def _changes(self) -> dict[str, dict[str, Any]]:
        """What changed in the subscribed objects since they were last sent."""
        if not self.subscribed:
            return {}
        status = self.face.objects[self.printer].status(self.subscribed)
        changes: dict[str, dict[str, Any]] = {}
        for name, values in status.items():
            before = self.sent.setdefault(name, {})
            changed = {k: v for k, v in values.items() if before.get(k, _NOTHING) != v}
            if changed:
                before.update(changed)
                changes[name] = changed
        return changes

    async def _tick(self) -> None:
        """Klipper's cadence (``klippy/webhooks.py``, ``QueryStatusHelper``): every 0.25 s,
        what changed in the subscribed objects since the last look, with Klippy's clock as
        its eventtime (nothing changed: nothing sent; Klipper's clock moves, and with it the
        toolhead's estimated_print_time, so a subscription to it hears four a second);
        Moonraker's process statistics every second, which keep a client's heartbeat fed.
        A state's change is looked at as it comes, as Moonraker passes Klippy's on."""
        next_stat = 0.0
        while True:
            self._state_changed.clear()
            changes = self._changes()
            if changes:
                self.send_later("notify_status_update", [changes, eventtime()])
            now = time.monotonic()
            if now >= next_stat:
                next_stat = now + PROC_STAT_EVERY
                self.send_later("notify_proc_stat_update", [self.face.proc_stats()])
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._state_changed.wait(), STATUS_EVERY)

    # --- sending ----------------------------------------------------------------------

    def send_later(self, method: str, params: list[Any] | None = None) -> None:
        if self.refused:
            return  # Moonraker tells a socket that must sign in again nothing
        message: dict[str, Any] = {"jsonrpc": "2.0", "method": method}
        if params is not None:
            message["params"] = params
        self._put(message)

    def _put(self, message: Any) -> None:
        self._put_text(json.dumps(message))

    def _put_text(self, text: str) -> None:
        """``text`` (a message as JSON) to send; a client that leaves too much unread is
        closed instead."""
        if self._dropped:
            return
        if self._outbox.full() or self._unsent + len(text) > OUTBOX_BYTES:
            # A client that reads nothing: dropped, not kept in memory.
            log.warning("moonraker: websocket %d reads nothing: closed", self.id)
            self._dropped = True
            self.face.connections.pop(self.id, None)
            asyncio.get_running_loop().create_task(self.close())
            return
        self._unsent += len(text)
        self._outbox.put_nowait(text)

    async def _write(self) -> None:
        while True:
            text = await self._outbox.get()
            await self.websocket.send_text(text)
            self._unsent -= len(text)


_NOTHING = object()


def _error(ident: Any, code: int, message: str) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "error": {"code": code, "message": message}, "id": ident}
