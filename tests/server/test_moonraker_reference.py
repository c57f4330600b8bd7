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

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.paths import TESTS
from tests.support.server import KEY, Server, free_port, gcode, wait_for

pytestmark = pytest.mark.timeout(300)  # the first run installs Moonraker (some 15 s)

VERSION = "0.11.0"
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "repetrel-host"
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
    if not (venv / "installed").exists():
        try:
            subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
            subprocess.run(
                [str(python), "-m", "pip", "install", "-q", f"moonraker=={VERSION}"],
                check=True,
                capture_output=True,
                timeout=240,
            )
        except (subprocess.SubprocessError, OSError) as exc:
            pytest.skip(f"Moonraker {VERSION} could not be installed here: {exc}")
        (venv / "installed").touch()
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
