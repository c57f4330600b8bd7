"""Moonraker's methods, one table for both transports: a method is named by its HTTP path
("/printer/info" is ``printer.info``; where one path takes several verbs, the last part
takes the verb, as ``server.database.get_item``), and its handler takes a :class:`Call`
and gives the result. Errors are :class:`RpcError` with Moonraker's HTTP status; the
websocket says them with Moonraker's JSON-RPC codes (its status, but 404 is -32601 and 401
-32602), each with its own sentence: only an unknown method says "Method not found"."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi import HTTPException

from repetrel_host.server.json_input import JsonTooDeep, parse_json
from repetrel_host.server.moonraker.face import MoonrakerFace, Subscriber
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.service import PrinterService, Refused

# Arguments a client adds to an HTTP call for its own ends (a token, its websocket, a cache
# breaker), left out of the method's, as Moonraker's EXCLUDED_ARGS; a websocket's call keeps
# its params whole (``server.connection.identify`` reads its ``access_token``).
EXCLUDED = frozenset({"token", "access_token", "connection_id", "_"})


class RpcError(Exception):
    """A refused call: ``status`` as Moonraker answers it over HTTP (400, 401, 404...)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message

    @property
    def code(self) -> int:
        """The JSON-RPC error code, as Moonraker's ``execute_method`` gives it: the status,
        but 404 (a missing file, namespace or job too) is -32601 and 401 -32602; the
        message stays the refusal's own sentence."""
        return {404: -32601, 401: -32602}.get(self.status, self.status)


# A call without a valid key, token or trusted network (Moonraker's words).
UNAUTHORIZED = RpcError(401, "Unauthorized")


@dataclass
class Call:
    """One call of a method: who made it, for which printer, with which arguments."""

    face: MoonrakerFace
    service: PrinterService
    user: str | None
    args: dict[str, Any]
    connection: Subscriber | None = None  # its websocket, or the one HTTP's names
    base_url: str = ""  # where the client reached us (for a Location header)

    @property
    def server(self) -> PrintServer:
        return self.face.server

    def get(self, name: str, default: Any = None) -> Any:
        """The argument ``name``, else ``default``."""
        return self.args.get(name, default)

    def required(self, name: str, null: bool = False) -> Any:
        """The argument ``name``; 400 "No data for argument: name" when it is missing (or
        null, unless ``null`` allows it)."""
        if name not in self.args or (self.args[name] is None and not null):
            raise RpcError(400, f"No data for argument: {name}")
        return self.args[name]

    def string(self, name: str, default: str | None = None) -> str:
        value = self.required(name) if default is None else self.args.get(name, default)
        if not isinstance(value, str):
            raise RpcError(400, f"Invalid value for argument {name}: {value!r} is not a string")
        return value

    def integer(self, name: str, default: int) -> int:
        return int(self._number(name, default, int))

    def number(self, name: str, default: float) -> float:
        return self._number(name, default, float)

    def _number(self, name: str, default: float, kind: Callable[[Any], float]) -> float:
        value = self.args.get(name, default)
        try:
            return kind(value)
        except (TypeError, ValueError):
            raise RpcError(400, f"Invalid value for argument {name}: {value!r}") from None

    def flag(self, name: str, default: bool = False) -> bool:
        value = self.args.get(name, default)
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0"):
            return value.lower() in ("true", "1")
        if isinstance(value, int):
            return bool(value)
        raise RpcError(400, f"Invalid value for argument {name}: {value!r} is not a boolean")


Handler = Callable[[Call], Awaitable[Any]]


@dataclass
class Table:
    """Every method's handler, by its JSON-RPC name and by its HTTP path and verb."""

    by_name: dict[str, Handler] = field(default_factory=dict)
    by_route: dict[tuple[str, str], Handler] = field(default_factory=dict)
    # Paths with a file's path after them (``/server/files/gcodes/...``): the rest of the
    # path is the call's ``path`` argument, its root first ("gcodes/a.gcode").
    by_prefix: dict[tuple[str, str], Handler] = field(default_factory=dict)

    def add(
        self,
        path: str,
        *verbs: str,
        name: str | None = None,
        websocket: bool = True,
        http: bool = True,
    ) -> Callable[[Handler], Handler]:
        """A handler for ``path`` with ``verbs`` (GET when none): named from the path, or
        ``name``; on the websocket unless not ``websocket`` (an upload is HTTP's only), over
        HTTP unless not ``http`` (a subscription is the websocket's only)."""

        def register(handler: Handler) -> Handler:
            called = name or path.strip("/").replace("/", ".")
            if websocket:
                self.by_name.setdefault(called, handler)
            for verb in verbs or ("GET",):
                if http and path.endswith("/"):
                    self.by_prefix[(path, verb)] = handler
                elif http:
                    self.by_route[(path, verb)] = handler
            return handler

        return register

    def route(self, path: str, verb: str) -> tuple[Handler | None, dict[str, str]]:
        """The method of ``path`` and ``verb`` over HTTP, and the arguments its path gives;
        (None, {}) when there is none."""
        found = self.by_route.get((path, verb))
        if found is not None:
            return found, {}
        for (prefix, method_verb), handler in self.by_prefix.items():
            if verb == method_verb and path.startswith(prefix) and len(path) > len(prefix):
                root = prefix.rstrip("/").rpartition("/")[2]
                return handler, {"path": f"{root}/{path[len(prefix) :]}"}
        return None, {}

    def knows(self, path: str) -> bool:
        """Some verb of ``path`` is a method (another verb is 405, not 404)."""
        return any(p == path for p, _ in self.by_route) or any(
            path.startswith(p) for p, _ in self.by_prefix
        )


METHODS = Table()
method = METHODS.add


async def call(handler: Handler, call: Call) -> Any:
    """``handler`` run for ``call``: the printer's refusals and the API's errors as
    :class:`RpcError`."""
    try:
        return await handler(call)
    except Refused as exc:
        raise RpcError(exc.status, str(exc)) from None
    except HTTPException as exc:  # a helper shared with the other faces
        detail = exc.detail if isinstance(exc.detail, dict) else {"error": exc.detail}
        text = str(detail.get("error", detail))
        # A refused file: its first error quoted too (one message is all a client shows).
        errors: list[str] = [f for f in detail.get("findings", ()) if f.startswith("error")]
        raise RpcError(exc.status_code, f"{text}: {errors[0]}" if errors else text) from None


def query_args(items: list[tuple[str, str]]) -> dict[str, Any]:
    """A query string's arguments, with Moonraker's type hints (``limit:int=5``,
    ``print:bool=true``, ``value:json=...``)."""
    args: dict[str, Any] = {}
    for key, value in items:
        name, _, hint = key.partition(":")
        try:
            if hint == "int":
                args[name] = int(value)
            elif hint == "float":
                args[name] = float(value)
            elif hint == "bool":
                args[name] = value.lower() in ("true", "1")
            elif hint == "json":
                args[name] = parse_json(value)
            else:
                args[name] = value
        except ValueError:
            raise RpcError(400, f"Invalid value for argument {name}: {value!r}") from None
        except JsonTooDeep as exc:
            raise RpcError(400, f"Invalid value for argument {name}: {exc}") from None
    return args
