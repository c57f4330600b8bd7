"""The reference: real Moonraker 0.11.0 from the registry, on a small fake Klippy, asked the
same calls as hyrel-server's face; the answers' keys and value types must match (not their
values: one is a Klipper printer, the other a fake Hyrel controller). Moonraker is installed
once into a cached virtualenv (``MOONRAKER_PYTHON`` names another); the test is skipped,
saying why, where it cannot be installed."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from moonraker_api import MoonrakerClient

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.server.test_moonraker import Heard, connected, until
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
