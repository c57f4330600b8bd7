"""docs/octoprint-compatibility.md stays true: every endpoint OctoPrint 1.11.8 documents
has a row; every row the server supports is one of its routes, at ``/api`` and under
``/printers/NAME``; every route of the OctoPrint face has a row; and what the table calls
not applicable answers 404 or 405 with a sentence, never 500."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import pytest
from fastapi.routing import APIRoute
from starlette.routing import WebSocketRoute

from repetrel_host.server.app import create_app
from repetrel_host.server.octoprint import sockjs
from repetrel_host.server.octoprint.push import Push
from repetrel_host.server.print_server import PrintServer
from repetrel_host.server.printers.config import PrinterConfig
from tests.support.paths import DATA, ROOT
from tests.support.server import Server

ROOT = ROOT
TABLE = ROOT / "docs" / "octoprint-compatibility.md"
DOCUMENTED = DATA / "octoprint-1.11.8-endpoints.txt"
_ROW = re.compile(
    r"^\| `(GET|POST|PUT|PATCH|DELETE|WEBSOCKET) (/\S+)` \| (supported|differs|not applicable) \|"
)
# OctoPrint's route parameters, as its docs write them: (path:x) spans folders.
_PARAMETER = re.compile(r"\((\w+):\w+\)|<\w+:\w+>")
# The OctoPrint face: what its clients call (the native API is /v1, the page is /).
_FACE = ("/api/", "/plugin/", "/downloads/", "/sockjs")


def rows() -> dict[tuple[str, str], str]:
    found = {}
    for line in TABLE.read_text().splitlines():
        match = _ROW.match(line)
        if match:
            found[match[1], match[2]] = match[3]
    return found


def pattern(path: str) -> re.Pattern[str]:
    """A row's path as a regular expression over concrete paths."""
    expression = ""
    position = 0
    for match in _PARAMETER.finditer(path):
        expression += re.escape(path[position : match.start()])
        expression += ".+" if match[1] == "path" else "[^/]+"
        position = match.end()
    return re.compile(expression + re.escape(path[position:]))


def routes(tmp_path: Path) -> set[tuple[str, str]]:
    """The server's routes, with sample parameters: its OpenAPI description, and the push
    socket's routes at the root and under ``/printers/sample`` (OpenAPI has no way to say a
    websocket; the requests below show that they answer there)."""
    server = PrintServer(tmp_path, {"p": PrinterConfig("fake")}, "key", 1)
    found = set()
    for path, operations in create_app(server).openapi()["paths"].items():
        found.update((method.upper(), sample(path)) for method in operations)
    for route in sockjs.router(Push(server)).routes:
        if isinstance(route, WebSocketRoute):
            methods = {"WEBSOCKET"}
        else:
            assert isinstance(route, APIRoute)
            methods = route.methods - {"OPTIONS"}
        for prefix in ("", "/printers/sample"):
            found.update((method, sample(prefix + route.path)) for method in methods)
    server.store.close()
    return found


def sample(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "sample", path.rstrip("/") or "/")


def test_every_documented_endpoint_has_a_row() -> None:
    table = rows()
    lines = DOCUMENTED.read_text().splitlines()
    documented = [line.split()[1:] for line in lines if not line.startswith("#")]
    assert len(documented) == 81
    missing = [f"{method} {path}" for method, path in documented if (method, path) not in table]
    assert not missing, f"rows missing from {TABLE.name}: {missing}"


def test_supported_rows_are_routes_and_every_route_has_a_row(tmp_path: Path) -> None:
    served = routes(tmp_path)
    table = rows()
    for (method, path), status in table.items():
        if status == "not applicable":
            continue
        expression = pattern(path)
        for prefix in ("", "/printers/sample"):
            assert any(
                m == method and p.startswith(prefix) and expression.fullmatch(p[len(prefix) :])
                for m, p in served
            ), f"{status} in the table, but no route: {method} {prefix}{path}"
    face = [(m, p) for m, p in served if p.startswith(_FACE)]
    assert face
    for method, path in face:
        assert any(m == method and pattern(row).fullmatch(path) for m, row in table), (
            f"a route with no row in {TABLE.name}: {method} {path}"
        )
        assert (method, f"/printers/sample{path}") in served  # every printer has it


@pytest.mark.timeout(60)
def test_what_is_not_applicable_answers_404_or_405_with_a_sentence(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    absent = [key for key, status in rows().items() if status == "not applicable"]
    assert len(absent) > 30
    with server.client() as client:
        for method, path in absent:
            concrete = _PARAMETER.sub("sample", path)
            answer = client.request(method, concrete, json={})
            assert answer.status_code in (404, 405), f"{method} {concrete}: {answer.status_code}"
            assert answer.json()["error"], f"{method} {concrete}"


@pytest.mark.timeout(60)
def test_the_push_socket_answers_at_the_root_and_for_each_printer(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake", "other": "fake"})
    with server.client() as client:
        for prefix in ("", "/printers/demo", "/printers/other"):
            assert client.get(f"{prefix}/sockjs").text == "Welcome to SockJS!\n"
            assert client.get(f"{prefix}/sockjs/info").json()["websocket"] is True
            opened = client.post(f"{prefix}/sockjs/000/compat{len(prefix)}/xhr")
            assert opened.text == "o\n"
            connected = client.post(f"{prefix}/sockjs/000/compat{len(prefix)}/xhr")
            # A message is a JSON object in the frame's array, not a string: OctoPrint's
            # SockJS server (sockjs-tornado) sends its dicts so.
            assert connected.text.startswith('a[{"connected":{'), connected.text[:80]
            sent = client.post(f"{prefix}/sockjs/000/compat{len(prefix)}/xhr_send", json=[])
            assert sent.status_code == 204
        assert client.get("/printers/nobody/sockjs/info").status_code == 404
