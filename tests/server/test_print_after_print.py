"""A print after a print, for real: a hyrel-server process with the fake controller on a
pty. After a job the queue is held (its part may be on the bed); a person's start of a file,
from any face's start, says the bed is clear: it releases the hold and prints, before the
jobs that waited behind the hold. With ``--start-waits-for-release`` (a farm's) every start
waits for a release, refused with why, and nothing runs. Each face says the hold in its
client's own terms; a start after an interrupted job still sends the owed safe stop first."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import MARLIN_SAFE_STOP, executed
from tests.support.server import Server, commands_of, gcode, job_state, wait_for

pytestmark = pytest.mark.timeout(90)

FARM = "--start-waits-for-release"
FIRST = gcode(5, start=10)  # G1 X10.. X14: each file's lines are its own
SECOND = gcode(5, start=50)
BEHIND = gcode(5, start=90)


def upload(http: httpx.Client, name: str, text: str) -> None:
    """``name`` stored (Moonraker's upload, no print)."""
    stored = http.post("/server/files/upload", files={"file": (name, text)})
    assert stored.status_code == 201, stored.text


# Each face's start of a stored file: the answer as the face gives it.
def moonraker_start(http: httpx.Client, name: str) -> httpx.Response:
    return http.post("/printer/print/start", json={"filename": name})


def moonraker_sdcard(http: httpx.Client, name: str) -> httpx.Response:
    return http.post("/printer/gcode/script", json={"script": f"SDCARD_PRINT_FILE FILENAME={name}"})


def moonraker_upload(http: httpx.Client, name: str) -> httpx.Response:
    text = {"a.gcode": FIRST, "b.gcode": SECOND}[name]
    return http.post("/server/files/upload", data={"print": "true"}, files={"file": (name, text)})


def octoprint_upload(http: httpx.Client, name: str) -> httpx.Response:
    text = {"a.gcode": FIRST, "b.gcode": SECOND}[name]
    return http.post("/api/files/local", data={"print": "true"}, files={"file": (name, text)})


def octoprint_select(http: httpx.Client, name: str) -> httpx.Response:
    return http.post(f"/api/files/local/{name}", json={"command": "select", "print": True})


def octoprint_job_start(http: httpx.Client, name: str) -> httpx.Response:
    selected = http.post(f"/api/files/local/{name}", json={"command": "select"})
    assert selected.status_code == 204, selected.text
    return http.post("/api/job", json={"command": "start"})


STARTS: dict[str, Callable[[httpx.Client, str], httpx.Response]] = {
    "printer.print.start": moonraker_start,
    "SDCARD_PRINT_FILE": moonraker_sdcard,
    "moonraker upload print=true": moonraker_upload,
    "octoprint upload print": octoprint_upload,
    "octoprint select print": octoprint_select,
    "octoprint job start": octoprint_job_start,
}


def jobs(http: httpx.Client) -> list[dict[str, Any]]:
    listed: list[dict[str, Any]] = http.get("/v1/printers/bench/jobs").json()
    return sorted(listed, key=lambda j: j["id"])


def print_stats(http: httpx.Client) -> dict[str, Any]:
    query = http.get("/printer/objects/query", params={"print_stats": "state,message"})
    found: dict[str, Any] = query.json()["result"]["status"]["print_stats"]
    return found


def octoprint_state(http: httpx.Client) -> dict[str, Any]:
    state: dict[str, Any] = http.get("/api/printer").json()["state"]
    return state


def first_job_held(http: httpx.Client, server: Server, start: str) -> None:
    """The first file printed by ``start`` (nothing held yet) and ended: its part is on the
    bed, the queue held; the second file is stored and a third job waits behind the hold."""
    server.wait_ready("bench")
    if "upload" not in start:  # else the upload that starts stores it
        upload(http, "a.gcode", FIRST)
        upload(http, "b.gcode", SECOND)
    started = STARTS[start](http, "a.gcode")
    assert started.status_code in (200, 201, 204), started.text
    wait_for(lambda: [j["state"] for j in jobs(http)] == ["completed"], what="the first job")
    assert http.get("/v1/printers/bench").json()["held"] is True
    behind = http.post("/v1/printers/bench/jobs", files={"file": ("c.gcode", BEHIND)})
    assert behind.status_code == 201, behind.text


@pytest.mark.parametrize("start", list(STARTS))
@pytest.mark.slow
def test_a_start_after_a_print_releases_the_hold_and_goes_first(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], start: str
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    with server.client() as http:
        first_job_held(http, server, start)
        # Each client sees why nothing starts by itself, and that a start is welcome.
        note = print_stats(http)
        assert note["state"] == "complete"
        assert note["message"] == (
            "Queue held (job 1 completed: its part may still be on the bed): clear the bed, "
            "then start a print"
        )
        queue = http.get("/server/job_queue/status").json()["result"]
        assert queue["queue_state"] == "paused"
        state = octoprint_state(http)
        assert state["text"] == "Operational (bed not cleared)"
        assert state["flags"]["ready"] is True and state["flags"]["operational"] is True
        assert state["flags"]["held"] is True

        answer = STARTS[start](http, "b.gcode")
        assert answer.status_code in (200, 201, 204), answer.text
        wait_for(
            lambda: [j["state"] for j in jobs(http)] == ["completed", "queued", "completed"],
            what="the second file printed, the job behind the hold still waiting",
        )
        # Held again by the second job's part: the job that waited behind waits on.
        assert http.get("/v1/printers/bench").json()["held"] is True
        assert print_stats(http)["message"].startswith("Queue held (job 3 completed")
        time.sleep(0.5)
        assert job_state(http, 2)["state"] == "queued"
    fake.request("status")  # the log is complete
    ran = executed(fake.log_path)
    assert ran[-len(commands_of(SECOND)) :] == commands_of(SECOND)
    assert "G1 X90 F3000" not in ran  # the job behind the hold did not run
    said = server.stderr.read_text()
    assert "the queue's hold (job 1 completed: its part may still be on the bed) released" in said


MOONRAKER_REFUSAL = (
    "printer bench's queue is held (job 1 completed: its part may still be on the bed): "
    "release it once nothing is still on the bed (start_waits_for_release: a start does not "
    "release it)"
)


@pytest.mark.parametrize("start", list(STARTS))
@pytest.mark.slow
def test_where_every_start_waits_for_a_release_a_start_is_refused_with_why(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], start: str
) -> None:
    fake = bench()
    server = servers({"bench": fake.port}, FARM)
    with server.client() as http:
        first_job_held(http, server, start)
        assert print_stats(http)["message"] == (
            "Queue held (job 1 completed: its part may still be on the bed): clear the bed, "
            "then release the queue"
        )
        state = octoprint_state(http)
        assert state["text"] == "Operational (bed not cleared)"
        assert state["flags"]["ready"] is False and state["flags"]["operational"] is True
        fake.request("status")
        before = len(executed(fake.log_path))

        answer = STARTS[start](http, "b.gcode")
        if start.startswith("octoprint"):
            assert answer.status_code == 409, answer.text
            error = answer.json()["error"]
            if start == "octoprint upload print":  # kept, not printed
                assert error == f"b.gcode is stored, not printed: {MOONRAKER_REFUSAL}"
            else:
                assert error == MOONRAKER_REFUSAL
        else:
            assert answer.status_code == 400, answer.text
            assert answer.json()["error"]["message"] == MOONRAKER_REFUSAL
        time.sleep(1.0)
        assert [j["name"] for j in jobs(http)] == ["a.gcode", "c.gcode"]
        assert http.get("/v1/printers/bench").json()["held"] is True
        fake.request("status")
        assert len(executed(fake.log_path)) == before  # nothing ran
    assert "released by" not in server.stderr.read_text()


@pytest.mark.slow
def test_a_start_after_an_interrupted_job_sends_the_owed_safe_stop_first(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.004")
    server = servers({"bench": fake.port})
    with server.client() as http:
        upload(http, "b.gcode", SECOND)
        job = http.post("/v1/printers/bench/jobs", files={"file": ("long.gcode", gcode(3000))})
        assert job.status_code == 201, job.text
        wait_for(lambda: job_state(http, 1)["lines"] > 200, what="progress on record")
    server.stop(signal.SIGKILL)
    fake.request("status")
    before = len(executed(fake.log_path))

    restarted = servers({"bench": fake.port})
    with restarted.client() as http:
        # Started at once, the printer maybe not greeted yet: held, and the stop owed.
        answer = moonraker_start(http, "b.gcode")
        assert answer.status_code == 200, answer.text
        wait_for(lambda: job_state(http, 2)["state"] == "completed", what="the started file")
        assert job_state(http, 1)["state"] == "interrupted"
    fake.request("status")
    after = executed(fake.log_path)[before:]
    # The owed safe stop went first (at the greeting), then the file, whole.
    stop = next(i for i in range(len(after)) if after[i : i + 7] == MARLIN_SAFE_STOP)
    assert after[stop + len(MARLIN_SAFE_STOP) :] == commands_of(SECOND), after
    assert "(job 1 was interrupted: its part may be on the bed) released" in (
        restarted.stderr.read_text()
    )


@pytest.mark.slow
def test_a_start_while_the_queue_is_held_on_request_prints_and_the_queue_stays_held(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """A hold someone asked for (Moonraker's ``server.job_queue.pause``) is the queue's,
    not the bed's: a start prints its file, as Moonraker's does whatever its queue, and the
    queued job still waits for the release, even where jobs follow one another by
    themselves (``--automatic-transition``)."""
    fake = bench()
    server = servers({"bench": fake.port}, "--automatic-transition")
    with server.client() as http:
        server.wait_ready("bench")
        assert http.post("/server/job_queue/pause").status_code == 200
        behind = http.post("/v1/printers/bench/jobs", files={"file": ("c.gcode", BEHIND)})
        assert behind.status_code == 201, behind.text
        assert print_stats(http)["message"] == (
            "Queue held (held on request): release the queue to run the queued jobs"
        )
        upload(http, "a.gcode", FIRST)
        assert moonraker_start(http, "a.gcode").status_code == 200
        wait_for(
            lambda: [j["state"] for j in jobs(http)] == ["queued", "completed"],
            what="the file started printed, the queued job still waiting",
        )
        time.sleep(1.5)  # the queue's loop looks again each second
        assert job_state(http, 1)["state"] == "queued"
        assert http.get("/v1/printers/bench").json()["hold_reason"] == "held on request"
        assert http.get("/server/job_queue/status").json()["result"]["queue_state"] == "paused"
    fake.request("status")
    ran = executed(fake.log_path)
    assert ran[-len(commands_of(FIRST)) :] == commands_of(FIRST)
    assert "G1 X90 F3000" not in ran
