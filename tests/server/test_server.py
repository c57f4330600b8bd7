"""The print server, for real: a hyrel-server process, HTTP over loopback, the fake
controller on a pty (started here, so that its executed log tells what ran)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
import socket
import sqlite3
import stat
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiomqtt
import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.fake_camera import png
from tests.support.helpers import MARLIN_SAFE_STOP, executed, hyrel_send, run_server_cli
from tests.support.paths import DATA, ROOT
from tests.support.server import (
    CAMERA,
    KEY,
    Server,
    camera_config,
    commands_of,
    free_port,
    gcode,
    job_state,
    server_config,
    wait_for,
)


def test_an_upload_made_as_prusaslicer_makes_it_is_printed_exactly_once(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    text = gcode(400)
    with server.client() as client:
        # PrusaSlicer's "Test": GET api/version, an "api" field and text "OctoPrint...".
        version = client.get("/api/version").json()
        assert version["api"] and version["text"].startswith("OctoPrint")
        # Its "Upload and Print": print, path, then the file, multipart, with the key.
        answer = client.post(
            "/api/files/local",
            data={"print": "true", "path": ""},
            files={"file": ("cube.gcode", text.encode(), "application/octet-stream")},
        )
        assert answer.status_code == 201, answer.text
        body = answer.json()
        assert body["done"] is True and body["files"]["local"]["name"] == "cube.gcode"
        job_id = body["job"]["id"]
        done = wait_for(lambda: job_state(client, job_id)["state"] == "completed", what="the job")
        assert done
        record = job_state(client, job_id)
        assert record["lines"] == 401 and record["last_line"] == 401 and record["error"] is None
        # The part is on the bed: nothing more starts until someone says so.
        assert client.get("/v1/printers/bench").json()["held"] is True
        listed = client.get("/api/files").json()["files"]
        assert [f["name"] for f in listed] == ["cube.gcode"]
        resource = client.get(body["files"]["local"]["refs"]["resource"]).json()
        assert resource["size"] == len(text)
        # OctoPrint keeps the finished job's file and progress; the held queue says so.
        job = client.get("/api/job").json()
        assert job["state"] == "Operational (bed not cleared)"
        assert job["job"]["file"]["name"] == "cube.gcode"
        assert job["progress"]["completion"] == 100.0
    fake.request("status")  # the log is complete
    assert executed(fake.log_path)[-401:] == commands_of(text)
    assert executed(fake.log_path).count("G28") == 1


def test_upload_without_print_waits_until_selected_and_started(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    # Every start waits for a release (a farm's): a start while held is refused.
    server = servers({"bench": fake.port}, "--start-waits-for-release")
    with server.client() as client:
        answer = client.post(
            "/printers/bench/api/files/local",
            data={"select": "true", "print": "false"},
            files={"file": ("part.gcode", b"G28\nG1 X5\n")},
        )
        assert answer.status_code == 201 and "job" not in answer.json()
        assert client.get("/v1/printers/bench/jobs").json() == []
        assert client.get("/api/job").json()["job"]["file"]["name"] == "part.gcode"
        assert client.post("/api/job", json={"command": "start"}).status_code == 204
        jobs = wait_for(
            lambda: [
                j for j in client.get("/v1/printers/bench/jobs").json() if j["state"] == "completed"
            ],
            what="the started job",
        )
        assert jobs[0]["name"] == "part.gcode"
        # The part is on the bed: a start says so (a slicer shows OctoPrint's "error").
        refused = client.post("/api/job", json={"command": "start"})
        assert refused.status_code == 409 and "still on the bed" in refused.json()["error"]
        # Once released, start prints the last job's file again, as OctoPrint's does.
        assert client.post("/v1/printers/bench/release").status_code == 204
        assert client.post("/api/job", json={"command": "start"}).status_code == 204
        wait_for(
            lambda: (
                len([j for j in client.get("/v1/printers/bench/jobs").json()]) == 2
                and client.get("/v1/printers/bench/jobs").json()[0]["state"] == "completed"
            ),
            what="the job printed again",
        )
        client.post("/v1/printers/bench/release")
        assert (
            client.post("/api/files/local/part.gcode", json={"command": "unselect"}).status_code
            == 409
        )
        # Nothing selected and no last job to print again: nothing to start.
        assert (
            client.post("/api/files/local/part.gcode", json={"command": "select"}).status_code
            == 204
        )
        assert (
            client.post("/api/files/local/part.gcode", json={"command": "unselect"}).status_code
            == 204
        )
        refused = client.post("/api/job", json={"command": "start"})
        assert refused.status_code == 409 and "no file is selected" in refused.json()["error"]
    fake.request("status")
    assert executed(fake.log_path).count("G1 X5") == 2


@pytest.mark.slow
def test_the_event_stream_tells_states_jobs_progress_and_temperatures(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.002")
    server = servers({"bench": fake.port})
    seen: list[dict[str, Any]] = []
    completed = False
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        with client.stream("GET", "/v1/events", params={"printer": "bench"}) as stream:
            lines = stream.iter_lines()
            job_id = client.post(
                "/v1/printers/bench/jobs", files={"file": ("seen.gcode", gcode(600))}
            ).json()["id"]
            for line in lines:
                if line.startswith("data: "):
                    seen.append(json.loads(line[len("data: ") :]))
                    event = seen[-1]
                    completed |= event["type"] == "job" and event["job"]["state"] == "completed"
                    states = [e["state"] for e in seen if e["type"] == "printer"]
                    if (
                        completed
                        and states[-1] == "ready"
                        and any(e["type"] == "temperatures" for e in seen)
                    ):
                        break  # temperatures come every 2 s; ready follows the job's end
    first = seen[0]
    assert first["type"] == "printer" and first["name"] == "bench" and first["state"] == "ready"
    jobs = [e["job"]["state"] for e in seen if e["type"] == "job" and e["job"]["id"] == job_id]
    assert jobs == ["queued", "printing", "completed"]
    progress = [e["lines"] for e in seen if e["type"] == "progress"]
    assert progress and progress == sorted(progress) and progress[-1] == 601
    states = [e["state"] for e in seen if e["type"] == "printer"]
    assert "printing" in states and states[-1] == "ready"
    assert any(e["type"] == "temperatures" and "T" in e["readings"] for e in seen)


@pytest.mark.slow
def test_hyrel_send_submits_to_the_server_follows_lists_and_cancels(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.002")
    server = servers({"bench": fake.port})
    job = tmp_path / "part.gcode"
    job.write_text(gcode(300))

    def send(*args: str, key: str = KEY) -> subprocess.CompletedProcess[str]:
        return hyrel_send(*args, "--server", server.url, env={"HYREL_API_KEY": key})

    sent = send(str(job))
    assert sent.returncode == 0, sent.stderr
    assert "part.gcode: queued on printer bench (ready)" in sent.stdout
    assert "part.gcode: completed: 301 lines (to line 301)" in sent.stdout
    # The queue is held now (the part is on the bed): --release says the bed is clear.
    again = send(str(job), "--release")
    assert again.returncode == 0, again.stderr
    assert "part.gcode: completed: 301 lines (to line 301)" in again.stdout
    listed = send("--list", "--printer", "bench")
    assert listed.returncode == 0 and listed.stdout.count("completed") == 2
    # Each ended job's duration and end, in hyrel-send's one format.
    assert len(re.findall(r"\(took [\d.]+s, ended \d\d:\d\d\)\n", listed.stdout)) == 2
    again = send("--cancel", "1")
    assert again.returncode == 2 and "job 1 is completed: nothing to cancel" in again.stderr
    refused = send(str(job), key="wrong")
    assert refused.returncode == 2 and "a valid API key is needed" in refused.stderr
    nobody = hyrel_send("--list", "--server", "127.0.0.1:9")
    assert nobody.returncode == 3 and "cannot reach the print server" in nobody.stderr
    assert executed(fake.log_path).count("G28") == 2  # each job once


def test_an_m0_pauses_until_resume_and_the_queue_can_be_reordered(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port}, "--automatic-transition")

    def submit(client: httpx.Client, name: str, text: str) -> int:
        answer = client.post("/v1/printers/bench/jobs", files={"file": (name, text)})
        return int(answer.json()["id"])

    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        assert client.post("/v1/printers/bench/hold").status_code == 204
        first = submit(client, "first.gcode", "G28\nM0 ; look at the first layer\nG1 X5\n")
        second = submit(client, "second.gcode", "G1 X2\n")
        third = submit(client, "third.gcode", "G1 X3\n")
        moved = client.post(f"/v1/jobs/{third}/move", json={"before": second}).json()
        assert [j["id"] for j in moved if j["state"] == "queued"] == [first, third, second]
        assert client.post(f"/v1/jobs/{first}/move", json={"before": 999}).status_code == 409
        assert client.post("/v1/printers/bench/release").status_code == 204
        wait_for(lambda: job_state(client, first)["state"] == "paused", what="the M0")
        assert client.get("/v1/printers/bench").json()["state"] == "paused"
        assert client.get("/api/job").json()["state"] == "Paused"
        assert client.post("/v1/printers/bench/resume").status_code == 204
        wait_for(lambda: job_state(client, second)["state"] == "completed", what="the queue")
        assert [job_state(client, j)["state"] for j in (first, third)] == ["completed"] * 2
        assert client.post(f"/v1/jobs/{first}/move", json={}).status_code == 409
    assert executed(fake.log_path)[-5:] == ["G28", "M400", "G1 X5", "G1 X3", "G1 X2"]


# --- never losing anything -----------------------------------------------------------------


@pytest.mark.slow
def test_kill_9_mid_job_keeps_the_queue_and_marks_the_job_interrupted(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    with server.client() as client:
        first = client.post("/v1/printers/bench/jobs", files={"file": ("long.gcode", gcode(3000))})
        second = client.post("/v1/printers/bench/jobs", files={"file": ("next.gcode", gcode(5))})
        assert first.status_code == second.status_code == 201
        first_id, second_id = first.json()["id"], second.json()["id"]
        wait_for(lambda: job_state(client, first_id)["lines"] > 200, what="progress on record")
    server.stop(signal.SIGKILL)
    fake.request("status")
    ran = executed(fake.log_path)

    restarted = servers({"bench": fake.port})
    with restarted.client() as client:
        record = job_state(client, first_id)
        assert record["state"] == "interrupted"
        # Not sent as the server ended; sent once the printer answered (maybe by now).
        assert record["error"].startswith("the server ended while the job was streaming")
        # Acknowledged through at least the line on record: it did run.
        assert 200 < record["last_line"] <= len(ran)
        assert job_state(client, second_id)["state"] == "queued"
        printer = client.get("/v1/printers/bench").json()
        assert printer["held"] is True
        # The interrupted job's safe stop goes first, then nothing starts by itself.
        wait_for(lambda: executed(fake.log_path)[-7:] == MARLIN_SAFE_STOP, what="the safe stop")
        time.sleep(1.0)
        assert (
            "its safe stop went once the printer answered" in job_state(client, first_id)["error"]
        )
        assert job_state(client, second_id)["state"] == "queued"
        assert client.post("/v1/printers/bench/release").status_code == 204
        wait_for(lambda: job_state(client, second_id)["state"] == "completed", what="job 2")
    assert executed(fake.log_path)[-6:] == commands_of(gcode(5))


@pytest.mark.slow
def test_sigterm_stops_the_job_with_its_safe_stop_and_exits(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    with server.client() as client:
        job_id = client.post(
            "/v1/printers/bench/jobs", files={"file": ("long.gcode", gcode(3000))}
        ).json()["id"]
        wait_for(lambda: client.get("/v1/printers/bench").json()["job"], what="the job")
        wait_for(lambda: client.get("/v1/printers/bench").json()["job"]["lines"] > 100)
        with client.stream("GET", "/v1/events"):  # a page left open must not hold the stop
            started = time.monotonic()
            assert server.stop(signal.SIGTERM) == 0
            assert time.monotonic() - started < 20
    fake.request("status")
    ran = executed(fake.log_path)
    assert ran[-7:] == MARLIN_SAFE_STOP and len(ran) < 3000
    restarted = servers({"bench": fake.port})
    with restarted.client() as client:
        record = job_state(client, job_id)
        assert record["state"] == "interrupted" and "safe stop" in record["error"]
        assert client.get("/v1/printers/bench").json()["held"] is True


HEAT = (DATA / "heat.gcode").read_text()  # M190 S60, M109 S200...


def heater_targets(fake: BuiltInFake) -> dict[str, float]:
    return {name: float(t) for name, (_, t) in fake.request("status")["temperatures"].items()}


@pytest.mark.slow
def test_a_cancel_during_the_heat_up_breaks_the_wait_and_is_answered_when_safe(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--heat-rate", "1")
    server = servers({"bench": fake.port})
    with server.client() as client:
        job_id = client.post(
            "/v1/printers/bench/jobs", files={"file": ("heat.gcode", HEAT)}
        ).json()["id"]
        wait_for(lambda: "M140 S60" in executed(fake.log_path), what="the bed heating")
        started = time.monotonic()
        answer = client.delete(f"/v1/jobs/{job_id}")
        assert answer.status_code == 200, answer.text
        assert time.monotonic() - started < 10  # M108 ended M190's wait (and M109's)
        record = answer.json()
        assert record["state"] == "cancelled" and record["error"] is None
        assert record["safe_stop"] is None
        done = [c for c in executed(fake.log_path) if c != "M108"]
        assert done[-7:] == MARLIN_SAFE_STOP and heater_targets(fake) == {"T": 0.0, "B": 0.0}
        # What the controller ran after the cancel is on record: a resume runs none twice.
        ran = done[done.index("G21") : -7]
        assert ran == commands_of(HEAT)[1 : len(ran) + 1] and record["last_line"] == len(ran) + 1


@pytest.mark.slow
def test_a_stop_nothing_can_break_is_owed_across_a_restart(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--heat-rate", "1", "--no-emergency-parser")
    server = servers({"bench": fake.port}, "--stop-timeout", "3")
    with server.client() as client:
        job_id = client.post(
            "/v1/printers/bench/jobs", files={"file": ("heat.gcode", HEAT)}
        ).json()["id"]
        wait_for(lambda: "M140 S60" in executed(fake.log_path), what="the bed heating")
        answer = client.delete(f"/v1/jobs/{job_id}")
        # Answered at once: accepted, still stopping, and why.
        assert answer.status_code == 202, answer.text
        assert "waiting for a heater (M190 S60" in answer.json()["stopping"]
        assert "no emergency parser" in answer.json()["stopping"]
        started = time.monotonic()
        assert server.stop(signal.SIGTERM) == 75  # the stop left owed: said by the exit code
        assert time.monotonic() - started < 20
    assert heater_targets(fake)["B"] == 60.0  # truly still on
    fake.request("heat_rate none")  # the wait ends; what the controller held runs
    restarted = servers({"bench": fake.port})
    with restarted.client() as client:
        wait_for(
            lambda: job_state(client, job_id)["safe_stop"] == "sent", what="the owed safe stop"
        )
        record = job_state(client, job_id)
    assert record["state"] == "cancelled" and "the safe stop was abandoned" in record["error"]
    assert executed(fake.log_path)[-7:] == MARLIN_SAFE_STOP
    assert heater_targets(fake) == {"T": 0.0, "B": 0.0}


@pytest.mark.slow
def test_a_vanished_link_comes_back_and_the_next_job_runs(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        fake.request("link_drop 1.5")
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] != "ready", 10)
        job_id = client.post(
            "/v1/printers/bench/jobs", files={"file": ("after.gcode", gcode(20))}
        ).json()["id"]
        wait_for(lambda: job_state(client, job_id)["state"] == "completed", what="the job")
        assert client.post("/api/printer/command", json={"command": "M105"}).status_code == 204


def test_a_printer_that_is_not_there_does_not_stop_the_server(
    servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"gone": str(tmp_path / "no-such-tty"), "demo": "fake"})
    with server.client() as client:
        printers = {p["name"]: p for p in client.get("/v1/printers").json()}
        assert printers["gone"]["state"] == "disconnected"
        job = client.post("/v1/printers/gone/jobs", files={"file": ("a.gcode", gcode(3))})
        assert job.status_code == 201 and job.json()["state"] == "queued"  # kept for later
        refused = client.post("/v1/printers/gone/command", json={"command": "M105"})
        assert refused.status_code == 409 and "not connected" in refused.json()["detail"]
        wait_for(lambda: client.get("/v1/printers/demo").json()["state"] == "ready")
        assert client.get("/printers/demo/api/printer").json()["state"]["text"] == "Operational"
        assert client.get("/printers/gone/api/printer").status_code == 409
        assert client.get("/printers/nope/api/job").status_code == 404


def test_uploaded_files_are_deleted_unless_a_job_still_needs_them(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port}, "--automatic-transition")
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        client.post("/v1/printers/bench/hold")
        kept = client.post("/v1/printers/bench/jobs", files={"file": ("kept.gcode", gcode(5))})
        client.post("/api/files/local", files={"file": ("spare.gcode", gcode(5))})
        client.post("/api/files/local", data={"path": "old"}, files={"file": ("x.gcode", b"G28\n")})
        busy = client.delete("/api/files/local/kept.gcode")
        assert busy.status_code == 409
        assert (
            busy.json()["detail"]
            == f"'kept.gcode' is used by job {kept.json()['id']}: cancel it first"
        )
        assert server.client(key=None).delete("/v1/files/spare.gcode").status_code == 403
        assert client.delete("/v1/files/spare.gcode").status_code == 204
        assert client.delete("/api/files/local/old/x.gcode").status_code == 204
        assert client.delete("/api/files/local/spare.gcode").status_code == 404
        assert client.delete("/api/files/local/../jobs.sqlite").status_code in (400, 404)
        assert [f["path"] for f in client.get("/v1/files").json()] == ["kept.gcode"]
        client.post("/v1/printers/bench/release")
        wait_for(lambda: job_state(client, kept.json()["id"])["state"] == "completed")
        assert client.delete("/api/files/local/kept.gcode").status_code == 204  # done with it
        assert [(f["name"], f["type"]) for f in client.get("/api/files").json()["files"]] == [
            ("old", "folder")
        ]
    assert (server.data_dir / "jobs.sqlite").exists()


# --- camera snapshots --------------------------------------------------------------------


def test_m790_and_m791_take_snapshots_that_the_api_serves(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.002")
    ports = {"bench": fake.port, "blind": "fake"}
    config = camera_config(tmp_path, ports, bench=f"{CAMERA} {{path}}")
    server = servers({}, "--config", str(config))
    layers = "".join(f"M790\nG1 Z{z}\n" + gcode(100, start=z) for z in range(1, 4))
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        assert client.get("/v1/printers/bench").json()["camera"] is True
        job = client.post(
            "/v1/printers/bench/jobs", files={"file": ("shots.gcode", f"{layers}M791\n")}
        ).json()
        wait_for(lambda: job_state(client, job["id"])["state"] == "completed", what="the job")
        shots = wait_for(
            lambda: [
                s for s in client.get("/v1/printers/bench/snapshots").json() if "-job" in s["file"]
            ],
            what="the snapshots",
        )
        # M791 at the end: its snapshot waits its turn, so the finished part is always taken.
        last_line = 3 * 103 + 1  # each layer: M790, G1 Z, G28 and 100 moves
        wait_for(
            lambda: any(
                f"job{job['id']}-line{last_line}" in s["file"]
                for s in client.get("/v1/printers/bench/snapshots").json()
            ),
            what="M791's snapshot",
        )
        assert any(f"job{job['id']}-layer1" in s["file"] for s in shots)
        image = client.get(shots[0]["url"])
        assert image.status_code == 200 and image.headers["content-type"] == "image/png"
        assert image.content == png()
        assert (
            client.get("/v1/printers/bench")
            .json()["snapshot"]
            .startswith("/v1/printers/bench/snapshots/")
        )
        taken = client.post("/v1/printers/bench/snapshots")
        assert taken.status_code == 201 and client.get(taken.json()["url"]).content == png()
        missing = client.get("/v1/printers/bench/snapshots/..%2Fjobs.sqlite")
        assert missing.status_code == 404
        # A printer without a camera says so; M790/M791 did not reach either controller.
        blind = client.post("/v1/printers/blind/snapshots")
        assert blind.status_code == 409 and "has no camera" in blind.json()["detail"]
        assert client.get("/v1/printers/blind").json()["camera"] is False
    fake.request("status")
    ran = executed(fake.log_path)
    assert "M790" not in ran and "M791" not in ran and len(ran) >= 306


def test_a_failing_camera_and_m792_actions_are_told_and_the_job_goes_on(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    marker = tmp_path / "shell-ran"
    fake = bench()
    config = camera_config(tmp_path, {"bench": fake.port}, bench=f"{CAMERA} --fail {{path}}")
    server = servers({}, "--config", str(config))
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        failed = client.post("/v1/printers/bench/snapshots")
        assert failed.status_code == 502
        assert failed.json()["detail"] == (
            "printer bench: the camera command failed (exit 3): /dev/video0: No such device"
        )
        with client.stream("GET", "/v1/events", params={"printer": "bench"}) as stream:
            text = f"G28\nM791\nM792 ; SHELL touch {marker} ; SAY hi\nG1 X1\n"
            job = client.post("/v1/printers/bench/jobs", files={"file": ("a.gcode", text)}).json()
            told: list[str] = []
            for line in stream.iter_lines():
                event = json.loads(line[6:]) if line.startswith("data: ") else {}
                if event.get("type") == "message" and event["text"].startswith(("no ", "a.")):
                    told.append(event["text"])
                if len(told) == 3:
                    break
        assert sorted(told) == [
            "a.gcode:3: SAY hi (not done on the server)",
            f"a.gcode:3: SHELL touch {marker} (the server runs no programs)",
            "no snapshot: the camera command failed (exit 3): /dev/video0: No such device",
        ]
        wait_for(lambda: job_state(client, job["id"])["state"] == "completed")
        assert client.get("/v1/printers/bench/snapshots").json() == []
    assert not marker.exists()
    fake.request("status")  # the log is complete
    assert executed(fake.log_path)[-2:] == ["G28", "G1 X1"]


def test_a_bad_camera_setting_gets_one_sentence(tmp_path: Path) -> None:
    config = camera_config(tmp_path, {"demo": "fake"}, demo='fswebcam "unclosed')
    result = run_server_cli(
        "--config", str(config), "--data-dir", str(tmp_path / "data"), timeout=30
    )
    assert result.returncode == 2
    assert result.stderr == (
        f"hyrel-server: {config}: printers.demo.camera: Value error, the camera command "
        "cannot be split into words (No closing quotation)\n"
    )


# --- Hyrel's link and its job report -----------------------------------------------------


OLD_SCHEMA = """
CREATE TABLE jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT, printer TEXT NOT NULL, name TEXT NOT NULL,
    file TEXT NOT NULL, state TEXT NOT NULL, position REAL NOT NULL, submitted REAL NOT NULL,
    started REAL, ended REAL, lines INTEGER NOT NULL DEFAULT 0,
    last_line INTEGER NOT NULL DEFAULT 0, total_lines INTEGER NOT NULL DEFAULT 0, error TEXT
);
INSERT INTO jobs (printer, name, file, state, position, submitted, started, ended, lines)
VALUES ('hyrel', 'old.gcode', 'files/old.gcode', 'completed', 1, 1.0, 2.0, 3.0, 2);
"""


@pytest.mark.slow
def test_a_hyrel_link_printer_prints_and_keeps_the_m773_report_with_the_job(
    servers: Callable[..., Server], tmp_path: Path
) -> None:
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    with contextlib.closing(sqlite3.connect(data_dir / "jobs.sqlite")) as old:
        old.executescript(OLD_SCHEMA)
    config = server_config(
        tmp_path,
        hyrel={"port": "fake", "protocol": "hyrel", "report": True},
        plain={"port": "fake", "protocol": "hyrel"},
    )
    server = servers({}, "--config", str(config))
    text = "G28\nG90\nM83\nG1 X10 Y0 F3000\nG1 X20 Y10 E1.5\nM30\n"
    with server.client() as client:
        assert job_state(client, 1)["report"] is None  # from before: still there
        jobs = {
            name: client.post(
                f"/v1/printers/{name}/jobs", files={"file": (f"{name}.gcode", text)}
            ).json()["id"]
            for name in ("hyrel", "plain")
        }
        wait_for(
            lambda: all(job_state(client, j)["state"] == "completed" for j in jobs.values()),
            what="the jobs",
        )
        report = job_state(client, jobs["hyrel"])["report"]
        assert report["complete"] is True and "Begin M773" in report["text"]
        assert len(report["fields"]["Totals"]) == 2 and "End M773" in report["text"]
        listed = {j["id"]: j for j in client.get("/v1/printers/hyrel/jobs").json()}
        assert listed[jobs["hyrel"]]["report"] == report and listed[1]["report"] is None
        assert job_state(client, jobs["plain"])["report"] is None  # not asked for
        assert client.get("/v1/printers/plain").json()["protocol"] == "hyrel"
    assert server.stop() == 0
    kept = list((data_dir / "history").glob(f"{jobs['hyrel']}-hyrel-report.txt"))
    assert len(kept) == 1 and "Begin M773" in kept[0].read_text()


def test_a_protocol_defaults_the_window_that_rx_buffer_and_max_lines_do_not_give(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import repetrel_host as rh
    from repetrel_host.config import UserConfig
    from repetrel_host.server.printers.config import PrinterConfig
    from repetrel_host.session.planning import DEFAULT_WINDOWS

    asked: dict[str, Any] = {}
    monkeypatch.setattr(rh, "connect", lambda port, **given: asked.update(given))
    PrinterConfig("fake", protocol="hyrel", max_lines=64).connect(UserConfig())
    hyrel = DEFAULT_WINDOWS["hyrel"]
    assert asked["protocol"] == "hyrel"
    assert asked["flow"] == rh.FlowControl(hyrel.mode, rx_buffer=hyrel.rx_buffer, max_lines=64)
    PrinterConfig("fake", rx_buffer=96).connect(UserConfig())
    assert asked["protocol"] is None and asked["flow"].rx_buffer == 96
    assert asked["flow"].max_lines == DEFAULT_WINDOWS["reprap"].max_lines


def test_a_bad_protocol_gets_one_sentence(tmp_path: Path) -> None:
    config = server_config(tmp_path, demo={"port": "fake", "protocol": "marlin"})
    result = run_server_cli(
        "--config", str(config), "--data-dir", str(tmp_path / "data"), timeout=30
    )
    assert result.returncode == 2
    assert result.stderr == (
        f"hyrel-server: {config}: printers.demo.protocol: Input should be 'reprap' or 'hyrel'\n"
    )


# --- security ----------------------------------------------------------------------------


def test_requests_without_the_key_are_refused_and_bad_uploads_too(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    data_dir = server.data_dir
    upload = {"file": ("a.gcode", b"G28\n")}
    with server.client(key=None) as anonymous, server.client("wrong") as wrong:
        for client in (anonymous, wrong):
            answer = client.post("/api/files/local", files=upload)
            assert answer.status_code == 403 and "API key" in answer.json()["detail"]
            assert (
                client.post("/v1/printers/demo/command", json={"command": "M105"}).status_code
                == 403
            )
            # Reads too, as on OctoPrint: it is how a slicer's "Test" tells a wrong key.
            for path in ("/api/version", "/api/job", "/v1/printers", "/v1/files", "/v1/events"):
                assert client.get(path).status_code == 403, path
    with server.client() as client:
        escape = client.post("/api/files/local", data={"path": "../.."}, files=upload)
        assert escape.status_code == 400 and "leaves the upload folder" in escape.json()["detail"]
        named = client.post("/api/files/local", files={"file": ("../../evil.gcode", b"G28\n")})
        assert named.status_code == 201
        assert named.json()["files"]["local"]["path"] == "evil.gcode"
        assert (data_dir / "files" / "evil.gcode").exists()
        assert not (data_dir.parent / "evil.gcode").exists()
        not_gcode = client.post("/api/files/local", files={"file": ("run.sh", b"rm -rf /\n")})
        assert not_gcode.status_code == 400 and "not a G-code file" in not_gcode.json()["detail"]
        long_line = "G1 X1 " + "Y1 " * 40 + "\n"
        refused = client.post(
            "/api/files/local", files={"file": ("long.gcode", long_line.encode())}
        )
        assert refused.status_code == 400
        assert refused.json()["detail"]["error"] == "long.gcode: refused (1 errors)"
        assert not (data_dir / "files" / "long.gcode").exists()
        bad_json = client.post("/api/job", json={"nothing": 1})
        assert bad_json.status_code == 400 and bad_json.json()["detail"].startswith("bad request")


def test_bodies_are_refused_before_they_are_read(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake"}, "--max-upload-mb", "1")

    def body() -> Iterator[bytes]:
        yield b'--x\r\nContent-Disposition: form-data; name="file"; filename="big.gcode"\r\n\r\n'
        for _ in range(16):  # 16 MB, chunked: no Content-Length to look at
            yield b"G1 X1\n" * 174_763

    headers = {"Content-Type": "multipart/form-data; boundary=x"}
    with server.client(key=None) as anonymous:
        answer = anonymous.post("/api/files/local", content=body(), headers=headers)
        assert answer.status_code == 403
    with server.client() as client:
        answer = client.post("/api/files/local", content=body(), headers=headers)
        assert answer.status_code == 413 and "over 1048576 bytes" in answer.json()["detail"]
    assert not list((server.data_dir / "files").iterdir())


@pytest.mark.slow
def test_a_second_server_on_the_same_data_folder_is_refused(
    servers: Callable[..., Server],
) -> None:
    first = servers({"demo": "fake"})
    second = run_server_cli(
        *("--data-dir", str(first.data_dir), "--printer", "demo=fake"),
        *("--bind", f"127.0.0.1:{free_port()}"),
        timeout=30,
    )
    assert second.returncode == 2
    assert f"another hyrel-server uses the data folder {first.data_dir}" in second.stderr
    # On the first one's port too: the folder is what it says, not the port it holds.
    again = run_server_cli(
        *("--data-dir", str(first.data_dir), "--printer", "demo=fake"),
        *("--bind", f"127.0.0.1:{first.port}"),
        timeout=30,
    )
    assert again.returncode == 2
    said = f"hyrel-server: another hyrel-server uses the data folder {first.data_dir}\n"
    assert again.stderr == said


def test_a_first_start_on_a_port_in_use_writes_nothing(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        data = tmp_path / "data"
        result = run_server_cli(
            *("--data-dir", str(data), "--printer", "demo=fake", "--bind", f"127.0.0.1:{port}"),
            timeout=30,
        )
    assert result.returncode == 2
    assert result.stderr == (
        f"hyrel-server: cannot listen on 127.0.0.1:{port} (--bind): Address already in use\n"
    )
    assert not data.exists()  # no folder, no database, no key


@pytest.mark.slow
def test_a_new_server_makes_a_key_kept_private_and_an_upload_limit(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"}, "--max-upload-mb", "1", key=False)
    key_file = server.data_dir / "api-key"
    key = key_file.read_text().strip()
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
    assert f"a new API key (kept in {key_file}): {key}" in server.stderr.read_text()
    with server.client(key) as client:
        big = b"G1 X1\n" * 200_000  # 1.2 MB
        answer = client.post("/api/files/local", files={"file": ("big.gcode", big)})
        assert answer.status_code == 413 and "over 1048576 bytes" in answer.json()["detail"]
        # Held, the queue keeps its jobs; released, they run.
        wait_for(lambda: client.get("/v1/printers/demo").json()["state"] == "ready")
        assert client.post("/v1/printers/demo/hold").status_code == 204
        job_id = client.post("/v1/printers/demo/jobs", files={"file": ("h.gcode", gcode(3))})
        job_id = job_id.json()["id"]
        time.sleep(1.0)
        assert job_state(client, job_id)["state"] == "queued"
        assert client.get("/v1/printers/demo").json()["held"] is True
        assert client.post("/v1/printers/demo/release").status_code == 204
        wait_for(lambda: job_state(client, job_id)["state"] == "completed", what="the job")
        assert client.post("/v1/printers/demo/sideways").status_code == 404


@pytest.mark.slow
def test_bad_server_settings_get_one_sentence(tmp_path: Path) -> None:
    for args, message in (
        (["--data-dir", str(tmp_path)], "no printer: give --printer NAME=PORT"),
        (["--printer", "a=fake"], "give --data-dir DIR"),
        (["--data-dir", str(tmp_path), "--printer", "afake"], "--printer afake: give NAME=PORT"),
        (["--data-dir", str(tmp_path), "--printer", "a/b=fake"], "printer name 'a/b'"),
        (["--data-dir", str(tmp_path), "--printer", "a=fake", "--bind", "nowhere"], "HOST:PORT"),
        (
            ["--data-dir", str(tmp_path / "data"), "--printer", f"a={tmp_path}"],
            f"printer a: cannot open {tmp_path}: it is a folder, not a serial port",
        ),
    ):
        result = run_server_cli(*args, timeout=30)
        assert result.returncode == 2, result.stderr
        assert message in result.stderr and "Traceback" not in result.stderr
    config = tmp_path / "server.toml"
    config.write_text('data_dir = "x"\nmax_upload_mb = "lots"\n[printers]\na = "fake"\n')
    result = run_server_cli("--config", str(config), timeout=30)
    assert result.returncode == 2 and f"{config}: max_upload_mb:" in result.stderr


def test_the_contrib_settings_and_unit_fit_the_server() -> None:
    from repetrel_host.config import read_toml
    from repetrel_host.server.settings import ServerSettings

    contrib = ROOT / "contrib"
    settings = ServerSettings.model_validate(read_toml(contrib / "hyrel-server.toml"))
    assert "hydra" in settings.printers and settings.bind == "127.0.0.1:8765"
    unit = (contrib / "hyrel-server.service").read_text()
    assert "ExecStart=/opt/repetrel-host/bin/hyrel-server --config /etc/hyrel-server.toml" in unit


# --- MQTT ------------------------------------------------------------------------------


async def _mqtt_messages(
    port: int, topic: str, until: Callable[[list[tuple[str, Any]]], bool], timeout: float = 30
) -> list[tuple[str, Any]]:
    """(topic, payload) of what arrives on ``topic`` until ``until(messages)``."""
    messages: list[tuple[str, Any]] = []
    async with aiomqtt.Client("127.0.0.1", port) as client:
        await client.subscribe(topic, qos=1)
        async with asyncio.timeout(timeout):
            async for message in client.messages:
                payload = bytes(message.payload).decode()  # type: ignore[arg-type]
                with contextlib.suppress(ValueError):
                    payload = json.loads(payload)
                messages.append((str(message.topic), payload))
                if until(messages):
                    return messages
    return messages


@pytest.mark.slow
def test_mqtt_publishes_states_jobs_progress_retained_and_takes_commands(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], broker: int, tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.002")
    config = camera_config(tmp_path, {"bench": fake.port}, bench=CAMERA)
    mqtt = ["--mqtt", f"127.0.0.1:{broker}", "--mqtt-commands"]
    server = servers({}, "--config", str(config), *mqtt)
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")

    async def scenario() -> None:
        async def upload() -> None:
            await asyncio.sleep(0.5)  # subscribed by then
            async with httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as web:
                files = {"file": ("farm.gcode", gcode(400) + "M791\n")}
                assert (await web.post("/v1/printers/bench/jobs", files=files)).status_code == 201

        def completed(messages: list[tuple[str, Any]]) -> bool:
            return any(
                topic == "hyrel/bench/job" and payload["job"]["state"] == "completed"
                for topic, payload in messages
            ) and any(topic == "hyrel/bench/snapshot" for topic, _ in messages)

        uploading = asyncio.create_task(upload())
        seen = await _mqtt_messages(broker, "hyrel/#", completed)
        await uploading
        topics = {topic for topic, _ in seen}
        assert {"hyrel/server/online", "hyrel/bench/state", "hyrel/bench/progress"} <= topics
        progress = [p["lines"] for t, p in seen if t == "hyrel/bench/progress"]
        assert progress[-1] == 401
        states = [p["state"] for t, p in seen if t == "hyrel/bench/state"]
        assert "printing" in states

        # A dashboard that starts later sees how things stand (retained).
        wanted = {"hyrel/bench/state", "hyrel/bench/job", "hyrel/bench/snapshot"}
        late = await _mqtt_messages(
            broker, "hyrel/bench/+", lambda m: wanted <= {t for t, _ in m}, 10
        )
        retained = dict(late)
        assert retained["hyrel/bench/state"]["state"] == "ready"
        assert retained["hyrel/bench/snapshot"]["url"].startswith("/v1/printers/bench/snapshots/")
        assert retained["hyrel/bench/job"]["job"]["state"] == "completed"

        async with aiomqtt.Client("127.0.0.1", broker) as commander:
            await commander.subscribe("hyrel/bench/reply", qos=1)
            await commander.publish("hyrel/bench/command", b"M105", qos=1)
            async with asyncio.timeout(10):
                async for message in commander.messages:
                    if str(message.topic) == "hyrel/bench/reply":
                        reply = json.loads(bytes(message.payload))  # type: ignore[arg-type]
                        break
        assert reply["ok"] is True and reply["reply"].startswith("ok T:")

    asyncio.run(scenario())
    assert server.stop() == 0

    async def after_stop() -> None:
        online = await _mqtt_messages(broker, "hyrel/server/online", lambda m: True, 10)
        assert online == [("hyrel/server/online", False)]

    asyncio.run(after_stop())
