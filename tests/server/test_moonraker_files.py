"""Moonraker's files, history and job queue, for real: klipperctl (HTTP) and moonraker-api
(the websocket) against a hyrel-server process with the fake controller; what they did read
back from the server's own API and the fake's log."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
from moonraker_api import MoonrakerClient

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.server.test_moonraker import Heard, connected, klipperctl, until
from tests.server.test_octoprint_socket import Listener, passive_login, socket_url
from tests.support.helpers import MARLIN_SAFE_STOP, executed
from tests.support.images import block, encoded, picture
from tests.support.paths import DATA
from tests.support.server import KEY, Server, gcode, wait_for

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def slow(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> tuple[Server, BuiltInFake]:
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    return server, fake


def print_state(server: Server) -> str:
    state: str = klipperctl(server, "--json", "printer", "query", "print_stats")["print_stats"][
        "state"
    ]
    return state


@pytest.mark.slow
def test_a_file_uploaded_listed_described_and_downloaded(
    slow: tuple[Server, BuiltInFake], tmp_path: Path
) -> None:
    server, _ = slow
    cone = tmp_path / "cone.gcode"
    preview = encoded(picture(32, 24), "PNG")
    cone.write_text(block(preview, 32, 24) + (DATA / "cone-prusaslicer.gcode").read_text())
    klipperctl(server, "files", "upload", str(cone), "--path", "parts", "--no-progress")
    listed = klipperctl(server, "--json", "files", "list")
    assert [(f["path"], f["size"]) for f in listed] == [("parts/cone.gcode", cone.stat().st_size)]
    info = klipperctl(server, "--json", "files", "info", "parts/cone.gcode")
    assert info["slicer"] == "PrusaSlicer" and info["slicer_version"].startswith("2.")
    assert info["layer_count"] > 10 and info["estimated_time"] > 60
    assert info["filament_total"] > 0 and info["object_height"] > 0
    with server.client() as http:
        got = http.get("/server/files/gcodes/parts/cone.gcode")
        assert got.status_code == 200 and got.content == cone.read_bytes()
        # The server's own API lists the same file, in the same folder.
        assert "parts/cone.gcode" in [f["path"] for f in http.get("/v1/files").json()]
        missing = http.get("/server/files/metadata", params={"filename": "nothing.gcode"})
        assert missing.status_code == 404
        other_root = http.get("/server/files/list", params={"root": "config"})
        assert other_root.status_code == 400
        directory = http.get("/server/files/directory", params={"path": "gcodes/parts"}).json()
        assert [f["filename"] for f in directory["result"]["files"]] == ["cone.gcode"]
        assert "slicer" not in directory["result"]["files"][0]
        # extended: each file's metadata in the listing (Fluidd's and Mobileraker's list).
        args = {"path": "gcodes/parts", "extended": "true"}
        extended = http.get("/server/files/directory", params=args).json()["result"]["files"]
        assert len(extended) == 1 and extended[0]["filename"] == "cone.gcode"
        assert {k: extended[0][k] for k in info if k not in ("filename", "thumbnails")} == {
            k: v for k, v in info.items() if k not in ("filename", "thumbnails")
        }
        (thumbnail,) = extended[0]["thumbnails"]
        assert thumbnail["relative_path"] == ".thumbs/cone-32x24.png"
        shown = http.get(f"/server/files/gcodes/parts/{thumbnail['relative_path']}")
        assert shown.status_code == 200 and shown.content == preview
        gone = http.delete("/server/files/gcodes/parts/cone.gcode")
        assert gone.json()["result"]["action"] == "delete_file"
        assert http.get("/v1/files").json() == []


@pytest.mark.slow
def test_an_upload_answers_as_moonraker_and_print_true_starts_it(
    slow: tuple[Server, BuiltInFake],
) -> None:
    server, fake = slow
    with server.client() as http:
        answer = http.post(
            "/server/files/upload",
            files={"file": ("long.gcode", gcode(20000))},
            data={"root": "gcodes", "print": "true"},
        )
        assert answer.status_code == 201, answer.text
        body = answer.json()
        assert "result" not in body and body["print_started"] is True
        assert body["item"]["path"] == "long.gcode" and body["item"]["root"] == "gcodes"
        assert answer.headers["location"].endswith("/server/files/gcodes/long.gcode")
        wait_for(lambda: print_state(server) == "printing", what="printing")
        bad = http.post(
            "/server/files/upload", files={"file": ("x.gcode", "G1 X1\n")}, data={"root": "config"}
        )
        assert bad.status_code == 400
        # A file that fails its check: refused, with its first error (the one message shown).
        long_line = "G1 X1 " + "Y1 " * 40 + "\n"
        refused = http.post("/server/files/upload", files={"file": ("overlong.gcode", long_line)})
        assert refused.status_code == 400
        said = refused.json()["error"]["message"]
        assert said.startswith("overlong.gcode: refused (1 errors): error: overlong.gcode:1: "), (
            said
        )
        assert "overlong.gcode" not in [f["path"] for f in http.get("/v1/files").json()]
    klipperctl(server, "print", "pause")
    wait_for(lambda: print_state(server) == "paused", what="paused")
    klipperctl(server, "print", "resume")
    wait_for(lambda: print_state(server) == "printing", what="printing again")
    klipperctl(server, "print", "cancel", "--yes")
    wait_for(lambda: print_state(server) == "cancelled", what="cancelled")
    fake.request("status")
    ran = executed(fake.log_path)
    assert ran[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP and len(ran) < 20000
    history = klipperctl(server, "--json", "history", "list")
    assert [(j["filename"], j["status"]) for j in history] == [("long.gcode", "cancelled")]
    totals = klipperctl(server, "--json", "history", "totals")
    assert totals["total_jobs"] == 1 and totals["longest_job"] > 0
    with server.client() as http:
        job = http.get("/server/history/job", params={"uid": history[0]["job_id"]}).json()
        assert job["result"]["job"]["status"] == "cancelled"
        # Its file's metadata, as Mainsail's and Fluidd's history lists show it.
        metadata = job["result"]["job"]["metadata"]
        assert metadata["size"] == (server.data_dir / "files" / "long.gcode").stat().st_size
        assert metadata["estimated_time"] > 0 and "job_id" not in metadata
        assert history[0]["metadata"] == metadata
        assert http.get("/server/history/job", params={"uid": "FFFFFF"}).status_code == 404


@pytest.mark.slow
def test_the_job_queue_is_the_servers_queue(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    heard = Heard()
    with server.client() as http:
        server.wait_ready("bench")
        for name in ("a.gcode", "b.gcode"):
            assert http.post("/v1/files", files={"file": (name, gcode(50))}).status_code == 201

    async def run() -> None:
        async with connected(
            MoonrakerClient(heard, "127.0.0.1", server.port, api_key=KEY)
        ) as moonraker:
            await moonraker.call_method("server.job_queue.pause")
            klipperctl(server, "queue", "add", "a.gcode", "b.gcode")
            status = await moonraker.call_method("server.job_queue.status")
            assert status["queue_state"] == "paused"
            assert [j["filename"] for j in status["queued_jobs"]] == ["a.gcode", "b.gcode"]
            second = status["queued_jobs"][1]["job_id"]
            await moonraker.call_method("server.job_queue.jump", job_id=second)
            status = await moonraker.call_method("server.job_queue.status")
            assert [j["filename"] for j in status["queued_jobs"]] == ["b.gcode", "a.gcode"]
            await until(
                lambda: any(m == "notify_job_queue_changed" for m, _ in heard.notifications),
                "the queue's notification",
            )

            def finished() -> list[Any]:
                return [
                    d[0]["job"]["filename"]
                    for m, d in heard.notifications
                    if m == "notify_history_changed" and d[0]["action"] == "finished"
                ]

            # Each job ends with its part on the bed: the queue holds until started again.
            for done in (["b.gcode"], ["b.gcode", "a.gcode"]):
                klipperctl(server, "queue", "start")
                await until(lambda done=done: finished() == done, f"{done} finished", 60)
                await until(
                    lambda: (
                        klipperctl(server, "--json", "queue", "status")["queue_state"] == "paused"
                    ),
                    "held after the job",
                )

    asyncio.run(run())
    with server.client() as http:
        ended = [(j["name"], j["state"]) for j in http.get("/v1/printers/bench/jobs").json()]
    assert ended == [("b.gcode", "completed"), ("a.gcode", "completed")]  # by id, newest first


@pytest.mark.slow
def test_a_websocket_is_told_of_files_added_and_removed(
    slow: tuple[Server, BuiltInFake],
) -> None:
    server, _ = slow
    heard = Heard()

    async def run() -> list[dict[str, Any]]:
        async with connected(MoonrakerClient(heard, "127.0.0.1", server.port, api_key=KEY)):
            async with httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as http:
                made = await http.post(
                    "/server/files/upload", files={"file": ("n.gcode", "G1 X1\n")}
                )
                assert made.status_code == 201
                await http.delete("/server/files/gcodes/n.gcode")

            def changes() -> list[dict[str, Any]]:
                return [d[0] for m, d in heard.notifications if m == "notify_filelist_changed"]

            await until(lambda: len(changes()) >= 2, "two file notifications")
            return changes()

    changes = asyncio.run(run())
    assert [(c["action"], c["item"]["path"]) for c in changes] == [
        ("create_file", "n.gcode"),
        ("delete_file", "n.gcode"),
    ]


@pytest.mark.slow
def test_a_move_from_either_face_is_one_move_with_where_it_was(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """Moonraker's move and OctoPrint's, of a file and a folder: a Moonraker websocket hears
    one ``move_file`` (``move_dir``) with its ``source_item``, no delete after it (Mainsail
    reads ``source_item.path``); a copy is ``create_file``. OctoPrint's socket hears
    OctoPrint's three events of a move."""
    server = servers({"bench": bench().port})
    server.wait_ready("bench")
    heard = Heard()
    octoprint = Listener(socket_url(server))
    auth = passive_login(server)

    def changes() -> list[tuple[str, str, str | None]]:
        return [
            (d[0]["action"], d[0]["item"]["path"], d[0].get("source_item", {}).get("path"))
            for m, d in heard.notifications
            if m == "notify_filelist_changed"
        ]

    async def run() -> None:
        async with (
            connected(MoonrakerClient(heard, "127.0.0.1", server.port, api_key=KEY)),
            httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as http,
        ):
            sent = await http.post("/v1/files", files={"file": ("a.gcode", gcode(20))})
            assert sent.status_code == 201
            moved = await http.post(
                "/server/files/move", json={"source": "gcodes/a.gcode", "dest": "gcodes/b.gcode"}
            )
            assert moved.json()["result"]["source_item"] == {"path": "a.gcode", "root": "gcodes"}
            octo = {"command": "move", "destination": "c.gcode"}
            assert (await http.post("/api/files/local/b.gcode", json=octo)).status_code == 201
            await http.post("/server/files/directory", json={"path": "gcodes/box"})
            box = {"source": "gcodes/box", "dest": "gcodes/crate"}
            assert (await http.post("/server/files/move", json=box)).status_code == 200
            copy = {"source": "gcodes/c.gcode", "dest": "gcodes/crate/d.gcode"}
            assert (await http.post("/server/files/copy", json=copy)).status_code == 200
            await until(lambda: len(changes()) >= 6, "six file notifications")
            await asyncio.sleep(0.3)  # nothing more comes

    try:
        octoprint.wait(lambda: octoprint.messages, "OctoPrint's connected message")
        octoprint.send({"auth": auth})
        octoprint.wait(lambda: octoprint.of("current"), "OctoPrint's socket let in")
        asyncio.run(run())

        def files_told() -> list[str]:
            return [e for e in octoprint.events() if e.endswith(("Added", "Removed", "Moved"))]

        octoprint.wait(lambda: len(files_told()) >= 12, "OctoPrint's file events")
        events = files_told()
        moves = [
            (e["payload"]["source_path"], e["payload"]["destination_path"])
            for e in octoprint.of("event")
            if e["type"] == "FileMoved"
        ]
    finally:
        octoprint.close()
    assert changes() == [
        ("create_file", "a.gcode", None),
        ("move_file", "b.gcode", "a.gcode"),
        ("move_file", "c.gcode", "b.gcode"),
        ("create_dir", "box", None),
        ("move_dir", "crate", "box"),
        ("create_file", "crate/d.gcode", None),
    ]
    # OctoPrint's filemanager tells a move as removed, added and moved.
    move = ["Removed", "Added", "Moved"]
    assert events == [
        "FileAdded",
        *(f"File{e}" for e in move * 2),
        "FolderAdded",
        *(f"Folder{e}" for e in move),
        "FileAdded",
    ]
    assert moves == [("a.gcode", "b.gcode"), ("b.gcode", "c.gcode")]


@pytest.mark.slow
def test_print_true_while_a_job_runs_queues_the_upload(
    slow: tuple[Server, BuiltInFake], tmp_path: Path
) -> None:
    """Moonraker's answer to ``print=true`` on a busy printer: 201, not started, queued (as
    Moonraker with ``queue_gcode_uploads``). The file being printed is not replaced by an
    upload of its name: that upload is stored beside it, and the item says where."""
    server, _ = slow
    with server.client() as http:
        first = http.post(
            "/server/files/upload",
            files={"file": ("long.gcode", gcode(20000))},
            data={"print": "true"},
        )
        assert first.status_code == 201 and first.json()["print_started"] is True
        wait_for(lambda: print_state(server) == "printing", what="printing")
        printing = (server.data_dir / "files" / "long.gcode").read_bytes()
        answers = [
            http.post(
                "/server/files/upload", files={"file": (name, gcode(30))}, data={"print": "true"}
            )
            for name in ("next.gcode", "long.gcode")
        ]
        assert [a.status_code for a in answers] == [201, 201], [a.text for a in answers]
        told = [
            (a.json()["item"]["path"], a.json()["print_started"], a.json()["print_queued"])
            for a in answers
        ]
        assert told == [("next.gcode", False, True), ("long-2.gcode", False, True)]
        assert (server.data_dir / "files" / "long.gcode").read_bytes() == printing
        queue = http.get("/server/job_queue/status").json()["result"]
        assert [j["filename"] for j in queue["queued_jobs"]] == ["next.gcode", "long-2.gcode"]
        # The job runs on: the one printing is the first upload still.
        assert (
            klipperctl(server, "--json", "printer", "query", "print_stats")["print_stats"][
                "filename"
            ]
            == "long.gcode"
        )
