"""The reference: real Moonraker 0.11.0 from the registry, on a small fake Klippy, asked the
same calls as hyrel-server's face; the answers' keys and value types must match (not their
values: one is a Klipper printer, the other a fake Hyrel controller). Moonraker is installed
once into a cached virtualenv (``MOONRAKER_PYTHON`` names another); the test is skipped,
saying why, where it cannot be installed."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import httpx
import pytest
import websocket
from moonraker_api import MoonrakerClient

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.server.test_moonraker import Heard, connected, until
from tests.support.paths import CACHE, TESTS, install_once
from tests.support.server import KEY, Server, free_port, gcode, wait_for

pytestmark = pytest.mark.timeout(300)  # the first run installs Moonraker (some 15 s)

VERSION = "0.11.0"
FAKE_KLIPPY = TESTS / "support" / "fake_klippy.py"

# What both are asked: (method, HTTP verb, path, arguments).
CALLS = [
    ("server.info", "GET", "/server/info", {}),
    ("printer.info", "GET", "/printer/info", {}),
    ("printer.objects.list", "GET", "/printer/objects/list", {}),
    (
        "printer.objects.query",
        "POST",
        "/printer/objects/query",
        {
            "objects": {
                name: None
                for name in (
                    "print_stats",
                    "virtual_sdcard",
                    "webhooks",
                    "toolhead",
                    "extruder",
                    "heater_bed",
                    "display_status",
                    "pause_resume",
                    "idle_timeout",
                    "gcode_move",
                    "fan",
                    "heaters",
                )
            }
        },
    ),
    ("server.files.list", "GET", "/server/files/list", {}),
    ("server.files.metadata", "GET", "/server/files/metadata", {"filename": "cube.gcode"}),
    ("server.files.get_directory", "GET", "/server/files/directory", {"path": "gcodes"}),
    ("server.history.list", "GET", "/server/history/list", {}),
    ("server.history.totals", "GET", "/server/history/totals", {}),
    ("server.job_queue.status", "GET", "/server/job_queue/status", {}),
    ("server.database.list", "GET", "/server/database/list", {}),
    ("server.temperature_store", "GET", "/server/temperature_store", {}),
    ("server.gcode_store", "GET", "/server/gcode_store", {}),
    ("server.webcams.list", "GET", "/server/webcams/list", {}),
    ("machine.system_info", "GET", "/machine/system_info", {}),
    ("machine.proc_stats", "GET", "/machine/proc_stats", {}),
    ("access.oneshot_token", "GET", "/access/oneshot_token", {}),
]
# Errors: the same status, and Moonraker's error body.
ERRORS = [
    ("an unknown method", "GET", "/printer/no_such_thing", {}),
    ("a missing argument", "GET", "/server/files/metadata", {}),
    ("a file that is not there", "GET", "/server/files/metadata", {"filename": "none.gcode"}),
    ("a namespace that is not there", "GET", "/server/database/item", {"namespace": "nope"}),
    ("the wrong verb", "GET", "/printer/print/start", {}),
]


def moonraker_python() -> Path:
    """A Python with Moonraker installed: ``MOONRAKER_PYTHON``, else a virtualenv of the
    user's cache made once."""
    given = os.environ.get("MOONRAKER_PYTHON")
    if given:
        return Path(given)
    venv = CACHE / f"moonraker-{VERSION}"
    python = venv / "bin" / "python"
    install_once(
        venv,
        f"Moonraker {VERSION}",
        [sys.executable, "-m", "venv", "--clear", str(venv)],
        [str(python), "-m", "pip", "install", "-q", f"moonraker=={VERSION}"],
        timeout=240,
    )
    return python


@pytest.fixture
def reference(tmp_path: Path) -> Iterator[str]:
    """Real Moonraker on the fake Klippy, trusting this machine; its URL."""
    python = moonraker_python()
    data = tmp_path / "printer_data"
    (data / "config").mkdir(parents=True)
    (data / "gcodes").mkdir()
    socket_path = tmp_path / "klippy_uds"
    port = free_port()
    (data / "config" / "moonraker.conf").write_text(
        f"[server]\nhost: 127.0.0.1\nport: {port}\nklippy_uds_address: {socket_path}\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n[history]\n\n[job_queue]\n"
        # OctoPrint's /api/version, which FDM Monster asks first (test_fdm_monster.py)
        "\n[octoprint_compat]\n"
    )
    log = (tmp_path / "moonraker.log").open("w")
    klippy = subprocess.Popen(
        [sys.executable, str(FAKE_KLIPPY), str(socket_path), str(data / "gcodes")],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert klippy.stdout is not None and klippy.stdout.readline().strip() == "ready"
    moonraker = subprocess.Popen(
        [str(python), "-m", "moonraker", "-d", str(data), "-n"], stdout=log, stderr=log
    )
    url = f"http://127.0.0.1:{port}"
    try:

        def ready() -> bool:
            assert moonraker.poll() is None, (tmp_path / "moonraker.log").read_text()
            try:
                info = httpx.get(f"{url}/server/info", timeout=2).json()["result"]
            except (httpx.TransportError, KeyError, ValueError):
                return False
            return bool(info["klippy_state"] == "ready")

        wait_for(ready, timeout=60, what="Moonraker and its Klippy")
        yield url
    finally:
        for process in (moonraker, klippy):
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()


def shape(value: Any) -> Any:
    """A value's keys and types, not its values (a list by its first item)."""
    if isinstance(value, dict):
        return {key: shape(item) for key, item in value.items()}
    if isinstance(value, list):
        return [shape(value[0])] if value else []
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    return "null" if value is None else type(value).__name__


def differences(ours: Any, theirs: Any, where: str = "") -> list[str]:
    """Where ``ours`` lacks a key of ``theirs`` or has another type (null matches any: a
    value not known yet)."""
    if "null" in (ours, theirs):
        return []
    if isinstance(theirs, dict):
        if not isinstance(ours, dict):
            return [f"{where or 'the answer'}: {ours} where Moonraker has an object"]
        found = []
        for key, item in theirs.items():
            place = f"{where}.{key}" if where else key
            if key not in ours:
                found.append(f"{place}: missing")
            else:
                found += differences(ours[key], item, place)
        return found
    if isinstance(theirs, list):
        if not isinstance(ours, list):
            return [f"{where}: {ours} where Moonraker has a list"]
        return differences(ours[0], theirs[0], f"{where}[]") if ours and theirs else []
    return [] if ours == theirs else [f"{where}: {ours} where Moonraker has {theirs}"]


def ask(url: str, verb: str, path: str, args: dict[str, Any], key: str | None) -> httpx.Response:
    headers = {"X-Api-Key": key} if key else {}
    if verb == "GET":
        return httpx.get(url + path, params=args, headers=headers, timeout=30)
    return httpx.post(url + path, json=args, headers=headers, timeout=30)


@pytest.fixture
def ours(bench: Callable[..., BuiltInFake], servers: Callable[..., Server]) -> Server:
    server = servers({"bench": bench().port})
    server.wait_ready("bench")
    return server


@pytest.mark.slow
def test_the_same_calls_answer_in_moonrakers_shapes(reference: str, ours: Server) -> None:
    cube = gcode(200)
    for url, key in ((reference, None), (ours.url, KEY)):
        upload = httpx.post(
            f"{url}/server/files/upload",
            files={"file": ("cube.gcode", cube)},
            headers={"X-Api-Key": key} if key else {},
            timeout=30,
        )
        assert upload.status_code == 201, upload.text
    found: list[str] = []
    for method, verb, path, args in CALLS:
        theirs = ask(reference, verb, path, args, None)
        mine = ask(ours.url, verb, path, args, KEY)
        assert theirs.status_code == 200, f"{method}: Moonraker said {theirs.text}"
        if mine.status_code != 200:
            found.append(f"{method}: HTTP {mine.status_code} {mine.text}")
            continue
        found += [f"{method}: {d}" for d in differences(shape(mine.json()), shape(theirs.json()))]
    for what, verb, path, args in ERRORS:
        theirs = ask(reference, verb, path, args, None)
        mine = ask(ours.url, verb, path, args, KEY)
        if mine.status_code != theirs.status_code:
            found.append(
                f"{what}: HTTP {mine.status_code} where Moonraker says {theirs.status_code}"
            )
        if theirs.status_code != 405 and set(mine.json()["error"]) < {"code", "message"}:
            found.append(f"{what}: {mine.json()} is not Moonraker's error body")
    assert not found, "\n".join(found)


# --- ways in and argument forms (issue 50) ------------------------------------------------

JSON = {"Content-Type": "application/json"}
# Each: (what, verb, path, headers, body); compared by status and error message, or by the
# result's keys (its top two levels).
WAYS_IN = [
    ("an empty JSON body on a GET", "GET", "/server/files/directory?path=gcodes", JSON, b""),
    ("an empty JSON body on a POST", "POST", "/printer/objects/query?webhooks", JSON, b""),
    ("a blank JSON body", "POST", "/printer/objects/query?webhooks", JSON, b" \n"),
    (
        "a query's objects and a body's",
        "POST",
        "/printer/objects/query?webhooks",
        JSON,
        b'{"objects": {"print_stats": ["state"]}}',
    ),
    ("an object's fields in the query", "GET", "/printer/objects/query?print_stats=state", {}, b""),
    (
        "a subscription naming no websocket",
        "POST",
        "/printer/objects/subscribe?connection_id=12345&webhooks",
        JSON,
        b"",
    ),
    ("a wrong key, trusted network", "GET", "/server/info", {"X-Api-Key": "wrong"}, b""),
    ("a wrong bearer", "GET", "/server/info", {"Authorization": "Bearer wrong"}, b""),
    ("a wrong access token", "GET", "/server/info?access_token=wrong", {}, b""),
    ("a wrong X-Access-Token", "GET", "/server/info", {"X-Access-Token": "wrong"}, b""),
    ("OctoPrint's apikey: not Moonraker's", "GET", "/server/info?apikey=wrong", {}, b""),
    ("printer.info by POST", "POST", "/printer/info", {}, b""),
    ("printer.objects.list by POST", "POST", "/printer/objects/list", {}, b""),
    ("printer.gcode.script by GET", "GET", "/printer/gcode/script?script=M115", {}, b""),
    ("an unknown one-shot token", "GET", "/server/info?token=False", {}, b""),
    ("OctoPrint's version, trusted network", "GET", "/api/version", {}, b""),
    ("OctoPrint's server, trusted network", "GET", "/api/server", {}, b""),
]


def call(opened: websocket.WebSocket, method: str, **params: Any) -> Any:
    """The answer to ``method`` on the websocket ``opened`` (notifications skipped)."""
    opened.send(json.dumps({"jsonrpc": "2.0", "method": method, "params": params, "id": 7}))
    while True:
        message = json.loads(opened.recv())
        if message.get("id") == 7:
            return message


def gist(answer: Any) -> Any:
    """What of an answer both servers must agree on: an error's message; a status's objects
    and their fields; "ok"; else that OctoPrint's version is named ("server")."""
    if isinstance(answer.get("error"), dict):
        return answer["error"]["message"]
    result = answer.get("result", answer)
    if not isinstance(result, dict):
        return result
    if "status" in result:
        return {name: sorted(fields) for name, fields in result["status"].items()}
    return "server" in result


def observed(url: str) -> dict[str, Any]:
    """What ``url`` answers each of :data:`WAYS_IN` (from a trusted network), and a
    websocket's subscription made over HTTP by its ``connection_id``."""
    seen: dict[str, Any] = {}
    with httpx.Client(base_url=url, timeout=30) as curl:
        for what, verb, path, headers, body in WAYS_IN:
            answer = curl.request(verb, path, headers=headers, content=body)
            seen[what] = (answer.status_code, gist(answer.json()))
        socket_url = url.replace("http", "ws", 1) + "/websocket"
        opened = websocket.create_connection(socket_url, timeout=30)
        try:
            identify = {"client_name": "FDM Monster", "version": "2.1.1", "type": "other"}
            identify["url"] = "https://github.com/fdm-monster/fdm-monster"
            identified = call(opened, "server.connection.identify", **identify)
            ident = identified["result"]["connection_id"]
            path = f"/printer/objects/subscribe?connection_id={ident}&webhooks&print_stats=state"
            answer = curl.post(path, headers=JSON)
            status = answer.json()["result"]["status"]
            subscribed = (answer.status_code, sorted(status), sorted(status["print_stats"]))
            seen["a subscription over HTTP"] = subscribed
        finally:
            opened.close()
    # A first identify with a wrong key, from a trusted network: refused, and so is every
    # call after it.
    opened = websocket.create_connection(socket_url, timeout=30)
    try:
        wrong = call(opened, "server.connection.identify", **identify, api_key="wrong")
        seen["an identify with a wrong key"] = wrong["error"]
        seen["a call after it"] = call(opened, "printer.info")["error"]
    finally:
        opened.close()
    # A wrong key at the websocket: Moonraker opens it and answers every call 401 (its
    # -32602); ours refuses the upgrade with 401. Either way it gets nothing.
    try:
        opened = websocket.create_connection(socket_url, header=["X-Api-Key: wrong"], timeout=30)
    except websocket.WebSocketBadStatusException as refused:
        seen["a wrong key's websocket gets nothing"] = refused.status_code == 401
    else:
        answer = call(opened, "printer.info")
        opened.close()
        seen["a wrong key's websocket gets nothing"] = answer["error"]["code"] == -32602
    return seen


@pytest.fixture
def ours_trusting(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> Server:
    config = tmp_path / "trusting.toml"
    config.write_text(
        f'moonraker_trusted_clients = ["127.0.0.0/8"]\n[printers]\nbench = "{bench().port}"\n'
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("bench")
    return server


@pytest.mark.slow
def test_the_ways_in_and_argument_forms_answer_as_moonrakers(
    reference: str, ours_trusting: Server
) -> None:
    theirs = observed(reference)
    mine = observed(ours_trusting.url)
    found = [
        f"{what}: {mine.get(what)} where Moonraker answers {said}"
        for what, said in theirs.items()
        if mine.get(what) != said
    ]
    assert not found, "\n".join(found)


# Klipper's commands: (what, path, arguments), answered with the same status, result or
# message, and G-code responses (the fake Klippy says them as Klipper does).
COMMANDS = [
    ("a cancel with no print", "/printer/print/cancel", {}),
    ("an extended command neither has", "/printer/gcode/script", {"script": "FOOBAR"}),
    ("a babystep", "/printer/gcode/script", {"script": "SET_GCODE_OFFSET Z_ADJUST=0.05"}),
    ("an extruder it lacks", "/printer/gcode/script", {"script": "M104 T1 S200"}),
]


@pytest.mark.slow
def test_klippers_commands_answer_and_respond_as_klipper(reference: str, ours: Server) -> None:
    found: list[str] = []

    def responses(url: str, key: str | None) -> list[str]:
        store = ask(url, "GET", "/server/gcode_store", {}, key).json()["result"]["gcode_store"]
        return [item["message"] for item in store if item["type"] == "response"]

    for what, path, args in COMMANDS:
        told = []
        for url, key in ((reference, None), (ours.url, KEY)):
            before = len(responses(url, key))
            answer = ask(url, "POST", path, args, key)
            body = answer.json()
            said = body["result"] if "result" in body else body["error"]["message"]
            # The responses are told as the call runs; wait for the last of them.
            wait_for(lambda u=url, k=key, n=before: len(responses(u, k)) > n, 5, what)
            told.append((answer.status_code, said, responses(url, key)[before:]))
        if told[1] != told[0]:
            found.append(f"{what}: ours {told[1]} where Moonraker {told[0]}")
    assert not found, "\n".join(found)


def file_changes(url: str, key: str | None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """An upload, the same name uploaded over it, a move, a copy and a delete, with a
    websocket listening: its ``notify_filelist_changed`` (but of hidden folders: Moonraker
    makes ``.thumbs``), and the second upload's answer."""
    heard = Heard()
    headers = {"X-Api-Key": key} if key else {}

    def changes() -> list[dict[str, Any]]:
        told = [d[0] for m, d in heard.notifications if m == "notify_filelist_changed"]
        return [c for c in told if not c["item"]["path"].startswith(".")]

    async def run() -> dict[str, Any]:
        port = int(url.rsplit(":", 1)[1])
        async with (
            connected(MoonrakerClient(heard, "127.0.0.1", port, api_key=key)),
            httpx.AsyncClient(base_url=url, headers=headers, timeout=30) as http,
        ):

            async def upload(text: str, told: int) -> dict[str, Any]:
                sent = await http.post("/server/files/upload", files={"file": ("a.gcode", text)})
                assert sent.status_code == 201, sent.text
                await until(lambda: len(changes()) >= told, f"{told} file notifications")
                answer: dict[str, Any] = sent.json()
                return answer

            await upload(gcode(50), 1)
            again = await upload(gcode(60), 2)
            for verb, path, args in (
                (
                    "POST",
                    "/server/files/move",
                    {"source": "gcodes/a.gcode", "dest": "gcodes/b.gcode"},
                ),
                (
                    "POST",
                    "/server/files/copy",
                    {"source": "gcodes/b.gcode", "dest": "gcodes/c.gcode"},
                ),
                ("DELETE", "/server/files/gcodes/c.gcode", {}),
            ):
                done = await http.request(verb, path, params=args)
                assert done.status_code == 200, done.text
            await until(lambda: len(changes()) >= 5, "5 file notifications")
            await asyncio.sleep(1.5)  # anything more Moonraker tells, after its delay
            return again

    again = asyncio.run(run())
    return changes(), again


@pytest.mark.slow
def test_file_changes_are_told_as_moonraker_tells_them(reference: str, ours: Server) -> None:
    """A move is one ``move_file`` with its ``source_item``, an upload over a file of the
    same name is ``create_file``, and a listing with ``extended`` has each file's metadata."""
    theirs, their_upload = file_changes(reference, None)
    mine, my_upload = file_changes(ours.url, KEY)

    def told(changes: list[dict[str, Any]]) -> list[tuple[str, str, str | None]]:
        return [
            (c["action"], c["item"]["path"], c.get("source_item", {}).get("path")) for c in changes
        ]

    assert told(theirs) == [
        ("create_file", "a.gcode", None),
        ("create_file", "a.gcode", None),
        ("move_file", "b.gcode", "a.gcode"),
        ("create_file", "c.gcode", None),
        ("delete_file", "c.gcode", None),
    ]
    assert told(mine) == told(theirs)
    found = [
        f"{m['action']}: {d}"
        for m, t in zip(mine, theirs, strict=True)
        for d in differences(shape(m), shape(t))
    ]
    assert my_upload["action"] == their_upload["action"] == "create_file"
    found += [f"upload: {d}" for d in differences(shape(my_upload), shape(their_upload))]
    args = {"path": "gcodes", "extended": "true"}
    their_list = ask(reference, "GET", "/server/files/directory", args, None).json()["result"]
    my_list = ask(ours.url, "GET", "/server/files/directory", args, KEY).json()["result"]
    assert [f["filename"] for f in my_list["files"]] == ["b.gcode"]
    # Moonraker's metadata of the file: its parsed keys, in the listing.
    assert {"uuid", "gcode_end_byte"} <= set(their_list["files"][0])
    found += [f"extended: {d}" for d in differences(shape(my_list), shape(their_list))]
    assert not found, "\n".join(found)


async def live(url: str, key: str | None) -> dict[str, Any]:
    """What a websocket client hears of an idle printer in 3 s of a subscription, then of
    ``M104 S205`` and ``M105`` over ``printer.gcode.script``."""
    headers = {"X-Api-Key": key} if key else {}
    ws_url = url.replace("http", "ws", 1) + "/websocket"
    async with (
        aiohttp.ClientSession(headers=headers) as session,
        session.ws_connect(ws_url) as socket,
    ):
        ids = iter(range(1, 100))
        heard: list[dict[str, Any]] = []

        async def call(method: str, **params: Any) -> Any:
            ident = next(ids)
            await socket.send_json(
                {"jsonrpc": "2.0", "method": method, "params": params, "id": ident}
            )
            async for message in socket:
                found = json.loads(message.data)
                if found.get("id") == ident:
                    return found["result"]
                heard.append(found)
            raise AssertionError("the websocket closed")

        async def listen(seconds: float) -> None:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(seconds):
                    async for message in socket:
                        heard.append(json.loads(message.data))

        wanted = {"toolhead": None, "extruder": ["target"]}
        first = await call("printer.objects.subscribe", objects=wanted)
        await listen(3)
        updates = [m["params"] for m in heard if m.get("method") == "notify_status_update"]
        heard.clear()
        set_it = await call("printer.gcode.script", script="M104 S205")
        query = await call("printer.objects.query", objects={"extruder": ["target"]})
        await listen(0.5)
        after_m104 = [m for m in heard if m.get("method") == "notify_gcode_response"]
        heard.clear()
        await call("printer.gcode.script", script="M105")
        await listen(0.5)
        m105 = [m["params"][0] for m in heard if m.get("method") == "notify_gcode_response"]
    return {
        "first": first,
        "updates": updates,
        "set": set_it,
        "target": query["status"]["extruder"]["target"],
        "after_m104": after_m104,
        "m105": m105,
    }


@pytest.mark.slow
def test_live_status_and_gcode_replies_as_moonraker_on_klipper(
    reference: str, ours: Server
) -> None:
    # Klipper's clock moves: four updates a second with a later eventtime each, the
    # toolhead's estimated_print_time with it; a target is set by the time the script
    # returns; no "ok" is told for a command; M105 answers in Klipper's words.
    for url, key in ((reference, None), (ours.url, KEY)):
        heard = asyncio.run(live(url, key))
        who = "Moonraker" if key is None else "hyrel-server"
        updates = heard["updates"]
        assert len(updates) >= 8, f"{who}: {len(updates)} updates in 3 s"
        times = [heard["first"]["eventtime"], *(eventtime for _, eventtime in updates)]
        assert times == sorted(times) and len(set(times)) == len(times), who
        clock = [status["toolhead"]["estimated_print_time"] for status, _ in updates]
        assert clock == sorted(clock) and clock[-1] > clock[0], who
        assert not any("extruder" in status for status, _ in updates), who
        assert heard["set"] == "ok" and heard["target"] == 205, who
        assert heard["after_m104"] == [], who
        assert len(heard["m105"]) == 1, who
        assert re.fullmatch(r"B:\d+\.\d /\d+\.\d T0:\d+\.\d /205\.0", heard["m105"][0]), who
