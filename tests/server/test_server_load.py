"""No request takes the server down (issue 49): a body is read only as far as its route
needs, with a key or without (413 in the face's own shape, the connection closed before
the rest is sent), and clients that send half a request and wait (slowloris) are closed
after the header timeout and never crowd out a keyed client, a printer's reconnect and its
safe stop, or the log. A printer streams beside each attack and loses nothing."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.server.connections import RESERVED_FILES, RefusalLog
from repetrel_host.server.settings import ServerSettings
from tests.support.attack import busy_server, streaming_beside
from tests.support.helpers import MARLIN_SAFE_STOP, executed, heater_targets
from tests.support.paths import ROOT
from tests.support.server import KEY, Server, job_state, wait_for

pytestmark = pytest.mark.timeout(180)
LINKS = ["reprap", "hyrel"]
MB = 1024 * 1024
BODY_MB = 64  # the attack's 1,000 MB, at a test's scale: the server must not read it


def peak_memory(server: Server) -> int:
    """The server's peak resident memory so far (VmHWM), in bytes."""
    assert server.process is not None
    status = Path(f"/proc/{server.process.pid}/status").read_text()
    found = re.search(r"VmHWM:\s+(\d+) kB", status)
    assert found is not None
    return int(found.group(1)) * 1024


def open_files(server: Server) -> int:
    assert server.process is not None
    return len(list(Path(f"/proc/{server.process.pid}/fd").iterdir()))


class Body:
    """A body of ``mb`` MB made as it is sent (the client never holds it), counting what
    was taken from it: what the server let the client send."""

    def __init__(self, start: bytes, mb: int = BODY_MB) -> None:
        self.start = start
        self.mb = mb
        self.sent = 0

    def __iter__(self) -> Iterator[bytes]:
        yield self.start
        for _ in range(self.mb):
            self.sent += 1
            yield b"x" * MB


def moonraker_refused(answer: httpx.Response, status: int) -> str:
    """Moonraker's error shape: ``{"error": {"code", "message"}}``, the status its own."""
    assert answer.status_code == status, answer.text
    error = answer.json()["error"]
    assert error["code"] == status and isinstance(error["message"], str), answer.text
    return str(error["message"])


def octoprint_refused(answer: httpx.Response, status: int) -> str:
    assert answer.status_code == status, answer.text
    error = answer.json()["error"]
    assert isinstance(error, str), answer.text
    return error


@pytest.mark.parametrize("protocol", LINKS)
@pytest.mark.slow
def test_big_bodies_are_refused_before_they_are_read_with_a_key_or_without(
    tmp_path: Path,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    protocol: str,
) -> None:
    server, fake = busy_server(tmp_path, bench, servers, protocol)
    json_kind = {"Content-Type": "application/json"}
    before = peak_memory(server)
    with streaming_beside(server, fake, moves=12_000), server.client(key=None) as anyone:
        # Open to anyone: a login, an app asking for a key, the push socket's messages.
        for path in ("/api/login", "/plugin/appkeys/request", "/printers/busy/api/login"):
            body = Body(b'{"passive": "')
            said = octoprint_refused(anyone.post(path, content=body, headers=json_kind), 413)
            assert said == f"the request's body is over 65536 bytes, the most {path} takes"
            assert body.sent < BODY_MB // 2, f"{path}: {body.sent} MB sent before the 413"
        assert anyone.post("/sockjs/000/abcdefgh/xhr").text.startswith("o")  # a session
        body = Body(b'["')
        octoprint_refused(anyone.post("/sockjs/000/abcdefgh/xhr_send", content=body), 413)
        assert body.sent < BODY_MB // 2
        # Refused for want of a key, unread: the refusal comes whole, the rest is not read.
        body = Body(b"")
        refused = anyone.post("/v1/printers/busy/hold", content=body)
        assert octoprint_refused(refused, 403) and refused.headers["connection"] == "close"
        assert body.sent < BODY_MB // 2
        # Its length said first: refused before a byte of it is read.
        body = Body(b"{")
        length = {**json_kind, "Content-Length": str(BODY_MB * MB + 1)}
        octoprint_refused(anyone.post("/api/login", content=body, headers=length), 413)
        assert body.sent < BODY_MB // 2
        with server.client() as keyed:
            # With the key: a JSON body is a few MB at most, on every face.
            body = Body(b'{"namespace": "a", "key": "b", "value": "')
            answer = keyed.post("/server/database/item", content=body, headers=json_kind)
            said = moonraker_refused(answer, 413)
            assert said.startswith("the request's body is over 2097152 bytes")
            assert body.sent < BODY_MB // 2
            body = Body(b'{"file": "')
            answer = keyed.post("/v1/printers/busy/queue", content=body, headers=json_kind)
            octoprint_refused(answer, 413)
            assert body.sent < BODY_MB // 2
            # A body the route never reads is not read to its end either: the answer
            # closes the connection.
            body = Body(b"")
            answer = keyed.post("/v1/printers/busy/hold", content=body)
            assert answer.status_code == 204 and answer.headers["connection"] == "close"
            assert body.sent < BODY_MB // 2
            assert keyed.post("/v1/printers/busy/release").status_code == 204
            # Uploads still take files far over the bound of a JSON body.
            big = b"".join(b"G1 X%d Y1\n" % (i % 200) for i in range(600_000))  # 6 MB
            assert len(big) > 3 * MB
            stored = keyed.post("/api/files/local", files={"file": ("big.gcode", big)})
            assert stored.status_code == 201, stored.text
            stored = keyed.post("/server/files/upload", files={"file": ("big2.gcode", big)})
            assert stored.status_code == 201, stored.text
    grown = peak_memory(server) - before
    assert grown < 100 * MB, f"the server's peak memory grew by {grown // MB} MB"


def test_moonrakers_form_errors_come_in_moonrakers_shape(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"busy": bench().port})
    with server.client() as client:
        broken = client.post(
            "/server/files/upload",
            content=b"--xx\r\nnot a part",
            headers={"Content-Type": "multipart/form-data"},  # no boundary
        )
        assert "boundary" in moonraker_refused(broken, 400).lower()
        # OctoPrint's face keeps its own shape.
        broken = client.post(
            "/api/files/local", content=b"x", headers={"Content-Type": "multipart/form-data"}
        )
        assert "boundary" in octoprint_refused(broken, 400).lower()


def test_a_websocket_message_over_its_bound_closes_that_socket_alone(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"busy": bench().port})
    url = server.url.replace("http", "ws") + "/websocket"
    headers = {"X-Api-Key": KEY}
    with connect(url, additional_headers=headers, max_size=None, open_timeout=10) as big:
        request = {"jsonrpc": "2.0", "method": "server.info", "id": 1}
        big.send(json.dumps({**request, "params": {"pad": "x" * (3 * MB)}}))
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                big.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009  # too big
    with connect(url, additional_headers=headers, open_timeout=10) as small:
        small.send(json.dumps({**request, "params": {"pad": "x" * MB}}))  # within it
        while "result" not in (answer := json.loads(small.recv(timeout=10))):
            pass
        assert answer["id"] == 1 and "klippy_state" in answer["result"]


HALF_A_REQUEST = b"POST /api/login HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "
SLOW_CLIENTS = 120
MAX_CONNECTIONS = 40
HEADER_TIMEOUT = 3


def half_sent(server: Server, count: int) -> list[socket.socket]:
    """``count`` connections, each with half a request head sent, no key."""
    held = []
    for _ in range(count):
        slow = socket.create_connection(("127.0.0.1", server.port), timeout=10)
        slow.sendall(HALF_A_REQUEST)
        held.append(slow)
    return held


def closed_by_server(slow: socket.socket) -> bool:
    try:
        return slow.recv(1) == b""
    except ConnectionResetError:
        return True


@pytest.mark.parametrize("protocol", LINKS)
@pytest.mark.slow
def test_half_sent_requests_are_closed_and_crowd_out_nobody(
    tmp_path: Path,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    protocol: str,
) -> None:
    # A second printer, Marlin's, printing with its heaters on: its link drops during the
    # attack, and its safe stop must go as soon as it is back.
    lost = bench("--move-time", "0.005")
    settings = f"max_connections = {MAX_CONNECTIONS}\nheader_timeout = {HEADER_TIMEOUT}\n"
    server, fake = busy_server(
        tmp_path, bench, servers, protocol, settings, lost={"port": lost.port}
    )
    heated = "M104 S200\nM140 S60\n" + "".join(f"G1 X{i % 200} F3000\n" for i in range(4000))
    with server.client() as client:
        job = client.post("/v1/printers/lost/jobs", files={"file": ("hot.gcode", heated)})
        job_id = job.json()["id"]
        wait_for(lambda: job_state(client, job_id)["lines"] > 20, what="the hot job printing")
    files_before = open_files(server)
    with streaming_beside(server, fake):
        started = time.monotonic()
        slow = half_sent(server, SLOW_CLIENTS)
        # Never more connections than the limit: the oldest that sent nothing are closed.
        wait_for(
            lambda: open_files(server) <= files_before + MAX_CONNECTIONS + 2,
            timeout=5,
            what="the connections within their limit",
        )
        assert sum(closed_by_server(s) for s in slow[:40]) >= 40 - 5
        # A keyed client gets in at once, on a new connection each time.
        for _ in range(5):
            with server.client() as keyed:
                assert keyed.get("/v1/printers/busy").status_code == 200
            slow += half_sent(server, 10)
        # The link drops: the job is stopped, and its safe stop goes once it is back.
        assert lost.request("link_drop 2")["ok"]
        with server.client() as keyed:
            keyed.delete(f"/v1/jobs/{job_id}")
        wait_for(
            lambda: executed(lost.log_path)[-7:] == MARLIN_SAFE_STOP,
            timeout=30,
            what="the safe stop after the link came back",
        )
        assert heater_targets(lost) == {"T": 0.0, "B": 0.0}
        # Every half-sent request is closed once the header timeout is up.
        for each in slow:
            each.settimeout(HEADER_TIMEOUT + 10)
            assert closed_by_server(each)
        assert time.monotonic() - started >= HEADER_TIMEOUT
        for each in slow:
            each.close()
    log = server.stderr.read_text()
    assert "Traceback" not in log, log[-3000:]
    timed_out = f"closed connections that sent no complete request within {HEADER_TIMEOUT} s"
    crowded = f"at {MAX_CONNECTIONS} connections: closed the oldest that had sent no request"
    assert log.count(timed_out) == 1 and log.count(crowded) == 1, log[-3000:]


@pytest.mark.parametrize(
    ("soft", "hard", "wanted", "held"),
    [(300, 300, 768, 44), (300, 2000, 768, 768), (1024, 1024, 768, 768)],
)
def test_the_connections_held_fit_the_file_limit_with_room_for_the_printers(
    soft: int, hard: int, wanted: int, held: int
) -> None:
    program = (
        "import resource\n"
        f"resource.setrlimit(resource.RLIMIT_NOFILE, ({soft}, {hard}))\n"
        "from repetrel_host.server.connections import connection_limit\n"
        f"print(connection_limit({wanted}), resource.getrlimit(resource.RLIMIT_NOFILE)[0])\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=30
    )
    limit, files = map(int, done.stdout.split())
    assert limit == held and files >= held + 256, done.stderr
    assert ("at most 44 connections" in done.stderr) == (held < wanted)


def test_refusals_are_logged_once_a_minute_per_kind_with_their_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    said = RefusalLog(every=0.3)

    async def refuse() -> None:
        for _ in range(50):
            said.note("late", "closed a slow one")
        said.note("crowded", "closed an old one")
        await asyncio.sleep(0.5)  # the time is up: the rest said in one line

    with caplog.at_level(logging.WARNING, logger="repetrel_host.server"):
        asyncio.run(refuse())
    assert caplog.messages == [
        "closed a slow one",
        "closed an old one",
        "closed a slow one (49 times in the last minute)",
    ]


def test_the_units_file_limit_fits_the_default_connections() -> None:
    unit = (ROOT / "contrib" / "hyrel-server.service").read_text()
    found = re.search(r"^LimitNOFILE=(\d+)$", unit, re.MULTILINE)
    assert found is not None
    default = ServerSettings.model_fields["max_connections"].default
    assert int(found.group(1)) == default + RESERVED_FILES  # every descriptor below 1,024


def test_the_servers_connections_send_at_once_without_nagles_algorithm() -> None:
    """An answer on a kept connection went 40 ms late (Nagle's algorithm held its second
    write for the client's delayed ACK): the server's sockets say they are TCP, so asyncio
    turns the algorithm off on each connection it accepts."""
    from repetrel_host.server.main import bound

    async def scenario() -> int:
        listening = bound("127.0.0.1", 0, "--bind")
        accepted: asyncio.Future[int] = asyncio.get_running_loop().create_future()

        class Note(asyncio.Protocol):
            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                made = transport.get_extra_info("socket")
                accepted.set_result(made.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
                transport.close()

        server = await asyncio.get_running_loop().create_server(Note, sock=listening)
        try:
            port = listening.getsockname()[1]
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            return await asyncio.wait_for(accepted, 10)
        finally:
            server.close()

    assert asyncio.run(scenario()) == 1


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_refused_websockets_are_logged_once_a_minute_not_each(
    servers: Callable[..., Server],
) -> None:
    server = servers({"p": "fake"})
    for _ in range(30):  # another site's page, each refused before its upgrade
        with pytest.raises(InvalidStatus):
            connect(
                f"ws://127.0.0.1:{server.port}/websocket",
                additional_headers={"X-Api-Key": KEY, "Origin": "http://evil.example"},
                open_timeout=10,
            )
    with server.client() as client:  # the server answers on
        assert client.get("/v1/printers").status_code == 200
    server.stop()
    log = server.stderr.read_text()
    assert log.count("refused websocket upgrades") == 1, log
    assert "connection rejected" not in log and '"WebSocket /websocket" 403' not in log, log
