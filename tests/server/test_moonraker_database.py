"""Moonraker's database and JSON-RPC batches under attack (issue 49, item 6): a flood of
writes costs each write its own size, off the event loop; values, keys, namespaces,
batches and their answers are bounded, each refused in a sentence, never a 500; a data
folder of an earlier version keeps its namespaces."""

from __future__ import annotations

import asyncio
import json
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from websockets.sync import client as ws_client

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.attack import busy_server, streaming_beside
from tests.support.server import KEY, Server, wait_for

pytestmark = pytest.mark.timeout(240)

FLOOD = 10_000  # post_items, in batches of
BATCH = 100  # (the most a batch may hold)
VALUE = "v" * 170  # with its key and the call, the flood is 2.4 MB of JSON, as the issue's


def call(method: str, ident: int, **params: Any) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "method": method, "params": params, "id": ident}


def written(server: Server) -> int:
    """Bytes the server process wrote so far (to files, its store's among them)."""
    assert server.process is not None
    io = Path(f"/proc/{server.process.pid}/io").read_text()
    return int(next(line for line in io.splitlines() if line.startswith("wchar:")).split()[1])


class Socket:
    """Moonraker's websocket, as a client that sends a message and waits for its answer."""

    def __init__(self, socket: aiohttp.ClientWebSocketResponse) -> None:
        self.socket = socket

    async def send(self, message: Any) -> Any:
        """The answer to ``message`` (a call or a batch); notifications are skipped."""
        await self.socket.send_str(json.dumps(message))
        while True:
            answer = json.loads((await self.socket.receive(timeout=60)).data)
            if isinstance(answer, list) or "id" in answer:
                return answer


async def on_websocket(server: Server, work: Callable[[Socket], Any]) -> Any:
    url = server.url.replace("http", "ws") + "/websocket"
    async with aiohttp.ClientSession() as session:
        socket = await session.ws_connect(url, headers={"X-Api-Key": KEY}, max_msg_size=0)
        try:
            return await work(Socket(socket))
        finally:
            await socket.close()


def flood_batches() -> list[list[dict[str, Any]]]:
    """10,000 post_items, each a new key in one namespace, in batches of 100."""
    calls = [
        call("server.database.post_item", i, namespace="flood", key=f"items.i{i}", value=VALUE)
        for i in range(FLOOD)
    ]
    return [calls[start : start + BATCH] for start in range(0, FLOOD, BATCH)]


def each_costs_its_own_size(costs: list[int]) -> None:
    """The last batches wrote no more than the first ones did (each write its own size;
    a namespace written whole each time wrote 100 times more by the end)."""
    first, last = min(costs[:5]), min(costs[-5:])
    assert last < 3 * first + (1 << 20), f"the first batches wrote {first} bytes, the last {last}"


@pytest.fixture(params=["reprap", "hyrel"])
def streaming(
    request: pytest.FixtureRequest,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
) -> tuple[Server, BuiltInFake]:
    """A server whose printer ``busy`` (on each link) can stream beside the attack."""
    server, fake = busy_server(tmp_path, bench, servers, request.param)
    return server.wait_ready("busy"), fake


@pytest.mark.slow
def test_a_flood_of_writes_over_the_websocket_costs_each_its_own_size(
    streaming: tuple[Server, BuiltInFake],
) -> None:
    server, fake = streaming

    async def flood(socket: Socket) -> list[int]:
        costs = []
        for batch in flood_batches():
            before = written(server)
            answers = await socket.send(batch)
            costs.append(written(server) - before)
            assert [a["result"]["value"] for a in answers] == [VALUE] * BATCH, answers[0]
        return costs

    with streaming_beside(server, fake):
        costs = asyncio.run(on_websocket(server, flood))
    each_costs_its_own_size(costs)
    with server.client() as http:
        kept = http.get("/server/database/item", params={"namespace": "flood"}).json()
    assert len(kept["result"]["value"]["items"]) == FLOOD


@pytest.mark.slow
def test_a_flood_of_writes_over_http_json_rpc_costs_each_its_own_size(
    streaming: tuple[Server, BuiltInFake],
) -> None:
    server, fake = streaming
    costs = []
    with streaming_beside(server, fake), server.client() as http:
        for batch in flood_batches():
            before = written(server)
            answers = http.post("/server/jsonrpc", json=batch).json()
            costs.append(written(server) - before)
            assert len(answers) == BATCH and "result" in answers[-1], answers[-1]
        # A delete costs its own size too (it reads no more than the item and its parent).
        deleted = http.post(
            "/server/jsonrpc",
            json=[
                call("server.database.delete_item", i, namespace="flood", key=f"items.i{i}")
                for i in range(BATCH)
            ],
        ).json()
        assert deleted[0]["result"]["value"] == VALUE
    each_costs_its_own_size(costs)


@pytest.mark.slow
def test_a_batch_past_its_bounds_is_refused_or_cut_in_a_sentence(
    streaming: tuple[Server, BuiltInFake],
) -> None:
    """10,000 calls of gcode_store in one batch: refused whole, none run; answers past
    4 MB: errors that say so, the batch answered."""
    server, fake = streaming
    store_flood = [call("server.gcode_store", i, count=1000) for i in range(10_000)]
    big = "b" * 900_000
    posts = [
        call("server.database.post_item", i, namespace=f"big{i}", key="k", value=big)
        for i in range(6)
    ]
    reads = [call("server.database.get_item", i, namespace=f"big{i}") for i in range(6)]

    async def attack(socket: Socket) -> None:
        refused = await socket.send(store_flood)
        assert refused["error"]["code"] == -32600
        assert refused["error"]["message"] == (
            "Invalid Request: a batch of 10000 calls, at most 100"
        )
        for post in posts:  # one by one: their answers echo 0.9 MB each
            assert "result" in await socket.send(post)
        answers = await socket.send(reads)
        kept = [a for a in answers if "result" in a]
        assert len(answers) == 6 and len(kept) == 4  # 4 of 0.9 MB fit in 4 MB, not 5
        assert answers[-1]["error"] == {
            "code": 413,
            "message": "the batch's answer would pass 4 MB: this call ran, its answer is left out",
        }

    with streaming_beside(server, fake):
        asyncio.run(on_websocket(server, attack))
        with server.client() as http:
            refused = http.post("/server/jsonrpc", json=store_flood)
            assert refused.status_code == 200  # JSON-RPC's answer, as Moonraker's HTTP gives it
            assert refused.json()["error"]["code"] == -32600


@pytest.fixture
def server(bench: Callable[..., BuiltInFake], servers: Callable[..., Server]) -> Server:
    return servers({"bench": bench().port}).wait_ready("bench")


def refused(answer: Any) -> tuple[int, str]:
    """Moonraker's error over HTTP: its status and sentence (its body's own shape)."""
    error = answer.json()["error"]
    assert error["code"] == answer.status_code
    return answer.status_code, error["message"]


def test_values_keys_and_namespaces_past_their_bounds_are_refused(server: Server) -> None:
    deep_value: Any = 1
    for _ in range(31):
        deep_value = [deep_value]
    with server.client() as http:
        item = "/server/database/item"
        ok = http.post(item, json={"namespace": "n", "key": "a", "value": deep_value})
        assert ok.status_code == 200  # 1 part and 31 levels: 32
        too_deep = http.post(item, json={"namespace": "n", "key": "a.b", "value": deep_value})
        assert refused(too_deep) == (
            400,
            "Invalid value: nested deeper than 32 levels with its key",
        )
        long_key = ".".join(["k"] * 5000)
        for verb in ("GET", "POST", "DELETE"):
            answer = http.request(
                verb, item, params={"namespace": "n", "key": long_key, "value": "1"}
            )
            assert refused(answer) == (400, "Invalid key: 5000 parts, at most 32")
        listed = http.post(item, json={"namespace": "n", "key": ["k"] * 5000, "value": 1})
        assert refused(listed) == (400, "Invalid key: 5000 parts, at most 32")
        control = http.post(item, json={"namespace": "n", "key": ["a\x1fb"], "value": 1})
        assert refused(control) == (400, "Invalid key: a part holds a control character")
        name = http.post(item, json={"namespace": "n" * 300, "key": "a", "value": 1})
        assert refused(name) == (400, "Invalid namespace: a name of at most 256 bytes")

    async def big_values(socket: Socket) -> None:
        huge = await socket.send(
            call(
                "server.database.post_item", 1, namespace="n", key="x", value="h" * (3 << 19)
            )  # 1.5 MB: a message may have 2
        )
        assert huge["error"] == {"code": 400, "message": "Invalid value: larger than 1 MB as JSON"}
        # 948 levels (the issue's): refused, so it cannot answer 500 later.
        nested = "[" * 948 + "]" * 948
        message = json.dumps(call("server.database.post_item", 2, namespace="n", key="d"))
        text = message.replace('"key": "d"', f'"key": "d", "value": {nested}')
        await socket.socket.send_str(text)
        answer = json.loads((await socket.socket.receive(timeout=30)).data)
        while "id" not in answer:
            answer = json.loads((await socket.socket.receive(timeout=30)).data)
        # Refused as it is read (no client nests JSON that deep), on the socket that goes on.
        assert answer["error"]["code"] == -32700
        assert "nested too deep" in answer["error"]["message"]
        # Deep enough to be read, too deep to be kept: refused as it is stored.
        deep = await socket.send(
            call("server.database.post_item", 3, namespace="deep", key="e", value=[[[[[[[]]]]]]])
        )
        assert "result" in deep
        forty = json.loads("[" * 40 + "]" * 40)
        refused_deep = await socket.send(
            call("server.database.post_item", 4, namespace="deep", key="f", value=forty)
        )
        assert refused_deep["error"]["code"] == 400, refused_deep
        await socket.send(call("server.database.delete_item", 5, namespace="deep", key="e"))
        filled = [
            call("server.database.post_item", i, namespace="full", key=f"k{i}", value="f" * 700_000)
            for i in range(3)
        ]
        answers = [await socket.send(each) for each in filled]  # a message holds 2 MB at most
        assert "result" in answers[1]
        assert answers[2]["error"] == {
            "code": 400,
            "message": "Namespace 'full' would pass 2 MB: not stored",
        }
        many = [
            call("server.database.post_item", i, namespace=f"ns{i}", key="k", value=i)
            for i in range(100)
        ]
        answers = await socket.send(many)  # 100 and "n" and "full": two too many
        assert [a["error"]["message"] for a in answers if "error" in a] == [
            "Too many namespaces: at most 100"
        ] * 2

    asyncio.run(on_websocket(server, big_values))
    with server.client() as http:
        whole = http.get("/server/database/item", params={"namespace": "n"})
        assert whole.json()["result"]["value"] == {"a": deep_value}
        assert len(http.get("/server/database/list").json()["result"]["namespaces"]) == 100


def test_items_nest_as_moonrakers_do(server: Server) -> None:
    """A write below an object splits it, below anything else replaces it by an object;
    a delete leaves an emptied object below the top, and drops an emptied namespace."""
    with server.client() as http:
        item = "/server/database/item"

        def post(key: str | list[str], value: Any) -> None:
            answer = http.post(item, json={"namespace": "ui", "key": key, "value": value})
            assert answer.json()["result"] == {"namespace": "ui", "key": key, "value": value}

        def get(key: str | None = None) -> Any:
            params = {"namespace": "ui"} | ({"key": key} if key is not None else {})
            return http.get(item, params=params)

        def delete(key: str) -> Any:
            answer = http.request("DELETE", item, params={"namespace": "ui", "key": key})
            return answer.json()["result"]["value"]

        post("general", {"a": 1, "b": {"c": 2}})
        post("general.b.d", 3)
        post(["x.y", "z"], 4)  # a part may hold a dot when the key is a list
        post("n", 5)
        post("n.m", 6)  # not an object: replaced by one
        assert get().json()["result"]["value"] == {
            "general": {"a": 1, "b": {"c": 2, "d": 3}},
            "x.y": {"z": 4},
            "n": {"m": 6},
        }
        assert get("general.b").json()["result"]["value"] == {"c": 2, "d": 3}
        assert get("general.b.c").json()["result"]["value"] == 2
        assert delete("general.b.c") == 2 and delete("general.b.d") == 3
        assert get("general").json()["result"]["value"] == {"a": 1, "b": {}}
        assert delete("general.a") == 1
        assert refused(get("general.a")) == (404, "Key 'general.a' in namespace 'ui' not found")
        assert refused(get("n.m.q")) == (404, "Key 'n.m.q' in namespace 'ui' not found")
        assert refused(get("x.y")) == (404, "Key 'x.y' in namespace 'ui' not found")
        dotted = http.request("DELETE", item, json={"namespace": "ui", "key": ["x.y"]})
        assert dotted.json()["result"]["value"] == {"z": 4}
        assert delete("general") == {"b": {}} and delete("n") == {"m": 6}
        # Nothing left: the namespace is gone, as Moonraker drops an emptied one.
        assert refused(get()) == (404, "Namespace ui not found")
        assert "ui" not in http.get("/server/database/list").json()["result"]["namespaces"]


def test_a_data_folder_of_an_earlier_version_keeps_its_namespaces(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    """Its job store kept each namespace whole: moved to the database at start, an item
    nested past the bounds (948 levels, which answered 500 for good) left out, and a
    namespace too deep to read at all."""
    data = tmp_path / "data"
    data.mkdir()
    old = sqlite3.connect(data / "jobs.sqlite")
    old.execute("CREATE TABLE client_data (namespace TEXT PRIMARY KEY, value TEXT NOT NULL)")
    settings = {"general": {"locale": "de", "theme": {"dark": True}}, "macros": {}}
    deep = {"fine": 1, "deep": json.loads("[" * 948 + "]" * 948)}
    old.executemany(
        "INSERT INTO client_data VALUES (?, ?)",
        [
            ("mainsail", json.dumps(settings)),
            ("attacked", json.dumps(deep)),
            ("unreadable", '{"x": ' + "[" * 5000 + "]" * 5000 + "}"),  # past json's reach
        ],
    )
    old.commit()
    old.close()
    server = servers({"bench": bench().port}).wait_ready("bench")
    with server.client() as http:
        item = "/server/database/item"
        kept = http.get(item, params={"namespace": "mainsail"}).json()
        assert kept["result"]["value"] == settings
        assert http.get(item, params={"namespace": "attacked"}).json()["result"]["value"] == {
            "fine": 1
        }
        listed = http.get("/server/database/list").json()["result"]["namespaces"]
        assert sorted(listed) == ["attacked", "mainsail"]
    tables = sqlite3.connect(data / "jobs.sqlite").execute("SELECT name FROM sqlite_master")
    assert "client_data" not in {row[0] for row in tables}
    assert "left out" in server.stderr.read_text()


@pytest.mark.slow
def test_a_websocket_that_reads_none_of_its_big_answers_is_closed(server: Server) -> None:
    """Its answers are kept unsent up to 32 MB, not without end: past that it is closed."""
    big = "r" * 900_000
    with server.client() as http:
        stored = http.post(
            "/server/database/item", json={"namespace": "r", "key": "k", "value": big}
        )
        assert stored.status_code == 200
    url = server.url.replace("http", "ws") + "/websocket"
    read = call("server.database.get_item", 0, namespace="r", key="k")
    # A queue of one message: the client stops reading once it holds one.
    with ws_client.connect(url, additional_headers={"X-Api-Key": KEY}, max_queue=1) as socket:
        for _ in range(60):  # 54 MB of answers
            socket.send(json.dumps(read))
        wait_for(lambda: "reads nothing: closed" in server.stderr.read_text(), what="the close")
    assert server.stderr.read_text().count("reads nothing: closed") == 1
    with server.client() as http:
        assert http.get("/server/database/list").json()["result"]["namespaces"] == ["r"]
