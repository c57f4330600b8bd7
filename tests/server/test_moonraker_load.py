"""What Mainsail, Fluidd and KlipperScreen ask of Moonraker as they load, in their order and
over their transports (a raw websocket with JSON-RPC batches, as Mainsail sends them; HTTP
for Fluidd's settings), against a real hyrel-server process: each answer has what the
client reads. The interfaces themselves run in a browser or on a display, which cannot be
installed here: their calls come from their sources (Mainsail's socket and store actions,
Fluidd's init, KlipperScreen's screen.py)."""

from __future__ import annotations

import asyncio
import itertools
import json
import signal
from collections.abc import Callable
from typing import Any

import aiohttp
import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import KEY, Server

pytestmark = pytest.mark.timeout(90)

SETTINGS = {"name": "Hyrel", "theme": {"primary": "#2196f3"}}  # what Mainsail keeps


class Socket:
    """A websocket as a web interface drives it: requests by id, notifications kept."""

    def __init__(self, socket: aiohttp.ClientWebSocketResponse) -> None:
        self.socket = socket
        self.ids = itertools.count()  # Mainsail's ids start at 0
        self.answers: dict[int, Any] = {}
        self.notifications: list[dict[str, Any]] = []
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for message in self.socket:
            data = json.loads(message.data)
            for one in data if isinstance(data, list) else [data]:
                if "id" in one:
                    self.answers[one["id"]] = one
                else:
                    self.notifications.append(one)

    async def batch(self, *calls: tuple[str, dict[str, Any]]) -> list[Any]:
        """The calls in one batch; each one's result (or its error)."""
        sent = [
            {"jsonrpc": "2.0", "method": name, "params": params, "id": next(self.ids)}
            for name, params in calls
        ]
        await self.socket.send_str(json.dumps(sent if len(sent) > 1 else sent[0]))
        for _ in range(400):
            if all(s["id"] in self.answers for s in sent):
                break
            await asyncio.sleep(0.025)
        answers = [self.answers[s["id"]] for s in sent]
        return [a.get("result", a.get("error")) for a in answers]

    async def call(self, name: str, **params: Any) -> Any:
        (answer,) = await self.batch((name, params))
        return answer

    def heard(self, method: str) -> list[Any]:
        return [n.get("params") for n in self.notifications if n["method"] == method]


async def connect(
    session: aiohttp.ClientSession, url: str, headers: dict[str, str] | None = None
) -> Socket:
    return Socket(await session.ws_connect(url, headers=headers or {"X-Api-Key": KEY}))


@pytest.fixture
def printer(bench: Callable[..., BuiltInFake], servers: Callable[..., Server]) -> Server:
    server = servers({"bench": bench().port})
    server.wait_ready("bench")
    return server


@pytest.mark.slow
def test_mainsails_load_sequence_and_its_settings_outlive_a_restart(
    printer: Server, bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    ws = printer.url.replace("http", "ws") + "/websocket"

    async def load() -> None:
        async with aiohttp.ClientSession() as session:
            mainsail = await connect(session, ws)
            identified = await mainsail.call(
                "server.connection.identify",
                client_name="mainsail",
                version="2.14.0",
                type="web",
                url="http://mainsail",
            )
            assert isinstance(identified["connection_id"], int)
            info, config, system, stats, database = await mainsail.batch(
                ("server.info", {}),
                ("server.config", {}),
                ("machine.system_info", {}),
                ("machine.proc_stats", {}),
                ("server.database.list", {"root": "config"}),
            )
            assert info["klippy_connected"] and info["klippy_state"] == "ready"
            assert {"history", "job_queue", "database"} <= set(info["components"])
            assert "gcodes" in info["registered_directories"]
            assert config["config"]["data_store"]["temperature_store_size"] > 0
            assert system["system_info"]["cpu_info"]["cpu_count"] >= 1
            assert "system_uptime" in stats and "throttled_state" in stats
            assert "mainsail" not in database["namespaces"]
            # Its own namespace: none yet (404), so it makes one.
            missing = await mainsail.call("server.database.get_item", namespace="mainsail")
            assert missing["code"] == -32601
            await mainsail.call(
                "server.database.post_item", namespace="mainsail", key="general", value=SETTINGS
            )
            cams = await mainsail.call("server.webcams.list")
            assert cams == {"webcams": []}  # no camera configured
            printer_info, objects = await mainsail.batch(
                ("printer.info", {}), ("printer.objects.list", {})
            )
            assert printer_info["state"] == "ready" and printer_info["hostname"]
            every = {name: None for name in objects["objects"] if not name.startswith("menu")}
            subscribed = await mainsail.call("printer.objects.subscribe", objects=every)
            assert set(subscribed["status"]) == set(every)
            status = subscribed["status"]
            assert status["configfile"]["settings"]["printer"]["kinematics"]
            assert len(status["toolhead"]["axis_maximum"]) == 4
            assert status["webhooks"]["state"] == "ready"
            help_, store, temperatures = await mainsail.batch(
                ("printer.gcode.help", {}),
                ("server.gcode_store", {}),
                ("server.temperature_store", {}),
            )
            assert "PAUSE" in help_ and store == {"gcode_store": []}
            assert set(temperatures["extruder"]) == {"temperatures", "targets", "powers"}
            await mainsail.call("printer.gcode.script", script="M104 S100")
            for _ in range(200):  # its updates and the statistics that feed its heartbeat
                targets = [
                    p[0]["extruder"]["target"]
                    for p in mainsail.heard("notify_status_update")
                    if "target" in p[0].get("extruder", {})
                ]
                if targets and mainsail.heard("notify_proc_stat_update"):
                    break
                await asyncio.sleep(0.05)
            assert targets == [100]
            assert mainsail.heard("notify_gcode_response") == []  # Klipper tells no "ok"
            await mainsail.socket.close()

    asyncio.run(load())
    printer.stop(signal.SIGTERM)
    again = servers({"bench": bench().port})
    with again.client() as http:
        kept = http.get("/server/database/item", params={"namespace": "mainsail"}).json()
    assert kept["result"]["value"] == {"general": SETTINGS}


def test_fluidds_settings_over_http(printer: Server) -> None:
    """Fluidd asks for its namespace over HTTP: 404 is fine, then it makes each root."""
    with printer.client() as http:
        first = http.get("/server/database/item", params={"namespace": "fluidd"})
        assert first.status_code == 404
        assert first.json()["error"]["message"] == "Namespace fluidd not found"
        for root in ("uiSettings", "macros", "console"):
            made = http.post(
                "/server/database/item", json={"namespace": "fluidd", "key": root, "value": {}}
            )
            assert made.json()["result"] == {"namespace": "fluidd", "key": root, "value": {}}
        http.post(
            "/server/database/item",
            json={"namespace": "fluidd", "key": "uiSettings.general.instanceName", "value": "H"},
        )
        whole = http.get("/server/database/item", params={"namespace": "fluidd"}).json()
        assert whole["result"]["value"] == {
            "uiSettings": {"general": {"instanceName": "H"}},
            "macros": {},
            "console": {},
        }
        deep = http.get(
            "/server/database/item",
            params={"namespace": "fluidd", "key": "uiSettings.general.instanceName"},
        ).json()
        assert deep["result"]["value"] == "H"
        gone = http.request(
            "DELETE", "/server/database/item", params={"namespace": "fluidd", "key": "macros"}
        )
        assert gone.json()["result"]["value"] == {}
        listed = http.get("/server/database/list").json()["result"]["namespaces"]
        assert listed == ["fluidd"]


@pytest.mark.slow
def test_klipperscreens_load_with_token_false_and_its_header(printer: Server) -> None:
    ws = printer.url.replace("http", "ws") + "/websocket?token=False"

    async def load() -> None:
        async with aiohttp.ClientSession() as session:
            screen = await connect(session, ws, {"x-api-key": KEY})
            await screen.call(
                "server.connection.identify",
                client_name="KlipperScreen",
                version="v0.4",
                type="display",
                url="",
            )
            info = await screen.call("server.info")
            for key in (
                "warnings",
                "failed_components",
                "missing_klippy_requirements",
                "components",
                "klippy_connected",
                "klippy_state",
            ):
                assert key in info
            config = await screen.call("printer.objects.query", objects={"configfile": None})
            sections = config["status"]["configfile"]["config"]
            assert {"extruder", "heater_bed", "printer"} <= set(sections)
            wanted = {
                "bed_mesh": None,  # not there: left out, as Klipper leaves it out
                "print_stats": ["print_duration", "filename", "state", "info"],
                "toolhead": ["homed_axes", "position", "extruder"],
                "extruder": ["target", "temperature", "power"],
                "webhooks": ["state", "state_message"],
            }
            status = (await screen.call("printer.objects.subscribe", objects=wanted))["status"]
            assert "bed_mesh" not in status
            assert set(status["print_stats"]) == set(wanted["print_stats"])
            assert status["toolhead"]["extruder"] == "extruder"
            await screen.socket.close()

    asyncio.run(load())


def test_a_browsers_one_shot_token_lets_one_websocket_in(printer: Server) -> None:
    with printer.client() as http:
        token = http.get("/access/oneshot_token").json()["result"]
    ws = printer.url.replace("http", "ws") + f"/websocket?token={token}"

    async def twice() -> int:
        async with aiohttp.ClientSession() as session:
            first = await session.ws_connect(ws)  # no header: the token lets it in
            await first.send_str(json.dumps({"jsonrpc": "2.0", "method": "printer.info", "id": 1}))
            answer = json.loads((await first.receive()).data)
            while "id" not in answer:
                answer = json.loads((await first.receive()).data)
            assert answer["result"]["state"] == "ready"
            await first.close()
            with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                await session.ws_connect(ws)
            return refused.value.status

    assert asyncio.run(twice()) == 401
    assert httpx.get(f"{printer.url}/printer/info", params={"token": token}).status_code == 401
