"""Odd input gets one sentence, never a 500 (issue 49's smaller findings): JSON nested too
deep on every face and socket, a thumbnail that is not there, an upload into a folder the
listings hide, a missing file over Moonraker's websocket, a file that starts with a UTF-8
byte order mark. A real server process; the deep JSON beside a printer streaming on."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import websocket

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.server.json_input import MAX_DEPTH, TOO_DEEP
from repetrel_host.session.job import Job
from tests.support.attack import busy_server, streaming_beside
from tests.support.helpers import executed, hyrel_send
from tests.support.server import KEY, Server, job_state, server_config, wait_for

pytestmark = pytest.mark.timeout(120)

# Past Python's parser (a RecursionError), and past the bound but not the parser.
DEEPEST = "[" * 100_000 + "]" * 100_000
DEEP_SHORT = "[" * 5000 + "]" * 5000  # under the push socket's 64 KB bound of a message
DEEP_OBJECT = '{"a":' * (MAX_DEPTH + 5) + "1" + "}" * (MAX_DEPTH + 5)
BOM = b"\xef\xbb\xbf"


def socket(server: Server, path: str, key: str | None = KEY) -> websocket.WebSocket:
    headers = [f"X-Api-Key: {key}"] if key else []
    return websocket.create_connection(f"ws://127.0.0.1:{server.port}{path}", 30, header=headers)


def json_answers(ws: websocket.WebSocket, until: Callable[[dict[str, Any]], bool]) -> Any:
    """The first message read from ``ws`` that ``until`` takes (others, notifications, skipped)."""
    while True:
        message = json.loads(ws.recv())
        if isinstance(message, dict) and until(message):
            return message


def rpc_answer(ws: websocket.WebSocket, text: str, ident: Any) -> dict[str, Any]:
    ws.send(text)
    answer: dict[str, Any] = json_answers(ws, lambda m: "method" not in m and m.get("id") == ident)
    return answer


def deep_json_everywhere(server: Server) -> None:
    """Every way JSON comes in, nested too deep: each refused in one sentence, in its face's
    shape, and each socket answers on."""
    json_type = {"Content-Type": "application/json"}
    with server.client() as client, httpx.Client(base_url=server.url, timeout=30) as anonymous:
        for body in (DEEPEST, DEEP_OBJECT):
            # The native face's and OctoPrint's (FastAPI reads the body), OctoPrint's login
            # and appkeys' request (read by hand; the request needs no key).
            for http, path in (
                (client, "/v1/printers/busy/command"),
                (client, "/api/printer/command"),
                (client, "/api/login"),
                (anonymous, "/plugin/appkeys/request"),
            ):
                open_route = path in ("/api/login", "/plugin/appkeys/request")
                sent = body
                if body is DEEPEST and open_route:  # 200 KB: over an open route's bound
                    answer = http.post(path, content=body, headers=json_type)
                    assert answer.status_code == 413, (path, answer.text)
                    sent = DEEP_SHORT  # still deeper than Python's parser goes
                answer = http.post(path, content=sent, headers=json_type)
                assert answer.status_code in (400, 422), (path, answer.text)
                if body is DEEPEST or open_route:
                    assert answer.status_code == 400 and answer.json()["error"] == TOO_DEEP, path
            # Moonraker's, over HTTP: its error shape.
            answer = client.post("/printer/gcode/script", content=body, headers=json_type)
            assert answer.status_code == 400, answer.text
            assert answer.json()["error"]["message"] == TOO_DEEP
            rpc = client.post("/server/jsonrpc", content=body, headers=json_type).json()
            assert rpc["error"] == {"code": -32700, "message": f"Parse error: {TOO_DEEP}"}
        hinted = client.get("/server/database/item", params={"namespace": "x", "key": "y"})
        assert hinted.status_code == 404  # nothing stored: the deep value below was refused
        stored = client.post(
            "/server/database/item",
            params={"namespace": "x", "key": "y", "value:json": "[" * 99 + "]" * 99},
        )
        assert stored.status_code == 400 and TOO_DEEP in stored.json()["error"]["message"]
    # Moonraker's websocket: a parse error, and the socket answers on.
    moonraker = socket(server, "/websocket")
    try:
        for body in (DEEPEST, DEEP_OBJECT):
            refused = rpc_answer(moonraker, body, None)
            assert refused["error"] == {"code": -32700, "message": f"Parse error: {TOO_DEEP}"}
        ok = rpc_answer(
            moonraker, json.dumps({"jsonrpc": "2.0", "method": "printer.info", "id": 7}), 7
        )
        assert ok["result"]["state"] == "ready"
    finally:
        moonraker.close()
    # OctoPrint's push socket: ignored, as OctoPrint ignores what it does not understand,
    # and the socket goes on (its login then its state arrive).
    with server.client() as client:
        user = client.post("/api/login", json={"passive": True}).json()
    push = socket(server, "/sockjs/websocket")
    try:
        json_answers(push, lambda m: "connected" in m)
        push.send(DEEP_SHORT)
        push.send(DEEP_OBJECT)
        push.send(json.dumps({"auth": f"{user['name']}:{user['session']}"}))
        json_answers(push, lambda m: "history" in m or "current" in m)
    finally:
        push.close()
    # SockJS's xhr_send: its plain-text 400, with the sentence.
    with server.client() as client:
        opened = client.post("/sockjs/0/deep/xhr")
        assert opened.text.startswith("o")
        sent = client.post("/sockjs/0/deep/xhr_send", content=DEEP_SHORT)
        assert sent.status_code == 400 and sent.text == TOO_DEEP


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_json_nested_too_deep_is_one_sentence_everywhere_and_costs_the_printer_nothing(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    protocol: str,
) -> None:
    server, fake = busy_server(tmp_path, bench, servers, protocol)
    with streaming_beside(server.wait_ready("busy"), fake):
        deep_json_everywhere(server)
    assert "Traceback" not in server.stderr.read_text()


@pytest.fixture
def server(servers: Callable[..., Server]) -> Server:
    return servers({"demo": "fake"}).wait_ready("demo")


def test_a_missing_thumbnail_is_a_404_in_each_faces_shape(server: Server) -> None:
    with server.client() as client:
        stored = client.post("/api/files/local", files={"file": ("cube.gcode", b"G28\n")})
        assert stored.status_code == 201, stored.text
        native = client.get("/v1/files/none.gcode/thumbnail")
        assert native.status_code == 404 and native.json()["error"] == "no file 'none.gcode'"
        plain = client.get("/v1/files/cube.gcode/thumbnail")
        assert plain.status_code == 404 and "has no thumbnail" in plain.json()["error"]
        for path in (
            "no-folder/.thumbs/cube-300x300.png",  # the 500: a folder that is not there
            "cube.gcode/.thumbs/cube-300x300.png",  # a file taken for a folder
            ".thumbs/cube-300x300.png",  # a file without previews
            ".thumbs/none-300x300.png",
        ):
            answer = client.get(f"/server/files/gcodes/{path}")
            assert answer.status_code == 404, (path, answer.text)
            said = answer.json()["error"]
            assert said["code"] == 404 and said["message"].startswith("File does not exist:")
            assert client.get(f"/printers/demo/server/files/gcodes/{path}").status_code == 404
    assert "Traceback" not in server.stderr.read_text()


def test_nothing_goes_into_a_folder_the_listings_hide(server: Server) -> None:
    gcode = ("part.gcode", b"G28\n")
    with server.client() as client:
        refusals = [
            client.post("/api/files/local", data={"path": ".thumbs"}, files={"file": gcode}),
            client.post("/api/files/local", data={"path": "a/.hidden/b"}, files={"file": gcode}),
            client.post("/v1/files", data={"folder": ".thumbs"}, files={"file": gcode}),
            client.post("/api/files/local", data={"foldername": ".secret", "path": ""}),
            client.post("/v1/folders", json={"path": ".secret"}),
        ]
        for answer in refusals:
            assert answer.status_code == 400, answer.text
            assert "nothing there is listed" in answer.json()["error"]
        moonraker = [
            client.post("/server/files/upload", data={"path": ".thumbs"}, files={"file": gcode}),
            client.post("/server/files/directory", json={"path": "gcodes/.thumbs"}),
        ]
        for answer in moonraker:
            assert answer.status_code == 400, answer.text
            assert "nothing there is listed" in answer.json()["error"]["message"]
        # A move or a copy into one: refused too; the file stays where it is listed.
        assert client.post("/api/files/local", files={"file": gcode}).status_code == 201
        moved = client.post(
            "/server/files/move",
            json={"source": "gcodes/part.gcode", "dest": "gcodes/.thumbs/part.gcode"},
        )
        assert moved.status_code == 400 and "nothing there is listed" in moved.text
        listed = [f["path"] for f in client.get("/v1/files").json()]
        assert listed == ["part.gcode"]
    assert sorted(p.name for p in (server.data_dir / "files").iterdir()) == ["part.gcode"]


def test_a_missing_file_over_moonrakers_websocket_says_so_with_moonrakers_code(
    server: Server,
) -> None:
    """Moonraker answers a refused call with its HTTP status as the JSON-RPC code, but 404
    as -32601 and 401 as -32602 (``execute_method``), and its own sentence: only an unknown
    method says "Method not found"."""
    ws = socket(server, "/websocket")
    calls = [
        ("server.files.metadata", {"filename": "none.gcode"}),
        ("server.files.delete_file", {"path": "gcodes/none.gcode"}),
        ("server.files.get_directory", {"path": "gcodes/none"}),
        ("server.history.get_job", {"uid": "00000F"}),
        ("no.such.method", {}),
        ("server.files.metadata", {}),
    ]
    try:
        answers = [
            rpc_answer(ws, json.dumps({"jsonrpc": "2.0", "method": m, "params": p, "id": i}), i)
            for i, (m, p) in enumerate(calls)
        ]
    finally:
        ws.close()
    assert [a["error"] for a in answers] == [
        {"code": -32601, "message": "Metadata not available for none.gcode"},
        {"code": -32601, "message": "File does not exist: none.gcode"},
        {"code": -32601, "message": "Directory does not exist (none)"},
        {"code": -32601, "message": "Invalid job uid: 00000F"},
        {"code": -32601, "message": "Method not found"},
        {"code": 400, "message": "No data for argument: filename"},
    ]
    with server.client() as client:  # over HTTP: the status itself
        missing = client.get("/server/files/metadata", params={"filename": "none.gcode"})
        assert missing.status_code == 404
        assert missing.json()["error"]["message"] == "Metadata not available for none.gcode"


# --- a file that starts with a UTF-8 byte order mark ------------------------------------------


def test_a_byte_order_mark_is_skipped_and_counted_in_the_offsets(tmp_path: Path) -> None:
    job = tmp_path / "bom.gcode"
    job.write_bytes(BOM + b"G28 ; home\nG1 X1\n")
    commands = list(Job(job).commands())
    assert [(number, command, offset) for number, command, _, offset in commands] == [
        (1, "G28", len(BOM) + 11),
        (2, "G1 X1", len(BOM) + 17),
    ]
    job.write_bytes(b"G28\n" + BOM + b"G1 X1\n")  # one inside a file is no mark: refused
    with pytest.raises(Exception, match=r"bom\.gcode:2: the command is not ASCII text"):
        list(Job(job).commands())


def test_hyrel_send_sends_a_marked_files_first_line_without_the_mark(tmp_path: Path) -> None:
    job = tmp_path / "bom.gcode"
    job.write_bytes(BOM + b"G28\r\nG1 X1\r\n")
    with BuiltInFake(tmp_path / "fake.log") as fake:
        result = hyrel_send(str(job), "--port", fake.port, "--no-history")
    assert result.returncode == 0, result.stderr
    assert executed(tmp_path / "fake.log")[:2] == ["G28", "G1 X1"]


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_a_marked_upload_is_taken_and_printed_without_the_mark(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path, protocol: str
) -> None:
    fake = bench("--protocol", protocol)
    config = server_config(tmp_path, bom={"port": fake.port, "protocol": protocol})
    server = servers({}, "--config", str(config)).wait_ready("bom")
    with server.client() as client:
        stored = client.post(
            "/api/files/local", files={"file": ("bom.gcode", BOM + b"G28\nG1 X1\n")}
        )
        assert stored.status_code == 201, stored.text
        assert not [f for f in stored.json()["findings"] if f.startswith("error")]
        started = client.post("/v1/printers/bom/queue", json={"file": "bom.gcode"})
        assert started.status_code == 201, started.text
        job = started.json()["id"]
        wait_for(lambda: job_state(client, job)["state"] == "completed", what="the job's end")
    assert fake.log_path is not None
    ran = executed(fake.log_path)
    assert "G28" in ran and ran[ran.index("G28") + 1] == "G1 X1", ran
    assert not [line for line in ran if "\ufeff" in line or "ï»¿" in line]
