"""OctoPrint's push socket, as its clients use it, against a real hyrel-server process and
the fake controller on a pty: octorest's ``WebSocketEventHandler`` (SockJS's websocket
transport), a raw websocket as FDM Monster opens it (``/sockjs/websocket``: a passive
login's session, ``auth``, ``throttle``, ``subscribe``), OctoPrint's own sockjs-client in
headless Chromium (websocket and xhr-streaming), a socket without auth, and a client that
never reads beside one that does."""

from __future__ import annotations

import base64
import functools
import http.server
import json
import os
import shutil
import socket
import struct
import threading
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import websocket
from octorest import OctoRest, WebSocketEventHandler

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.server.octoprint.terminal import LOG_LINES, terminal_lines
from tests.support.helpers import DATA, executed
from tests.support.server import KEY, Server, gcode, wait_for

pytestmark = pytest.mark.timeout(120)

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")


def passive_login(server: Server, path: str = "") -> str:
    """``user:session`` for the socket's ``auth``, from OctoPrint's passive login with the
    key (as FDM Monster, OctoFarm and the apps get it)."""
    with server.client() as client:
        answer = client.post(f"{path}/api/login", json={"passive": True})
        assert answer.status_code == 200, answer.text
        user = answer.json()
    assert user["name"] == "admin" and user["session"]
    return f"{user['name']}:{user['session']}"


def upload(server: Server, name: str, text: str, path: str = "", **form: str) -> dict[str, Any]:
    with server.client() as client:
        answer = client.post(
            f"{path}/api/files/local", data=form, files={"file": (name, text.encode())}
        )
        assert answer.status_code == 201, answer.text
        body: dict[str, Any] = answer.json()
        return body


def job_done(server: Server, job_id: int) -> bool:
    with server.client() as client:
        return bool(client.get(f"/v1/jobs/{job_id}").json()["state"] == "completed")


class Listener:
    """A websocket client (websocket-client, as octorest and many scripts use) reading in
    a thread: every message, parsed; raw JSON objects, or SockJS frames (``sockjs``)."""

    def __init__(self, url: str, sockjs: bool = False) -> None:
        self.sockjs = sockjs
        self.socket = websocket.create_connection(url, timeout=60)
        self.messages: list[dict[str, Any]] = []
        self.frames: list[str] = []
        self.ended = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        try:
            while True:
                text = self.socket.recv()
                if not text:
                    return
                self.frames.append(text)
                if not self.sockjs:
                    self.messages.append(json.loads(text))
                elif text.startswith("a"):
                    self.messages.extend(json.loads(text[1:]))
        except (websocket.WebSocketException, OSError):
            pass
        finally:
            self.ended.set()

    def send(self, message: dict[str, Any]) -> None:
        text = json.dumps(message)
        self.socket.send(json.dumps([text]) if self.sockjs else text)

    def of(self, kind: str) -> list[Any]:
        return [message[kind] for message in list(self.messages) if kind in message]

    def events(self) -> list[str]:
        return [event["type"] for event in self.of("event")]

    def event(self, name: str) -> dict[str, Any]:
        found = [event["payload"] for event in self.of("event") if event["type"] == name]
        assert found, f"no {name} event (events: {self.events()})"
        payload: dict[str, Any] = found[-1]
        return payload

    def states(self) -> list[str]:
        return [current["state"]["text"] for current in self.of("current")]

    def wait(self, condition: Callable[[], Any], what: str, timeout: float = 60) -> Any:
        return wait_for(condition, timeout, what)

    def close(self) -> None:
        self.socket.close()


def socket_url(server: Server, path: str = "/sockjs/websocket") -> str:
    return f"ws://127.0.0.1:{server.port}{path}"


def long_lines(count: int) -> str:
    """A job of G1 moves as a slicer writes them (X, Y, Z, E, F: long lines)."""
    return "G28\n" + "".join(
        f"G1 X{i % 200}.125 Y{(i * 7) % 200}.5 Z0.3 E{i * 0.01:.5f} F1800\n" for i in range(count)
    )


# --- the wire, as OctoPrint's terminal shows it ---------------------------------------------


def test_the_wire_reads_as_octoprints_terminal_across_reads_and_ticks() -> None:
    """The session's pieces as they come (a write of several lines, a reply cut across
    reads, Marlin's CRLF and its report's leading space), over two ticks."""
    partial = [b"", b""]
    first = deque(
        [
            (True, b"N1 M110 N0*125\n"),
            (False, b"o"),
            (True, b"N2 G28*18\nN3 G1 X1*97\n"),
            (False, b"k\r\nok\r\n T:21.0 /0.0"),
        ]
    )
    assert terminal_lines(first, partial) == [
        "Send: N1 M110 N0*125",
        "Send: N2 G28*18",
        "Send: N3 G1 X1*97",
        "Recv: ok",
        "Recv: ok",
    ]
    second = deque([(False, b" B:21.0 /0.0\r\n\r\n"), (True, b"N4 M105*36\n")])
    assert terminal_lines(second, partial) == [
        "Recv:  T:21.0 /0.0 B:21.0 /0.0",
        "Send: N4 M105*36",
    ]
    assert partial == [b"", b""]
    # More than a terminal shows: the newest lines, and none cut in two (the line that
    # "*1" ends began in a piece left out).
    many = deque([(False, b"an old line's end\n"), (True, b"N5 G1 X2"), (True, b"*1\n")])
    many += [(True, b"N%d G1\n" % i) for i in range(6, 6 + LOG_LINES - 1)]
    many.append((False, b"ok\n"))
    lines = terminal_lines(many, partial)
    assert lines[0] == "Send: N6 G1" and lines[-1] == "Recv: ok"
    assert len(lines) == LOG_LINES
    more = deque([(True, b"N%d G1\n" % i) for i in range(1000, 1000 + 2 * LOG_LINES)])
    assert terminal_lines(more, partial)[0] == f"Send: N{1000 + LOG_LINES} G1"


# --- octorest ----------------------------------------------------------------------------


@pytest.mark.slow
def test_octorest_websocket_event_handler_gets_currents_and_print_done(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.003")
    server = servers({"bench": fake.port})
    auth = passive_login(server)
    received: list[Any] = []
    opened = threading.Event()
    handler = WebSocketEventHandler(
        server.url,
        on_open=lambda ws: opened.set(),
        on_close=lambda *_: None,  # octorest's own default takes too few arguments
        on_message=lambda ws, m: received.append(m),
    )
    handler.run()
    try:
        assert opened.wait(30)
        wait_for(lambda: any("connected" in m for m in received), what="connected")
        handler.send({"auth": auth})  # a bare object in the SockJS frame, as octorest writes it
        wait_for(lambda: any("history" in m for m in received), what="the history")
        job = upload(server, "part.gcode", gcode(600), print="true")["job"]["id"]

        def done() -> list[Any]:
            events = [m["event"] for m in received if isinstance(m, dict) and "event" in m]
            return [e for e in events if e["type"] == "PrintDone"]

        wait_for(done, what="PrintDone")
        assert job_done(server, job)
    finally:
        handler.socket.close()
    assert all(isinstance(m, dict) for m in received)  # objects, as OctoPrint sends them
    currents = [m["current"] for m in received if "current" in m]
    printing = [c for c in currents if c["state"]["flags"]["printing"]]
    assert printing and printing[-1]["job"]["file"]["name"] == "part.gcode"
    assert 0 < printing[-1]["progress"]["completion"] <= 100
    assert done()[0]["payload"]["name"] == "part.gcode" and done()[0]["payload"]["time"] > 0
    assert currents[-1]["progress"]["completion"] == 100.0
    ran = executed(fake.log_path)
    assert ran.count("G28") == 1 and len([c for c in ran if c.startswith("G1 X")]) == 600


# --- a farm manager's raw websocket --------------------------------------------------------


@pytest.mark.slow
def test_a_farm_managers_raw_websocket_follows_a_print_its_events_and_the_wire(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """As FDM Monster: the printer's URL + ``sockjs/websocket``, the passive login's
    session, ``auth``, ``throttle``; ``subscribe`` as OctoPrint's docs show it."""
    other = bench()
    fake = bench("--move-time", "0.01")
    server = servers({"other": other.port, "bench": fake.port})
    auth = passive_login(server, "/printers/bench")
    listener = Listener(socket_url(server, "/printers/bench/sockjs/websocket"))
    try:
        listener.wait(lambda: listener.messages, "the connected message")
        connected = listener.messages[0]["connected"]
        assert connected["version"].startswith("1.11") and connected["display_version"]
        assert connected["plugin_hash"] and connected["config_hash"]
        assert {"key": "STATUS"}.items() <= next(
            p for p in connected["permissions"] if p["key"] == "STATUS"
        ).items()
        assert "apikey" in connected
        listener.send({"auth": auth})
        listener.send({"throttle": 1})
        listener.send(
            {
                "subscribe": {
                    "state": {"logs": True, "messages": True},
                    "events": True,
                    "plugins": ["appkeys"],
                }
            }
        )
        history = listener.wait(lambda: listener.of("history"), "the history")[0]
        assert history["state"]["text"] == "Operational"
        assert history["state"]["flags"]["operational"] and history["state"]["flags"]["ready"]
        # An app asks for a key: the page's plugin message (OctoPrint's appkeys).
        with server.client(key=None) as anyone:
            anyone.post("/plugin/appkeys/request", json={"app": "Phone app"})
        request = listener.wait(lambda: listener.of("plugin"), "the appkeys message")[0]
        assert request["plugin"] == "appkeys" and request["data"]["type"] == "request_access"
        assert request["data"]["app_name"] == "Phone app" and request["data"]["user_token"]

        job = upload(server, "part.gcode", gcode(700), "/printers/bench", print="true")
        job_id = job["job"]["id"]
        listener.wait(lambda: "PrintStarted" in listener.events(), "PrintStarted")
        listener.wait(
            lambda: any(c["progress"]["completion"] for c in listener.of("current")), "progress"
        )
        with server.client() as client:
            pause = {"command": "pause", "action": "pause"}
            assert client.post("/printers/bench/api/job", json=pause).status_code == 204
            listener.wait(lambda: "PrintPaused" in listener.events(), "PrintPaused")
            resume = {"command": "pause", "action": "resume"}
            assert client.post("/printers/bench/api/job", json=resume).status_code == 204
        listener.wait(lambda: "PrintDone" in listener.events(), "PrintDone", 90)
        assert job_done(server, job_id)
        prints = [e for e in listener.events() if e.startswith("Print") and "State" not in e]
        assert prints == ["PrintStarted", "PrintPaused", "PrintResumed", "PrintDone"]
        for name in prints:
            payload = listener.event(name)
            assert payload["name"] == "part.gcode" and payload["path"] == "part.gcode"
            assert payload["origin"] == "local" and payload["size"] == len(gcode(700))
        assert listener.event("PrintDone")["time"] > 0
        assert 0 < listener.event("PrintPaused")["progress"] < 100
        assert {"FileAdded", "UpdatedFiles"} <= set(listener.events())
        assert listener.event("FileAdded")["type"] == ["machinecode", "gcode"]

        # Every phase, the short ones too, in a current of its own, in order. (A resume
        # is at once here: "Resuming" lasts no time a client could see, nor /api/job.)
        states = listener.states()
        seen = [s for i, s in enumerate(states) if i == 0 or s != states[i - 1]]
        phases = ["Printing", "Pausing", "Paused", "Printing", "Finishing"]
        assert _in_order(phases, seen), seen
        assert seen[-1] == "Operational (bed not cleared)"
        printing = [c for c in listener.of("current") if c["state"]["text"] == "Printing"]
        assert all(c["state"]["flags"]["printing"] for c in printing)
        assert printing[-1]["job"]["file"]["name"] == "part.gcode"
        assert any(0 < c["progress"]["completion"] < 100 for c in printing)
        assert any(c["busyFiles"] == [{"origin": "local", "path": "part.gcode"}] for c in printing)
        final = listener.of("current")[-1]
        assert final["progress"]["completion"] == 100.0
        # Held (the part on the bed), yet ready: a client's start says the bed is clear
        # (not ready where every start waits for a release: test_print_after_print.py).
        assert final["state"]["flags"]["held"] is True and final["state"]["flags"]["ready"]
        # The wire as OctoPrint's terminal shows it: the job's lines and the controller's.
        logs = [line for c in listener.of("current") for line in c["logs"]]
        assert any(line.startswith("Send: N") and " G1 X" in line for line in logs)
        assert "Recv: ok" in logs
        # Temperatures as Marlin reports them (" T:..." with its space: "Recv:  T:...").
        assert any(line.startswith("Recv: ") and " T:" in line for line in logs)
        assert any(c["temps"] for c in listener.of("current"))
        sample = next(t for c in listener.of("current") for t in c["temps"])
        assert isinstance(sample["time"], int) and "actual" in sample["tool0"]

        # Cancelled: Cancelling, then PrintCancelled and PrintFailed (reason cancelled).
        with server.client() as client:  # the part is off the bed
            assert client.post("/v1/printers/bench/release").status_code < 300
        upload(server, "second.gcode", gcode(2000, start=1), "/printers/bench", print="true")
        listener.wait(lambda: listener.events().count("PrintStarted") == 2, "the second start")
        with server.client() as client:
            cancel = client.post("/printers/bench/api/job", json={"command": "cancel"})
            assert cancel.status_code == 204
        listener.wait(lambda: "PrintFailed" in listener.events(), "PrintFailed")
        assert listener.events().index("PrintCancelled") < listener.events().index("PrintFailed")
        assert listener.event("PrintFailed")["reason"] == "cancelled"
        assert listener.event("PrintCancelled")["name"] == "second.gcode"
        assert "Cancelling" in listener.states()
    finally:
        listener.close()
    # Each job's lines once, in order; the second cut short by its cancel.
    first, second = gcode(700).splitlines(), gcode(2000, start=1).splitlines()
    ran = executed(fake.log_path)
    assert ran[: len(first)] == first
    moves = [line for line in ran[len(first) :] if line.startswith("G1 X")]
    assert moves == second[1 : len(moves) + 1] and ran[len(first)] == "G28"
    assert "G28" not in executed(other.log_path)  # the other printer's socket: not this


def _in_order(wanted: list[str], seen: list[str]) -> bool:
    """``wanted`` appear in ``seen`` in this order (others may come between)."""
    position = 0
    for state in seen:
        if position < len(wanted) and state == wanted[position]:
            position += 1
    return position == len(wanted)


# --- without auth -----------------------------------------------------------------------


@pytest.mark.slow
def test_without_auth_a_socket_gets_only_connected_and_a_wrong_session_is_refused(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.002")
    server = servers({"bench": fake.port})
    raw = Listener(socket_url(server))
    framed = Listener(socket_url(server, "/sockjs/123/abcdef/websocket"), sockjs=True)
    try:
        auth = passive_login(server)
        raw.wait(lambda: raw.messages, "connected")
        framed.wait(lambda: framed.messages, "connected")
        assert framed.frames[0] == "o"
        raw.send({"auth": auth.split(":")[0] + ":not-a-session"})
        framed.send({"auth": "someone:" + auth.split(":")[1]})  # a session, not theirs
        raw.wait(lambda: raw.of("reauthRequired"), "reauthRequired")
        framed.wait(lambda: framed.of("reauthRequired"), "reauthRequired")
        job = upload(server, "part.gcode", gcode(300), print="true")["job"]["id"]
        wait_for(lambda: job_done(server, job), what="the job")
        with server.client(key=None) as anyone:
            anyone.post("/plugin/appkeys/request", json={"app": "Phone app"})
        # What would have come did come to a client that logged in meanwhile...
        late = Listener(socket_url(server))
        late.wait(lambda: late.messages, "connected")
        late.send({"auth": auth})
        late.wait(lambda: late.of("history"), "the history")
        assert late.of("history")[0]["state"]["text"] == "Operational (bed not cleared)"
        late.close()
    finally:
        raw.close()
        framed.close()
    # ...and nothing beyond connected (and the refusal) to the others.
    for listener in (raw, framed):
        kinds = [next(iter(message)) for message in listener.messages]
        assert kinds == ["connected", "reauthRequired"], kinds
        assert listener.of("reauthRequired") == [{"reason": "stale"}]


@pytest.mark.slow
def test_with_public_reads_a_socket_needs_no_auth(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port}, "--public-read")
    listener = Listener(socket_url(server))
    try:
        history = listener.wait(lambda: listener.of("history"), "the history")[0]
        assert history["state"]["text"] == "Operational"
        upload(server, "part.gcode", gcode(100), print="true")
        listener.wait(lambda: "PrintDone" in listener.events(), "PrintDone")
        # OctoPrint's disconnect and connect, told as its Disconnected and Connected.
        with server.client() as client:
            for command in ("disconnect", "connect"):
                answer = client.post("/api/connection", json={"command": command})
                assert answer.status_code == 204
                name = command.capitalize() + "ed"
                listener.wait(lambda name=name: name in listener.events(), name)
        assert listener.event("Connected")["port"] == fake.port
        assert listener.states()[-1].startswith("Operational")
    finally:
        listener.close()


# --- OctoPrint's own sockjs-client, in a browser -----------------------------------------

PAGE = """<!doctype html><script src="sockjs.min.js"></script><script>
window.received = []; window.closeCode = null;
const socket = new SockJS(%(url)s, undefined, {transports: [%(transport)s]});
socket.onopen = () => socket.send(JSON.stringify({auth: %(auth)s}));
socket.onmessage = (message) => window.received.push(message.data);
socket.onclose = (event) => { window.closeCode = event.code; };
window.transport = () => socket.transport;
</script>"""


@pytest.fixture
def page_server(tmp_path: Path) -> Iterator[Callable[[str], str]]:
    """Serves a page (and sockjs.min.js beside it) from another origin than the server's,
    as a page that reaches OctoPrint from elsewhere; returns its URL."""
    folder = tmp_path / "page"
    folder.mkdir()
    shutil.copy(DATA / "sockjs.min.js", folder / "sockjs.min.js")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()

    def serve(html: str) -> str:
        (folder / "index.html").write_text(html)
        return f"http://127.0.0.1:{httpd.server_address[1]}/index.html"

    yield serve
    httpd.shutdown()


@pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="needs Debian's chromium and chromium-driver (.ci/run installs them)",
)
@pytest.mark.parametrize("transport", ["websocket", "xhr-streaming"])
@pytest.mark.slow
def test_octoprints_sockjs_client_in_a_browser_follows_a_print(
    transport: str,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    page_server: Callable[[str], str],
) -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    fake = bench("--move-time", "0.002")
    # The page is another origin's (another port): its websocket is let in once listed, as
    # OctoPrint's needs allowCrossOrigin.
    server = servers({"bench": fake.port}, "--cors-domain", "http://127.0.0.1:*")
    auth = passive_login(server)
    url = page_server(
        PAGE
        % {
            "url": json.dumps(f"{server.url}/sockjs"),
            "transport": json.dumps(transport),
            "auth": json.dumps(auth),
        }
    )
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(argument)
    browser = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        wait = WebDriverWait(browser, 60)
        browser.get(url)

        def received() -> list[dict[str, Any]]:
            messages: list[dict[str, Any]] = browser.execute_script("return window.received || []")
            return messages

        def kinds() -> list[str]:
            return [next(iter(message)) for message in received()]

        wait.until(lambda _: "history" in kinds())
        assert kinds()[0] == "connected"
        assert browser.execute_script("return window.transport()") == transport
        upload(server, "part.gcode", gcode(1500), print="true")

        def events() -> list[str]:
            return [m["event"]["type"] for m in received() if "event" in m]

        wait.until(lambda _: "PrintDone" in events())
        currents = [m["current"] for m in received() if "current" in m]
        assert any(c["state"]["text"] == "Printing" for c in currents)
        assert events().index("PrintStarted") < events().index("PrintDone")
        assert browser.execute_script("return window.closeCode") is None
    finally:
        browser.quit()
    ran = executed(fake.log_path)
    assert len([line for line in ran if line.startswith("G1 X")]) == 1500


# --- a stuck client -------------------------------------------------------------------


def _masked_text(text: str) -> bytes:
    """A client's websocket text frame (masked, as a client must send it)."""
    data, mask = text.encode(), os.urandom(4)
    length = (
        bytes([0x80 | len(data)]) if len(data) < 126 else b"\xfe" + struct.pack("!H", len(data))
    )
    return b"\x81" + length + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data))


def stuck_client(server: Server, auth: str) -> socket.socket:
    """A websocket client that logs in and then never reads (a frozen app): its receive
    buffer as small as the kernel allows."""
    stuck = socket.socket()
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stuck.connect(("127.0.0.1", server.port))
    key = base64.b64encode(os.urandom(16)).decode()
    stuck.sendall(
        f"GET /sockjs/websocket HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
        f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
        "Sec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += stuck.recv(1)  # the handshake's answer only, not a byte of what follows
    assert answer.startswith(b"HTTP/1.1 101"), answer
    stuck.sendall(_masked_text(json.dumps({"auth": auth})))
    return stuck


@pytest.mark.timeout(150)
@pytest.mark.slow
def test_a_client_that_never_reads_is_dropped_and_slows_nothing(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.002")
    server = servers({"bench": fake.port})
    auth = passive_login(server)
    stuck = stuck_client(server, auth)
    reader = Listener(socket_url(server))
    try:
        reader.send({"auth": auth})
        reader.wait(lambda: reader.of("history"), "the history")
        text = long_lines(12_000)  # 25 s or so: longer than a stuck client is kept
        job = upload(server, "part.gcode", text, print="true")["job"]["id"]
        wait_for(lambda: job_done(server, job), 120, "the job")
        reader.wait(lambda: "PrintDone" in reader.events(), "PrintDone for the reader")
        # What the stuck client was sent, read now: it ends (the server closed it) before
        # the print did.
        stuck.settimeout(30)
        got = b""
        while chunk := stuck.recv(1 << 16):
            got += chunk
        assert b'"connected"' in got and b'"history"' in got
        assert b"PrintDone" not in got
    finally:
        reader.close()
        stuck.close()
    assert reader.events().count("PrintDone") == 1
    ran = executed(fake.log_path)
    assert ran == [line for line in text.splitlines() if line], "the job ran exactly once"
    # The server closed it before the job ended (the reader, after).
    log = server.stderr.read_text().splitlines()
    closed = [i for i, line in enumerate(log) if "(raw websocket) closed" in line]
    ended = [i for i, line in enumerate(log) if f"job {job} completed" in line]
    assert closed and ended and closed[0] < ended[0], log


def test_sockjs_info_greeting_and_bad_requests_answer_as_sockjs(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    with httpx.Client(base_url=server.url, timeout=30) as anyone:  # no key: SockJS has none
        info = anyone.get("/sockjs/info", headers={"Origin": "http://farm.example"})
        assert info.status_code == 200
        assert {"websocket": True, "cookie_needed": False}.items() <= info.json().items()
        assert info.headers["access-control-allow-origin"] == "http://farm.example"
        assert anyone.get("/printers/bench/sockjs/info").status_code == 200
        assert anyone.get("/printers/nope/sockjs/info").status_code == 404
        assert anyone.get("/sockjs").text == "Welcome to SockJS!\n"
        preflight = anyone.options("/sockjs/1/abc/xhr_streaming")
        assert preflight.status_code == 204 and "POST" in preflight.headers["allow"]
        assert anyone.post("/sockjs/1/nosession/xhr_send", content=b'["x"]').status_code == 404
        # xhr-polling: open, then a message frame with connected.
        assert anyone.post("/sockjs/1/polled/xhr").text == "o\n"
        first = anyone.post("/sockjs/1/polled/xhr").text
        assert first.startswith("a[") and json.loads(first[1:])[0]["connected"]
        assert anyone.post("/sockjs/1/polled/xhr_send", content=b"").status_code == 400
        broken = anyone.post("/sockjs/1/polled/xhr_send", content=b"[not json")
        assert broken.status_code == 400 and broken.text == "Broken JSON encoding."
        auth = json.dumps([json.dumps({"auth": passive_login(server)})])
        assert anyone.post("/sockjs/1/polled/xhr_send", content=auth).status_code == 204
        history = anyone.post("/sockjs/1/polled/xhr").text
        assert json.loads(history[1:])[0]["history"]["state"]["text"] == "Operational"


# --- a cancel held up by a heat wait ---------------------------------------------------------


@pytest.mark.slow
def test_a_cancel_behind_a_heat_wait_reads_cancelling_to_clients_and_the_socket(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """Without an emergency parser nothing breaks the M109: the safe stop waits for it. Until
    it ends, octorest's state (/api/connection), /api/printer's text and flags, /api/job and
    the socket's current say Cancelling, as OctoPrint does; then Operational."""
    fake = bench("--heat-rate", "1", "--no-emergency-parser")
    server = servers({"bench": fake.port})
    rest = OctoRest(url=server.url, apikey=KEY)
    listener = Listener(socket_url(server))
    try:
        listener.wait(lambda: listener.messages, "the connected message")
        listener.send({"auth": passive_login(server)})
        listener.wait(lambda: listener.of("history"), "the history")
        job = upload(server, "wait.gcode", "M104 S40\nM109 S40\n" + gcode(50), print="true")

        def heating() -> bool:
            fake.request("status")  # the log is flushed before the answer
            return "M104 S40" in executed(fake.log_path)

        wait_for(heating, what="the heat wait")
        rest.cancel()
        assert rest.state() == "Cancelling"
        state = rest.printer()["state"]
        assert state["text"] == "Cancelling", state
        assert state["flags"]["cancelling"] and state["flags"]["printing"], state
        assert rest.job_info()["state"] == "Cancelling"
        listener.wait(lambda: "Cancelling" in listener.states(), "Cancelling on the socket")
        current = next(c for c in listener.of("current") if c["state"]["text"] == "Cancelling")
        assert current["state"]["flags"]["cancelling"], current["state"]

        wait_for(lambda: rest.state() != "Cancelling", timeout=90, what="the stop's end")
        # Operational (the bed not cleared: the queue waits, as after any job).
        assert rest.state().startswith("Operational")
        assert not rest.printer()["state"]["flags"]["cancelling"]
        listener.wait(
            lambda: listener.states()[-1].startswith("Operational"), "Operational on the socket"
        )
        with server.client() as client:
            assert client.get(f"/v1/jobs/{job['job']['id']}").json()["state"] == "cancelled"
    finally:
        listener.close()
    assert "G1 X49 F3000" not in executed(fake.log_path)  # the moves after it never ran
