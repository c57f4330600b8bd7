"""No way in without a key (issue 49): a forged ``X-Forwarded-For`` opens no trusted network,
a name the server does not answer to (DNS rebinding) and a page of another origin open
nothing, the page's cookie opens nothing on Moonraker's face, and open reads show no app's
request for a key. Each attack is made against a real server and its fake printer, whose
log says that nothing it carried ran."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import websocket

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed
from tests.support.server import KEY, Server, wait_for

pytestmark = pytest.mark.timeout(120)

TRUSTED = "192.168.1.0/24"
SCRIPT = "/printer/gcode/script"
SERVER = [sys.executable, "-m", "repetrel_host.server.main"]
# Moonraker's websocket, OctoPrint's raw push socket and its SockJS websocket.
SOCKETS = ("/websocket", "/sockjs/websocket", "/sockjs/0/abc/websocket")


def config(tmp_path: Path, printer: str, **settings: Any) -> str:
    """A TOML file with ``settings`` and one printer, ``bench``, on ``printer``."""
    path = tmp_path / "ways-in.toml"
    text = "".join(f"{key} = {json.dumps(value)}\n" for key, value in settings.items())
    path.write_text(f'{text}[printers]\nbench = "{printer}"\n')
    return str(path)


def heated(fake: BuiltInFake, target: str) -> bool:
    """``fake`` ran ``M104 S<target>`` (the attack's command)."""
    assert fake.log_path is not None
    return any(line.startswith(f"M104 S{target}") for line in executed(fake.log_path))


def upgrade(server: Server, path: str, **options: Any) -> int:
    """Open a websocket at ``path`` (websocket-client's options: header, origin, cookie,
    host, suppress_origin); its status: 101, or the refusal's (its body checked)."""
    try:
        opened = websocket.create_connection(f"ws://127.0.0.1:{server.port}{path}", **options)
    except websocket.WebSocketBadStatusException as refused:
        body = json.loads(refused.resp_body or b"{}")
        said = body["error"]["message"] if isinstance(body["error"], dict) else body["error"]
        assert said and "Traceback" not in said, body
        return int(refused.status_code)
    opened.close()
    return 101


def forwarded(address: str) -> dict[str, str]:
    return {"X-Forwarded-For": address}


# --- X-Forwarded-For ---------------------------------------------------------------------


@pytest.mark.slow
def test_a_forged_forwarded_for_opens_no_trusted_network(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The issue's curl: a local client says it speaks for 192.168.1.77, a trusted network's
    address. uvicorn believed it from 127.0.0.1 (and from anyone with FORWARDED_ALLOW_IPS=*):
    now only from a proxy the settings name."""
    fake = bench()
    monkeypatch.setenv("FORWARDED_ALLOW_IPS", "*")  # uvicorn's own setting opens nothing
    server = servers(
        {}, "--config", config(tmp_path, fake.port, moonraker_trusted_clients=[TRUSTED])
    )
    server.wait_ready("bench")
    with httpx.Client(base_url=server.url, timeout=30) as curl:
        answer = curl.post(SCRIPT, json={"script": "M104 S245"}, headers=forwarded("192.168.1.77"))
        assert answer.status_code == 401
        assert answer.json()["error"]["message"] == "Unauthorized"
        assert (
            curl.get("/access/oneshot_token", headers=forwarded("192.168.1.77")).status_code == 401
        )
    assert upgrade(server, "/websocket", header=["X-Forwarded-For: 192.168.1.77"]) == 401
    with server.client() as client:  # the printer still answers, and ran none of it
        assert client.post(SCRIPT, json={"script": "M105"}).status_code == 200
    assert not heated(fake, "245")
    server.stop()

    # A web server in front, named: its X-Forwarded-For decides, both ways. Each proxy
    # adds the address it got the request from at the end: the last one not a proxy's is
    # the client, whatever the client wrote before it.
    proxied = servers(
        {},
        "--config",
        config(tmp_path, fake.port, moonraker_trusted_clients=[TRUSTED]),
        "--trusted-proxy",
        "127.0.0.1",
    )
    proxied.wait_ready("bench")
    with httpx.Client(base_url=proxied.url, timeout=30) as proxy:
        for client, status in [
            ("192.168.1.77", 200),
            ("10.0.0.5", 401),
            ("192.168.1.77, 10.0.0.5", 401),  # the client forged the trusted address
            ("10.0.0.5, 192.168.1.77", 200),
        ]:
            script = {"script": "M104 S201"} if status == 200 else {"script": "M104 S246"}
            answer = proxy.post(SCRIPT, json=script, headers=forwarded(client))
            assert answer.status_code == status, (client, answer.text)
        assert proxy.post(SCRIPT, json={"script": "M104 S246"}).status_code == 401  # the proxy
    assert upgrade(proxied, "/websocket", header=["X-Forwarded-For: 192.168.1.77"]) == 101
    assert upgrade(proxied, "/websocket", header=["X-Forwarded-For: 10.0.0.5"]) == 401
    wait_for(lambda: heated(fake, "201"), what="the trusted client's M104")
    assert not heated(fake, "246")


# --- Host (DNS rebinding) ----------------------------------------------------------------


def test_a_name_the_server_does_not_answer_to_is_refused_before_any_route(
    servers: Callable[..., Server],
) -> None:
    """A page at evil.example whose name now resolves to this server (DNS rebinding) asks
    for evil.example: refused, on each face, in its shape; an IP address, localhost, the
    machine's names and the ones listed are answered."""
    server = servers({"demo": "fake"}, "--server-name", "Printers.Lab.Example")
    port = server.port
    with server.client() as client:
        for host in ("evil.example", f"evil.example:{port}", "127.0.0.1.evil.example"):
            refused = client.get("/api/job", headers={"Host": host})
            assert refused.status_code == 421
            assert "does not answer to the name" in refused.json()["error"]
            moonraker = client.get("/server/info", headers={"Host": host})
            assert moonraker.status_code == 421
            assert moonraker.json()["error"]["code"] == 421
        name = socket.gethostname()
        for host in (
            f"127.0.0.1:{port}",
            f"[::1]:{port}",
            "10.1.2.3",
            f"localhost:{port}",
            f"printers.lab.example:{port}",
            "PRINTERS.LAB.EXAMPLE.",
            name,
            f"{name.split('.')[0]}.local:{port}",
        ):
            answer = client.get("/api/job", headers={"Host": host})
            assert answer.status_code == 200, (host, answer.text)
    key = [f"X-Api-Key: {KEY}"]
    for path in SOCKETS:
        assert upgrade(server, path, header=key, host="evil.example", suppress_origin=True) == 421
        assert upgrade(server, path, header=key, host="localhost", suppress_origin=True) == 101


@pytest.mark.parametrize(
    ("option", "value", "said"),
    [
        ("--server-name", "http://printers.lab", "not a host name"),
        ("--cors-domain", "http://printers.lab/", "not an origin"),
        ("--cors-domain", "http://printers.*", "top-level domain"),
        ("--trusted-proxy", "localhost", "trusted_proxies"),
    ],
)
def test_a_bad_way_in_setting_is_one_sentence(
    option: str, value: str, said: str, tmp_path: Path
) -> None:
    done = subprocess.run(
        [*SERVER, "--data-dir", str(tmp_path), "--printer", "x=fake", option, value],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert said in done.stderr and "Traceback" not in done.stderr


# --- Origin and the cookie -----------------------------------------------------------------


@pytest.fixture
def cookie_server(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> tuple[Server, BuiltInFake, str]:
    """A server (its page's origin, and http://*.lab.example listed), its fake, and the
    ``Cookie`` header the page's login leaves in a browser."""
    fake = bench()
    server = servers(
        {},
        "--config",
        config(tmp_path, fake.port, cors_domains=["http://*.lab.example"]),
    )
    server.wait_ready("bench")
    with server.client() as keyed:
        login = keyed.post("/api/login", json={"passive": True})
        assert login.status_code == 200
    cookie = "; ".join(f"{name}={value}" for name, value in login.cookies.items())
    return server, fake, cookie


def test_a_page_of_another_origin_opens_no_websocket_with_a_cookie_or_a_key(
    cookie_server: tuple[Server, BuiltInFake, str],
) -> None:
    """Another site's page opens a websocket with the browser's cookie for this server (no
    CORS stops a websocket): refused before the upgrade, on Moonraker's face and both of
    OctoPrint's sockets, and so with a key (a page cannot set one, but a bad page may hold
    one). A program (no Origin), the server's own page and a listed origin get in."""
    server, _, cookie = cookie_server
    own = f"http://127.0.0.1:{server.port}"
    key = [f"X-Api-Key: {KEY}"]
    for path in SOCKETS:
        for origin in ("http://evil.example", "null", f"http://127.0.0.1:{server.port + 1}"):
            assert upgrade(server, path, cookie=cookie, origin=origin) == 403, (path, origin)
            assert upgrade(server, path, header=key, origin=origin) == 403, (path, origin)
        assert upgrade(server, path, header=key, suppress_origin=True) == 101
        assert upgrade(server, path, header=key, origin=own) == 101
        assert upgrade(server, path, header=key, origin="http://mainsail.lab.example") == 101
        assert upgrade(server, f"/printers/bench{path}", header=key, origin=own) == 101
    with pytest.raises(websocket.WebSocketBadStatusException) as refused:
        websocket.create_connection(
            f"ws://127.0.0.1:{server.port}/websocket", origin="http://evil.example", header=key
        )
    said = json.loads(refused.value.resp_body or b"")["error"]["message"]
    assert said.startswith("a page from http://evil.example may not open this websocket")


def test_the_pages_cookie_opens_nothing_on_moonrakers_face(
    cookie_server: tuple[Server, BuiltInFake, str],
) -> None:
    """Moonraker takes a key, a one-shot token or a trusted network, never a cookie: a
    cookie alone (the browser sends it to any page's request) is 401 there, on its own
    origin too; OctoPrint's face still takes it, as the page uses it."""
    server, fake, cookie = cookie_server
    jar = {"Cookie": cookie}
    with httpx.Client(base_url=server.url, timeout=30) as browser:
        for path in ("/access/oneshot_token", "/server/info", "/printers/bench/server/info"):
            answer = browser.get(path, headers=jar)
            assert answer.status_code == 401, path
            assert answer.json()["error"]["message"] == "Unauthorized"
        answer = browser.post(SCRIPT, json={"script": "M104 S222"}, headers=jar)
        assert answer.status_code == 401
        assert browser.get("/api/job", headers=jar).status_code == 200  # the page's own
    own = f"http://127.0.0.1:{server.port}"
    assert upgrade(server, "/websocket", cookie=cookie, origin=own) == 401
    with server.client() as client:
        token = client.get("/access/oneshot_token").json()["result"]
        assert client.post(SCRIPT, json={"script": "M105"}).status_code == 200
    assert upgrade(server, f"/websocket?token={token}", origin=own) == 101
    assert not heated(fake, "222")


# --- app keys under open reads -------------------------------------------------------------


@contextmanager
def reading(url: str, heard: list[str]) -> Iterator[None]:
    """A websocket client that keeps every message in ``heard`` while the block runs."""
    opened = websocket.create_connection(url, timeout=30)

    def read() -> None:
        try:
            while text := opened.recv():
                heard.append(text)
        except (websocket.WebSocketException, OSError):
            pass

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        yield
    finally:
        opened.close()
        reader.join(timeout=10)


def test_open_reads_show_no_apps_request_for_a_key(servers: Callable[..., Server]) -> None:
    """A request's user_token decides it (Allow): with reads open, nobody without a key
    sees one, on OctoPrint's list, the native one, the event stream or the push socket;
    as OctoPrint, its list answers a user only."""
    server = servers({"demo": "fake"}, "--public-read")
    anonymous_events: list[str] = []
    keyed_events: list[str] = []
    pushed: list[str] = []

    def listen(into: list[str], key: str | None) -> None:
        query = f"?apikey={key}" if key else ""
        with httpx.stream("GET", f"{server.url}/v1/events{query}", timeout=60) as stream:
            for line in stream.iter_lines():
                into.append(line)
                if "announce.gcode" in line:
                    return

    listeners = [
        threading.Thread(target=listen, args=(anonymous_events, None), daemon=True),
        threading.Thread(target=listen, args=(keyed_events, KEY), daemon=True),
    ]
    for listener in listeners:
        listener.start()
    wait_for(lambda: anonymous_events and keyed_events, what="both event streams")
    with reading(f"ws://127.0.0.1:{server.port}/sockjs/websocket", pushed):
        wait_for(lambda: any("history" in text for text in pushed), what="the socket's history")
        with httpx.Client(base_url=server.url, timeout=30) as app:
            asked = app.post("/plugin/appkeys/request", json={"app": "spy"})
            assert asked.status_code == 201
            poll = f"/plugin/appkeys/request/{asked.json()['app_token']}"
            with server.client(key=None) as anonymous:
                for path in ("/api/plugin/appkeys", "/printers/demo/api/plugin/appkeys"):
                    refused = anonymous.get(path)
                    assert refused.status_code == 403, path
                    assert "API key" in refused.json()["error"]
                assert anonymous.get("/v1/appkeys").status_code == 403
            assert app.get(poll).status_code == 202  # the app still waits
            with server.client() as keyed:
                pending = keyed.get("/api/plugin/appkeys").json()["pending"]
                assert [p["app_id"] for p in pending.values()] == ["spy"]
                assert [p["app_id"] for p in keyed.get("/v1/appkeys").json()["pending"]] == ["spy"]
                wait_for(lambda: any("user_token" in line for line in keyed_events), what="it")
                # An event every listener hears, after the request's.
                done = keyed.post("/api/files/local", files={"file": ("announce.gcode", b"G28\n")})
                assert done.status_code == 201
        for listener in listeners:
            listener.join(timeout=30)
        wait_for(lambda: any("announce.gcode" in text for text in pushed), what="the upload")
    (user_token,) = pending
    assert any(user_token in line for line in keyed_events)
    assert any("announce.gcode" in line for line in anonymous_events)
    assert not any("appkey" in line or user_token in line for line in anonymous_events)
    assert not any(user_token in text for text in pushed), pushed
