"""Moonraker's ways in and argument forms as Klipper's clients use them (issue 50), against a
real server and its fake printer: a JSON body that is empty (FDM Monster's GETs and POSTs),
a websocket's subscription made over HTTP by its ``connection_id``, a wrong key from a
trusted network, and Moonraker's OctoPrint-compatible endpoints opened to a trusted network
(FDM Monster's Klipper printers ask ``/api/version`` first) while the rest of OctoPrint's
face keeps asking for a key."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import websocket

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed
from tests.support.server import KEY, Server, free_port, gcode, server_config, wait_for

pytestmark = pytest.mark.timeout(120)

JSON = {"Content-Type": "application/json"}
TRUSTED = "192.168.1.0/24"
# Through the server's named proxy (127.0.0.1): a client in the trusted network, and one not.
INSIDE = {"X-Forwarded-For": "192.168.1.77"}
OUTSIDE = {"X-Forwarded-For": "10.0.0.5"}


def ran(fake: BuiltInFake, line: str) -> bool:
    assert fake.log_path is not None
    return any(done.startswith(line) for done in executed(fake.log_path))


@pytest.fixture
def trusting(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> tuple[Server, BuiltInFake]:
    """A server that trusts 192.168.1.0/24 behind a proxy it names (127.0.0.1)."""
    fake = bench()
    config = tmp_path / "trusting.toml"
    config.write_text(
        f'moonraker_trusted_clients = ["{TRUSTED}"]\ntrusted_proxies = ["127.0.0.1"]\n'
        f'[printers]\nbench = "{fake.port}"\n'
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("bench")
    return server, fake


# --- an empty JSON body --------------------------------------------------------------------


def test_an_empty_json_body_is_no_arguments_as_fdm_monster_sends_it(
    printer: tuple[Server, BuiltInFake],
) -> None:
    """FDM Monster's calls, as it sends them: ``Content-Type: application/json`` and no body
    (or a blank one), the arguments in the query. A body that is JSON but not an object is
    still one sentence."""
    server, fake = printer
    with server.client() as client:
        stored = client.post("/server/files/upload", files={"file": ("cube.gcode", gcode(30))})
        assert stored.status_code == 201, stored.text
        for body in (b"", b" \r\n"):
            listed = client.request(
                "GET", "/server/files/directory?path=gcodes", content=body, headers=JSON
            )
            assert listed.status_code == 200, listed.text
            names = [f["filename"] for f in listed.json()["result"]["files"]]
            assert "cube.gcode" in names
            query = client.post(
                "/printer/objects/query?print_stats&extruder=target", content=body, headers=JSON
            )
            assert query.status_code == 200, query.text
            status = query.json()["result"]["status"]
            assert status["print_stats"]["state"] == "standby"
            assert status["extruder"] == {"target": 0}
        for body in (b"[1]", b"null", b'"x"'):
            refused = client.post("/printer/objects/query?webhooks", content=body, headers=JSON)
            assert refused.status_code == 400
            assert refused.json()["error"]["message"] == "the body is not a JSON object"
        started = client.post("/printer/print/start?filename=cube.gcode", headers=JSON)
        assert started.status_code == 200, started.text
        assert started.json() == {"result": "ok"}
    wait_for(lambda: ran(fake, "G1 X29"), what="the file started by an empty body's call")


# --- a subscription over HTTP --------------------------------------------------------------


@contextmanager
def socket_of(server: Server, path: str = "/websocket") -> Iterator[websocket.WebSocket]:
    opened = websocket.create_connection(
        f"ws://127.0.0.1:{server.port}{path}", header={"X-Api-Key": KEY}, timeout=30
    )
    try:
        yield opened
    finally:
        opened.close()


def answer_of(opened: websocket.WebSocket, method: str, ident: int, **params: Any) -> Any:
    """The answer to ``method`` on ``opened`` (the notifications before it skipped)."""
    opened.send(json.dumps({"jsonrpc": "2.0", "method": method, "params": params, "id": ident}))
    while True:
        message = json.loads(opened.recv())
        if message.get("id") == ident:
            return message


def rpc(opened: websocket.WebSocket, method: str, ident: int, **params: Any) -> Any:
    """``method``'s result on ``opened``."""
    message = answer_of(opened, method, ident, **params)
    assert "result" in message, message
    return message["result"]


def status_update(opened: websocket.WebSocket, wanted: Callable[[dict[str, Any]], bool]) -> Any:
    while True:
        message = json.loads(opened.recv())
        if message.get("method") == "notify_status_update" and wanted(message["params"][0]):
            return message["params"][0]


def test_a_websockets_subscription_made_over_http_sends_its_changes_there(
    printer: tuple[Server, BuiltInFake],
) -> None:
    """FDM Monster's way: ``server.connection.identify`` on the websocket, then ``POST
    /printer/objects/subscribe?connection_id=ID&print_stats&extruder=target`` over HTTP; the
    changes come as ``notify_status_update`` on that websocket."""
    server, fake = printer
    with socket_of(server) as opened, server.client() as client:
        identified = rpc(
            opened,
            "server.connection.identify",
            1,
            client_name="FDM Monster",
            version="2.1.1",
            type="other",
            url="https://github.com/fdm-monster/fdm-monster",
        )
        ident = identified["connection_id"]
        assert rpc(opened, "server.websocket.id", 2) == {"websocket_id": ident}
        subscribed = client.post(
            f"/printer/objects/subscribe?connection_id={ident}&print_stats&extruder=target",
            headers=JSON,
        )
        assert subscribed.status_code == 200, subscribed.text
        status = subscribed.json()["result"]["status"]
        assert status["extruder"] == {"target": 0}
        assert status["print_stats"]["state"] == "standby"
        said = client.post("/printer/gcode/script", json={"script": "M104 S133"})
        assert said.status_code == 200
        update = status_update(opened, lambda s: s.get("extruder", {}).get("target") == 133)
        assert set(update["extruder"]) == {"target"}  # only the fields subscribed
        # Not a websocket (closed, another printer's, never one): Moonraker's 400.
        for named in ("connection_id=12345&", "connection_id=x&", ""):
            refused = client.post(f"/printer/objects/subscribe?{named}webhooks", headers=JSON)
            assert refused.status_code == 400, refused.text
            said_back = refused.json()["error"]["message"]
            assert said_back == "No connection associated with subscription request"
    assert ran(fake, "M104 S133")


def test_a_subscription_over_http_names_a_websocket_of_its_own_printer(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"left": bench().port, "right": bench().port})
    server.wait_ready("left", "right")
    with socket_of(server, "/printers/right/websocket") as opened, server.client() as client:
        ident = rpc(opened, "server.websocket.id", 1)["websocket_id"]
        other = client.post(f"/printers/left/printer/objects/subscribe?connection_id={ident}")
        assert other.status_code == 400
        own = client.post(f"/printers/right/printer/objects/subscribe?connection_id={ident}")
        assert own.status_code == 200, own.text


# --- keys and trusted networks -------------------------------------------------------------


def test_a_wrong_key_is_refused_from_a_trusted_network_too(
    trusting: tuple[Server, BuiltInFake],
) -> None:
    """Moonraker refuses a wrong key whatever the network (401 "Unauthorized"): on HTTP, as
    a bearer, and at the websocket's upgrade. A one-shot token it does not know is
    ignored (KlipperScreen sends ``?token=False``)."""
    server, fake = trusting
    with httpx.Client(base_url=server.url, timeout=30) as curl:
        assert curl.get("/server/info", headers=INSIDE).status_code == 200
        assert curl.get("/server/info?token=False", headers=INSIDE).status_code == 200
        for wrong in (
            {"X-Api-Key": "wrong"},
            {"Authorization": "Bearer wrong"},
            {"X-Access-Token": "wrong"},  # Moonraker's login token: this server makes none
        ):
            answer = curl.post(
                "/printer/gcode/script", json={"script": "M104 S244"}, headers=INSIDE | wrong
            )
            assert answer.status_code == 401
            assert answer.json()["error"]["message"] == "Unauthorized"
        assert curl.get("/server/info?access_token=x", headers=INSIDE).status_code == 401
        # OctoPrint's ?apikey= is no Moonraker key: a wrong one is ignored there, as on Moonraker.
        assert curl.get("/server/info?apikey=wrong", headers=INSIDE).status_code == 200
        assert curl.get(f"/server/info?apikey={KEY}", headers=OUTSIDE).status_code == 200
        assert curl.get("/server/info", headers=INSIDE | {"X-Api-Key": KEY}).status_code == 200
        assert curl.get("/server/info", headers=OUTSIDE).status_code == 401
    base = f"ws://127.0.0.1:{server.port}/websocket"
    inside = [f"{k}: {v}" for k, v in INSIDE.items()]
    websocket.create_connection(base, header=inside, timeout=30).close()
    with pytest.raises(websocket.WebSocketBadStatusException) as refused:
        websocket.create_connection(base, header=[*inside, "X-Api-Key: wrong"], timeout=30)
    assert refused.value.status_code == 401
    said = json.loads(refused.value.resp_body or b"")["error"]["message"]
    assert said == "Unauthorized"
    # Signing in after the upgrade (server.connection.identify's api_key): a wrong key
    # leaves the socket nothing, trusted network or not, until a right one.
    opened = websocket.create_connection(base, header=inside, timeout=30)
    try:
        identify = {"client_name": "x", "version": "1", "type": "other", "url": "x"}
        refused_identify = answer_of(opened, "server.connection.identify", 1, api_key="wrong")
        assert refused_identify["error"] == {"code": -32602, "message": "Invalid API Key"}
        script = {"script": "M104 S244"}
        after = answer_of(opened, "printer.gcode.script", 2, **script)
        assert after["error"] == {"code": -32602, "message": "Unauthorized"}
        signed_in = answer_of(opened, "server.connection.identify", 3, **identify, api_key=KEY)
        assert "connection_id" in signed_in["result"]
        assert answer_of(opened, "printer.gcode.script", 4, script="M104 S212")["result"] == "ok"
    finally:
        opened.close()
    assert ran(fake, "M104 S212")
    assert not ran(fake, "M104 S244")


def test_a_trusted_network_opens_moonrakers_octoprint_endpoints_and_no_other(
    trusting: tuple[Server, BuiltInFake],
) -> None:
    """Moonraker's ``octoprint_compat`` paths (``/api/version`` first: FDM Monster's Klipper
    printers) answer a trusted network without a key, at the root and a printer's path;
    every other path of OctoPrint's face, and every path from elsewhere, still asks for
    one; a wrong key is 401, as Moonraker says it."""
    server, fake = trusting
    with httpx.Client(base_url=server.url, timeout=30) as curl:
        for path in ("/api/version", "/printers/bench/api/version"):
            version = curl.get(path, headers=INSIDE)
            assert version.status_code == 200, version.text
            assert version.json()["server"] and version.json()["text"].startswith("OctoPrint")
        for path in ("/api/server", "/api/job", "/api/printer", "/api/settings"):
            assert curl.get(path, headers=INSIDE).status_code == 200, path
        assert curl.get("/api/server", headers=INSIDE).json()["server"]
        assert curl.get("/api/currentuser", headers=INSIDE).status_code == 200
        assert curl.get("/api/printerprofiles", headers=INSIDE).status_code == 200
        command = {"commands": ["M104 S211"]}
        assert curl.post("/api/printer/command", json=command, headers=INSIDE).status_code == 204
        # The rest of OctoPrint's face: its key, as before.
        for verb, path in (("GET", "/api/files"), ("POST", "/api/job"), ("GET", "/v1/printers")):
            assert curl.request(verb, path, headers=INSIDE).status_code == 403, path
        assert curl.get("/api/version", headers=OUTSIDE).status_code == 403
        assert curl.get("/api/version").status_code == 403  # the proxy itself: not trusted
        refused = curl.post(
            "/api/printer/command",
            json={"commands": ["M104 S243"]},
            headers=INSIDE | {"X-Api-Key": "wrong"},
        )
        assert refused.status_code == 401
        assert refused.json()["error"] == "a valid API key is needed (the X-Api-Key header)"
    wait_for(lambda: ran(fake, "M104 S211"), what="the trusted client's command")
    assert not ran(fake, "M104 S243")


def test_a_page_of_another_site_gets_nothing_through_a_trusted_network(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    """A browser in the trusted network that opens another site's page: the page's form
    or image address (the browser marks it ``Sec-Fetch-Site: cross-site``) gets 401 on
    Moonraker's face and 403 on its OctoPrint paths, and no G-code reaches the controller;
    the browser's own pages (same-origin, same-site), a page whose origin ``cors_domains``
    lists, a program (no such header) and a key still get in."""
    fake = bench()
    config = tmp_path / "trusting.toml"
    config.write_text(
        'moonraker_trusted_clients = ["127.0.0.0/8"]\n'
        'cors_domains = ["http://mainsail.lab.example"]\n'
        f'[printers]\nbench = "{fake.port}"\n'
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("bench")
    evil = {"Sec-Fetch-Site": "cross-site", "Origin": "http://evil.example"}
    image = {"Sec-Fetch-Site": "cross-site"}  # an <img> sends no Origin
    listed = {"Sec-Fetch-Site": "cross-site", "Origin": "http://mainsail.lab.example"}
    form = {"script": "M104 S231"}
    with httpx.Client(base_url=server.url, timeout=30) as browser:
        refused = browser.post("/printer/gcode/script", data=form, headers=evil)
        assert refused.status_code == 401, refused.text
        assert refused.json()["error"]["message"] == "Unauthorized"
        shown = browser.get("/printer/gcode/script?script=M104%20S232", headers=image)
        assert shown.status_code == 401
        command = {"commands": ["M104 S233"]}
        assert browser.post("/api/printer/command", json=command, headers=evil).status_code == 403
        # Let in: the browser's own pages, a listed origin, a program, a key.
        for headers, line in (
            ({"Sec-Fetch-Site": "same-origin"}, "M104 S161"),
            ({"Sec-Fetch-Site": "same-site"}, "M104 S162"),
            (listed, "M104 S163"),
            ({}, "M104 S164"),
            (evil | {"X-Api-Key": KEY}, "M104 S165"),
        ):
            answer = browser.post("/printer/gcode/script", json={"script": line}, headers=headers)
            assert answer.status_code == 200, (headers, answer.text)
    for line in ("M104 S161", "M104 S162", "M104 S163", "M104 S164", "M104 S165"):
        wait_for(lambda line=line: ran(fake, line), what=line)
    assert not any(ran(fake, f"M104 S{t}") for t in (231, 232, 233))


# --- verbs -----------------------------------------------------------------------------


def test_klippys_own_endpoints_take_get_and_post_as_fdm_monster_sends_them(
    printer: tuple[Server, BuiltInFake],
) -> None:
    """Moonraker registers Klippy's endpoints for GET and POST alike: FDM Monster POSTs
    ``printer/info`` and GETs ``printer/gcode/script?script=``; the print's buttons stay
    POST's only, as there."""
    server, fake = printer
    with server.client() as client:
        info = client.post("/printer/info", headers=JSON)
        assert info.status_code == 200 and info.json()["result"]["state"] == "ready"
        listed = client.post("/printer/objects/list")
        assert "print_stats" in listed.json()["result"]["objects"]
        said = client.get("/printer/gcode/script", params={"script": "M104 S151"})
        assert said.status_code == 200 and said.json() == {"result": "ok"}
        assert client.get("/printer/print/start?filename=x.gcode").status_code == 405
    assert ran(fake, "M104 S151")


def test_a_printers_own_port_opens_the_same_octoprint_paths_to_a_trusted_network(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    """A ``moonraker_port`` is all Moonraker, for a client that takes a host and a port:
    Moonraker's OctoPrint-compatible paths there are that printer's, open to a trusted
    network as at the root; the rest of OctoPrint's face still asks for a key."""
    left, right = bench(), bench()
    own = free_port()
    config = server_config(
        tmp_path, left={"port": left.port}, right={"port": right.port, "moonraker_port": own}
    )
    config.write_text('moonraker_trusted_clients = ["127.0.0.0/8"]\n' + config.read_text())
    server = servers({}, "--config", str(config))
    server.wait_ready("left", "right")
    with httpx.Client(base_url=f"http://127.0.0.1:{own}", timeout=30) as curl:
        assert curl.get("/api/version").status_code == 200
        command = {"commands": ["M104 S166"]}
        assert curl.post("/api/printer/command", json=command).status_code == 204
        assert curl.get("/api/files").status_code == 403
    wait_for(lambda: ran(right, "M104 S166"), what="the command on the printer's own port")
    assert not ran(left, "M104 S166")
