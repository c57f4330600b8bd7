"""Where a request may come from, checked before any route, on every face.

- The name it asked for (its ``Host``): a page elsewhere that rebinds its own name to this
  server's address (DNS rebinding) asks for that name. An IP address is always answered (a
  rebinding needs a name), as are ``localhost``, the machine's own names, the farm's
  ``node_url`` host and the names the settings add (``server_names``); any other name is
  refused with 421.
- For a websocket, the page that opened it (its ``Origin``): a browser opens a websocket to
  any site, with that site's cookies, and no CORS stops it. A websocket with no ``Origin``
  (a program, not a page) or from the server's own origin is let in; another origin only
  when the settings list it (``cors_domains``, Moonraker's rules: ``*`` matches anything,
  e.g. ``http://*.lan``) or when its address is in a trusted network
  (``moonraker_trusted_clients``, as Moonraker lets it in). Else 403, before the upgrade.
- For any request a browser marks as sent by a page of another site (``Sec-Fetch-Site:
  cross-site``: a form, an image's address, a script), from an origin the settings do not
  let in as above: a trusted network does not open the API to it, a key still does. A
  trusted network asks for no key, and such a page needs none to send G-code otherwise.

Model: Tornado's ``WebSocketHandler.check_origin`` (Moonraker's and OctoPrint's servers:
the origin's host and port against the request's ``Host``) and Moonraker's ``check_cors``.
"""

from __future__ import annotations

import re
import socket
import threading
from collections.abc import Callable, Iterable
from ipaddress import ip_address
from typing import Any
from urllib.parse import urlsplit

from starlette.websockets import WebSocket

from repetrel_host.server.auth import CROSS_SITE, refusal
from repetrel_host.server.print_server import PrintServer

_SHOWN = 100  # characters of a refused name or origin said back
FQDN_WAIT = 2.0  # s: a host with a broken resolver starts anyway, without its FQDN


def machine_names() -> set[str]:
    """The names this machine answers to: ``localhost``, its host name, ``NAME.local``
    (mDNS) and its fully qualified name (when the resolver says it within 2 s)."""
    host = socket.gethostname().lower()
    names = {"localhost", host, f"{host.split('.')[0]}.local"}
    found: list[str] = []
    # getfqdn asks the resolver, which may hang for a long time on a machine offline.
    asking = threading.Thread(target=lambda: found.append(socket.getfqdn()), daemon=True)
    asking.start()
    asking.join(FQDN_WAIT)
    return names | {name.lower() for name in found}


def name_of(host: str) -> str:
    """The name in a ``Host`` header: ``Printers.Lab:8765`` is ``printers.lab``,
    ``[::1]:8765`` is ``::1``."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    name, colon, port = host.rpartition(":")
    if colon and port.isdigit() and ":" not in name:
        host = name
    return host.rstrip(".")


def _is_address(name: str) -> bool:
    try:
        ip_address(name)
    except ValueError:
        return False
    return True


def cors_pattern(domain: str) -> re.Pattern[str]:
    """``domain`` (an origin, ``*`` for any characters) as a pattern of origins."""
    return re.compile(re.escape(domain).replace(r"\*", ".*"), re.IGNORECASE)


class Origins:
    """The names the server answers to and the other origins whose pages may open its
    websockets."""

    def __init__(self, names: Iterable[str], cors_domains: Iterable[str] = ()) -> None:
        self.names = frozenset(name_of(name) for name in names if name)
        self.cors = tuple(cors_pattern(domain) for domain in cors_domains)

    def answers_to(self, host: str | None) -> bool:
        """The server answers a request for ``host`` (its ``Host`` header; a request without
        one, HTTP/1.0's, named nothing)."""
        if host is None:
            return True
        name = name_of(host)
        return _is_address(name) or name in self.names

    def may_open(self, origin: str, host: str, trusts: Callable[[str], bool]) -> bool:
        """A page from ``origin`` may open a websocket that asked for ``host``."""
        parts = urlsplit(origin)
        if parts.netloc and parts.netloc.lower() == host.strip().lower():
            return True  # the server's own page
        if any(pattern.fullmatch(origin) for pattern in self.cors):
            return True
        return parts.hostname is not None and trusts(parts.hostname)


class OriginGuard:
    """Before any route: 421 for a name the server does not answer to, 403 for a websocket
    from a page of another origin (see the module). Each face's error shape."""

    def __init__(self, app: Any, server: PrintServer, origins: Origins) -> None:
        self.app = app
        self.server = server
        self.origins = origins

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host")
        if not self.origins.answers_to(host):
            name = name_of(host or "")[:_SHOWN]
            said = f"this server does not answer to the name '{name}' (server_names lists more)"
            await _refuse(scope, receive, send, 421, said)
            return
        origin = headers.get("origin", headers.get("sec-websocket-origin"))
        trusts = self.server.access.trusts
        if headers.get("sec-fetch-site") == "cross-site" and not (
            origin is not None and self.origins.may_open(origin, host or "", trusts)
        ):
            # A page of another site: a trusted network does not open the API to it.
            scope["state"] = {**scope.get("state", {}), CROSS_SITE: True}
        if (
            scope["type"] == "websocket"
            and origin is not None
            and not self.origins.may_open(origin, host or "", trusts)
        ):
            origin = origin[:_SHOWN]
            said = (
                f"a page from {origin} may not open this websocket "
                "(cors_domains lists the other origins that may)"
            )
            await _refuse(scope, receive, send, 403, said)
            return
        await self.app(scope, receive, send)


async def _refuse(scope: Any, receive: Any, send: Any, status: int, said: str) -> None:
    """Answer ``status`` and ``said`` in the face's shape; a websocket's before its upgrade."""
    answer = refusal(scope["path"], status, said)
    if scope["type"] == "websocket":
        await WebSocket(scope, receive, send).send_denial_response(answer)
    else:
        await answer(scope, receive, send)
