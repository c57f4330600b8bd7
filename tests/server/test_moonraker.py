"""Moonraker's face, for real: a hyrel-server process with the fake controller on a pty,
driven by clients other projects wrote (moonraker-api, Home Assistant's Moonraker library,
over the websocket; klipperctl over HTTP): the key, the printer's objects and a subscription
to them, G-code (Klipper's own commands too) read back from the fake, the buttons a web
interface sends during a print, the link's state as Klippy's."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from moonraker_api import MoonrakerClient, MoonrakerListener
from moonraker_api.websockets.websocketclient import ClientNotAuthenticatedError

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import MARLIN_SAFE_STOP, executed
from tests.support.server import KEY, Server, free_port, gcode, server_config, wait_for

pytestmark = pytest.mark.timeout(90)


class Heard(MoonrakerListener):
    """What the server told the client: its notifications, in order."""

    def __init__(self) -> None:
        self.notifications: list[tuple[str, Any]] = []

    async def state_changed(self, state: str) -> None:
        pass

    async def on_notification(self, method: str, data: Any) -> None:
        self.notifications.append((method, data))

    def statuses(self) -> list[dict[str, Any]]:
        return [d[0] for m, d in self.notifications if m == "notify_status_update"]


def client(server: Server, listener: MoonrakerListener, key: str = KEY) -> MoonrakerClient:
    return MoonrakerClient(listener, "127.0.0.1", server.port, api_key=key)


@asynccontextmanager
async def connected(moonraker: MoonrakerClient) -> AsyncIterator[MoonrakerClient]:
    """``moonraker`` connected (its websocket's upgrade answered), disconnected after."""
    assert await moonraker.connect()
    try:
        yield moonraker
    finally:
        await moonraker.disconnect()


async def until(condition: Callable[[], Any], what: str, timeout: float = 15) -> Any:
    for _ in range(int(timeout / 0.05)):
        found = condition()
        if found:
            return found
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def targets(fake: BuiltInFake) -> dict[str, float]:
    return {name: float(t) for name, (_, t) in fake.request("status")["temperatures"].items()}


def klipperctl(server: Server, *args: str, key: str = KEY, url: str | None = None) -> Any:
    done = subprocess.run(
        [sys.executable, "-m", "klipperctl", "--url", url or server.url, "--api-key", key, *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads(done.stdout) if "--json" in args else done.stdout


def test_home_assistants_library_connects_with_the_key_and_reads_the_printer(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, _ = printer

    async def run() -> None:
        async with connected(client(server, Heard())) as moonraker:
            assert await moonraker.get_klipper_status() == "ready"
            info = await moonraker.get_server_info()
            assert info["klippy_connected"] and not info["missing_klippy_requirements"]
            assert (await moonraker.get_host_info())["hostname"]
            objects = await moonraker.get_supported_modules()
            for name in ("webhooks", "print_stats", "virtual_sdcard", "toolhead", "extruder"):
                assert name in objects
            unknown = await moonraker.call_method("printer.no_such_method")
            assert unknown["error"]["code"] == -32601
            missing = await moonraker.call_method("printer.gcode.script")
            assert missing["error"]["message"] == "No data for argument: script"
        with pytest.raises(ClientNotAuthenticatedError):
            await client(server, Heard(), key="wrong").connect()

    asyncio.run(run())


def test_a_subscription_carries_only_what_changed_and_gcode_sets_the_fakes_heater(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, fake = printer
    heard = Heard()

    async def run() -> None:
        async with connected(client(server, heard)) as moonraker:
            first = await moonraker.call_method(
                "printer.objects.subscribe",
                objects={"extruder": ["target", "temperature"], "print_stats": None},
            )
            assert first["status"]["extruder"]["target"] == 0
            assert first["status"]["print_stats"]["state"] == "standby"
            assert await moonraker.call_method("printer.gcode.script", script="M104 S120") == "ok"
            update = await until(
                lambda: next((s for s in heard.statuses() if "extruder" in s), None),
                "the extruder's update",
            )
            assert update["extruder"]["target"] == 120
            assert "print_stats" not in update  # nothing of it changed
            # Klipper's own command for it, as klipperctl and the web interfaces send it.
            said = await moonraker.call_method(
                "printer.gcode.script", script="SET_HEATER_TEMPERATURE HEATER=extruder TARGET=95"
            )
            assert said == "ok"
        # Every notification is JSON-RPC's, and the stats keep the socket fed.
        assert any(m == "notify_proc_stat_update" for m, _ in heard.notifications)
        # No "ok" told for it: Klipper sends none (the ok is a serial console's); what the
        # console says is told (HELP's list comes as responses).
        assert ("notify_gcode_response", ["ok"]) not in heard.notifications
        async with connected(client(server, heard)) as moonraker:
            assert await moonraker.call_method("printer.gcode.script", script="HELP") == "ok"
            await until(
                lambda: (
                    (
                        "notify_gcode_response",
                        ["// Available extended commands:"],
                    )
                    in heard.notifications
                ),
                "HELP's responses",
            )

    asyncio.run(run())
    assert targets(fake)["T"] == 95
    with server.client() as http:
        store = http.get("/server/gcode_store").json()["result"]["gcode_store"]
    assert [e["message"] for e in store if e["type"] == "command"] == [
        "M104 S120",
        "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=95",
        "HELP",
    ]


def test_klipperctl_reads_the_printer_and_sets_a_temperature(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, fake = printer
    info = klipperctl(server, "--json", "server", "info")
    assert info["klippy_state"] == "ready" and info["klippy_connected"] is True
    assert klipperctl(server, "--json", "printer", "info")["state"] == "ready"
    status = klipperctl(server, "status")
    assert "ready" in status.lower()
    klipperctl(server, "printer", "set-temp", "--hotend", "180", "--bed", "50")
    assert targets(fake)["T"] == 180 and targets(fake)["B"] == 50
    # As the controller's next temperature report tells it.
    wait_for(
        lambda: (
            klipperctl(server, "--json", "printer", "query", "heater_bed")["heater_bed"]["target"]
            == 50
        ),
        what="the bed's target in its object",
    )


@pytest.mark.parametrize(
    "path",
    [
        "/printer/info",
        "/server/info",
        "/machine/system_info",
        "/access/oneshot_token",
        "/printers/bench/printer/objects/list",
    ],
)
def test_a_wrong_key_or_none_is_refused_on_every_call(
    printer: tuple[Server, BuiltInFake], path: str
) -> None:
    server, _ = printer
    for headers in ({"X-Api-Key": "wrong"}, {}):
        answer = httpx.get(server.url + path, headers=headers, params={"token": "False"})
        assert answer.status_code == 401
        assert answer.json() == {"error": {"code": 401, "message": "Unauthorized", "traceback": ""}}


def test_a_refused_script_reaches_no_controller(printer: tuple[Server, BuiltInFake]) -> None:
    server, fake = printer
    answer = httpx.post(
        f"{server.url}/printer/gcode/script",
        json={"script": "M104 S222"},
        headers={"X-Api-Key": "wrong"},
    )
    assert answer.status_code == 401
    with server.client() as http:  # a command that is answered, after it
        assert http.post("/printer/gcode/script", json={"script": "M105"}).status_code == 200
    assert "M104 S222" not in executed(fake.log_path)
    assert targets(fake)["T"] == 0


def test_a_web_interfaces_pause_resume_and_cancel_buttons_during_a_print(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    """Mainsail and Fluidd send PAUSE, RESUME and CANCEL_PRINT as G-code: the same safe
    paths as the other faces, read back from print_stats and the fake's log."""
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    with server.client() as http:
        server.wait_ready("bench")
        job = http.post("/v1/printers/bench/jobs", files={"file": ("long.gcode", gcode(20000))})
        assert job.status_code == 201

        def state() -> str:
            query = http.get("/printer/objects/query", params={"print_stats": "state,filename"})
            stats: dict[str, str] = query.json()["result"]["status"]["print_stats"]
            return stats["state"]

        def script(line: str) -> None:
            answer = http.post("/printer/gcode/script", json={"script": line})
            assert answer.status_code == 200, answer.text

        wait_for(lambda: state() == "printing", what="printing")
        script("PAUSE")
        wait_for(lambda: state() == "paused", what="paused")
        script("RESUME")
        wait_for(lambda: state() == "printing", what="printing again")
        script("CANCEL_PRINT")
        wait_for(lambda: state() == "cancelled", what="cancelled")
        sdcard = http.get("/printer/objects/query?virtual_sdcard").json()["result"]["status"]
        assert 0 < sdcard["virtual_sdcard"]["progress"] < 1
    fake.request("status")
    ran = executed(fake.log_path)
    assert ran[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    assert len(ran) < 20000


def test_klippys_state_follows_the_link_through_a_firmware_restart(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, _ = printer
    heard = Heard()

    async def run() -> None:
        async with connected(client(server, heard)) as moonraker:
            await moonraker.call_method("printer.objects.subscribe", objects={"webhooks": None})
            assert await moonraker.call_method("printer.firmware_restart") == "ok"
            await until(
                lambda: any(
                    s.get("webhooks", {}).get("state") == "ready" for s in heard.statuses()
                ),
                "ready again",
            )

    asyncio.run(run())
    methods = [m for m, _ in heard.notifications if m.startswith("notify_klippy")]
    assert methods[:2] == ["notify_klippy_disconnected", "notify_klippy_ready"]  # as a restart
    states = [s["webhooks"]["state"] for s in heard.statuses() if "webhooks" in s]
    assert states[0] == "disconnected" and states[-1] == "ready"  # "startup" may come between


def test_a_trusted_network_needs_no_key_and_a_bad_one_is_one_sentence(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench()
    config = tmp_path / "server.toml"
    config.write_text(
        f'moonraker_trusted_clients = ["127.0.0.0/8"]\n[printers]\nbench = "{fake.port}"\n'
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("bench")

    async def run() -> None:
        no_key = MoonrakerClient(Heard(), "127.0.0.1", server.port)
        async with connected(no_key) as moonraker:
            assert (await moonraker.get_host_info())["state"] == "ready"

    asyncio.run(run())
    assert httpx.get(f"{server.url}/server/info").status_code == 200
    assert httpx.get(f"{server.url}/v1/printers").status_code == 403  # the other faces: keys
    config.write_text('moonraker_trusted_clients = ["192.168.1.300/24"]\n[printers]\nx = "fake"\n')
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "repetrel_host.server.main",
            "--config",
            str(config),
            "--data-dir",
            str(tmp_path / "other"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "moonraker_trusted_clients" in done.stderr and "Traceback" not in done.stderr


def test_an_emergency_stop_during_a_print_halts_the_controller_and_says_why(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    with server.client() as http:
        server.wait_ready("bench")
        job = http.post("/v1/printers/bench/jobs", files={"file": ("a.gcode", gcode(20000))})
        assert job.status_code == 201

        def stats() -> dict[str, Any]:
            query = http.get("/printer/objects/query", params={"print_stats": "state,message"})
            found: dict[str, Any] = query.json()["result"]["status"]["print_stats"]
            return found

        wait_for(lambda: stats()["state"] == "printing", what="printing")
        assert http.post("/printer/emergency_stop").json() == {"result": "ok"}
        ended = wait_for(lambda: stats()["state"] == "error" and stats(), what="the error")
    assert "emergency stop" in ended["message"]
    ran = executed(fake.log_path)
    assert "M112" in ran and len(ran) < 20000


def test_each_printer_has_its_own_face_under_its_name(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    left, right = bench(), bench()
    server = servers({"left": left.port, "right": right.port})
    server.wait_ready("left", "right")

    async def run() -> None:
        async with connected(
            MoonrakerClient(
                Heard(), "127.0.0.1", server.port, route_prefix="printers/right", api_key=KEY
            )
        ) as moonraker:
            assert await moonraker.call_method("printer.gcode.script", script="M104 S120") == "ok"

    asyncio.run(run())
    klipperctl(server, "printer", "gcode", "M140 S40", url=f"{server.url}/printers/left")
    assert targets(right)["T"] == 120 and targets(right).get("B", 0) == 0
    assert targets(left)["T"] == 0 and targets(left)["B"] == 40
    unknown = httpx.get(f"{server.url}/printers/nobody/server/info", headers={"X-Api-Key": KEY})
    assert unknown.status_code == 404
    assert unknown.json()["error"]["message"] == "no printer 'nobody'"


def test_a_hyrel_loadouts_heads_are_klippers_extruders_set_by_their_own_address(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--protocol", "hyrel")
    config = server_config(
        tmp_path, hyrel={"port": fake.port, "loadout": "wiki-two-heads", "protocol": "hyrel"}
    )
    server = servers({}, "--config", str(config))
    with server.client() as http:
        server.wait_ready("hyrel")
        heads = [h for h in http.get("/v1/printers/hyrel").json()["heaters"] if h["kind"] == "head"]
        objects = http.get("/printer/objects/list").json()["result"]["objects"]
        assert "extruder" in objects and "extruder1" in objects and "extruder2" not in objects
        script = "SET_HEATER_TEMPERATURE HEATER=extruder1 TARGET=190"
        assert http.post("/printer/gcode/script", json={"script": script}).status_code == 200
    # The loadout's second head (tool 2, slot 3), by its Hyrel address, as the page sets it.
    sent = heads[1]["command"].format(target=190)
    fake.request("status")
    assert sent in executed(fake.log_path)


def test_json_rpc_over_http_takes_a_batch_and_id_0_and_says_each_error(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, _ = printer
    batch = [
        {"jsonrpc": "2.0", "method": "printer.info", "id": 0},
        {"jsonrpc": "2.0", "method": "no.such.method", "id": 1},
        {"jsonrpc": "2.0", "method": "printer.info", "params": [1], "id": 2},
        {"jsonrpc": "2.0", "method": "server.connection.identify", "id": 3},
        {"jsonrpc": "2.0", "method": "printer.info"},  # a notification: no answer
    ]
    with server.client() as http:
        answers = http.post("/server/jsonrpc", json=batch).json()
        garbage = http.post("/server/jsonrpc", content=b"{not json").json()
    assert [a["id"] for a in answers] == [0, 1, 2, 3]
    assert answers[0]["result"]["state"] == "ready"
    assert [a["error"]["code"] for a in answers[1:]] == [-32601, -32602, 400]
    assert garbage == {
        "jsonrpc": "2.0",
        "error": {"code": -32700, "message": "Parse error"},
        "id": None,
    }


def test_a_printers_own_port_is_that_printers_face_and_a_taken_one_is_one_sentence(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    left, right = bench(), bench()
    own = free_port()
    config = server_config(
        tmp_path, left={"port": left.port}, right={"port": right.port, "moonraker_port": own}
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("left", "right")

    async def run() -> None:
        by_port = MoonrakerClient(Heard(), "127.0.0.1", own, api_key=KEY)  # a host and port
        async with connected(by_port) as moonraker:
            assert await moonraker.call_method("printer.gcode.script", script="M104 S120") == "ok"

    asyncio.run(run())
    assert targets(right)["T"] == 120 and targets(left)["T"] == 0
    # Taken: by the server itself (another data folder, the same printer's port), or the bind.
    for bind in ("127.0.0.1:0", f"127.0.0.1:{own}"):
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "repetrel_host.server.main",
                "--config",
                str(config),
                "--data-dir",
                str(tmp_path / "second"),
                "--bind",
                bind,
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert f"moonraker_port {own}" in done.stderr or f"{own} (printer right's" in done.stderr


def test_a_port_closed_on_purpose_is_klippy_disconnected_until_a_firmware_restart(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, _ = printer
    heard = Heard()

    async def run() -> None:
        async with connected(client(server, heard)) as moonraker:
            async with httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as http:
                closed = await http.post("/api/connection", json={"command": "disconnect"})
                assert closed.status_code == 204
            await until(lambda: ("notify_klippy_disconnected", None) in heard.notifications, "told")
            info = await moonraker.get_server_info()
            assert info["klippy_state"] == "disconnected" and info["klippy_connected"] is False
            assert await moonraker.call_method("printer.firmware_restart") == "ok"
            await until(lambda: ("notify_klippy_ready", None) in heard.notifications, "ready")
            assert await moonraker.get_klipper_status() == "ready"

    asyncio.run(run())


@pytest.mark.slow
def test_a_lost_link_is_klippy_shutdown_with_the_reason_then_ready_again(
    printer: tuple[Server, BuiltInFake],
) -> None:
    server, fake = printer
    heard = Heard()

    async def run() -> None:
        async with connected(client(server, heard)) as moonraker:
            await moonraker.call_method("printer.objects.subscribe", objects={"webhooks": None})
            assert fake.request("link_drop 2")["ok"]  # unplugged for 2 s, then back
            await until(lambda: ("notify_klippy_shutdown", None) in heard.notifications, "shutdown")
            await until(
                lambda: [
                    s for s in heard.statuses() if s.get("webhooks", {}).get("state") == "ready"
                ],
                "ready again",
            )

    asyncio.run(run())
    assert ("notify_klippy_ready", None) in heard.notifications
    said = [s["webhooks"] for s in heard.statuses() if "webhooks" in s]
    assert said[0]["state"] == "shutdown" and said[0]["state_message"]
    assert said[-1] == {"state": "ready", "state_message": "Printer is ready"}
