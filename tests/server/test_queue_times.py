"""A printer's queue in time, for real (a hyrel-server process, HTTP over loopback, the fake
controller on a pty): each queued job's estimate (its file's planned time at the printer's
learned pace), when it should start and end, and when the printer should be free."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from datetime import datetime
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import Server, gcode, past_paces, wait_for


def at(iso: str) -> float:
    """An ISO time of the API, in seconds since the epoch."""
    return datetime.fromisoformat(iso).timestamp()


def queued(client: httpx.Client) -> list[dict[str, Any]]:
    jobs: list[dict[str, Any]] = client.get("/v1/printers/bench/jobs").json()
    return [job for job in jobs if job["state"] == "queued"]


def planned(client: httpx.Client, path: str) -> float:
    """The file's print time from its moves, once the server worked it out."""

    def found() -> float | None:
        for entry in client.get("/v1/files").json():
            if entry["path"] == path and entry["analysis"]:
                seconds: float | None = entry["analysis"]["estimatedPrintTime"]
                return seconds
        return None

    seconds: float = wait_for(found, what=f"the print time of {path}")
    return seconds


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_queued_jobs_follow_the_running_one_and_the_printer_is_free_after_the_last(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.004")  # the running job: some 80 s
    server = servers({"bench": fake.port})
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        long = client.post("/v1/printers/bench/jobs", files={"file": ("long.gcode", gcode(20000))})
        first = client.post("/v1/printers/bench/jobs", files={"file": ("a.gcode", gcode(1000))})
        second = client.post("/v1/printers/bench/jobs", files={"file": ("b.gcode", gcode(2000))})
        assert long.status_code == first.status_code == second.status_code == 201

        def timed() -> list[dict[str, Any]] | None:
            jobs = queued(client)
            return jobs if all(job["estimated_end"] for job in jobs) else None

        a, b = wait_for(timed, what="both queued jobs' ends")
        assert [a["id"], b["id"]] == [first.json()["id"], second.json()["id"]]
        # Each takes its file's planned time (no past job: the pace is the plan's).
        assert abs(a["estimated_time"] - planned(client, "a.gcode")) <= 1
        assert abs(b["estimated_time"] - planned(client, "b.gcode")) <= 1
        assert b["estimated_time"] > a["estimated_time"] > 0
        assert not a["estimated_time_whole_file"] and not b["estimated_time_whole_file"]
        # In queue order: the first when the running job ends, the second after the first.
        assert b["estimated_start"] == a["estimated_end"]
        assert at(a["estimated_end"]) - at(a["estimated_start"]) == pytest.approx(
            a["estimated_time"], abs=1
        )
        assert at(b["estimated_end"]) - at(b["estimated_start"]) == pytest.approx(
            b["estimated_time"], abs=1
        )
        printer = client.get("/v1/printers/bench").json()
        assert at(printer["job"]["ends"]) == pytest.approx(at(a["estimated_start"]), abs=10)
        assert at(printer["free_at"]) == pytest.approx(at(b["estimated_end"]), abs=10)
        assert at(printer["free_at"]) > time.time() + a["estimated_time"] + b["estimated_time"]

        # The queue held: nothing says when the queued jobs start, nor when the printer
        # is free; how long each takes is still known.
        assert client.post("/v1/printers/bench/hold").status_code == 204
        for job in queued(client):
            assert job["estimated_time"] > 0
            assert job["estimated_start"] is None and job["estimated_end"] is None
        assert client.get("/v1/printers/bench").json()["free_at"] is None
        assert client.delete(f"/v1/jobs/{long.json()['id']}").status_code in (200, 202)


@pytest.mark.timeout(120)
def test_the_printers_learned_pace_scales_the_estimate_and_a_recovery_takes_the_rest(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        assert client.post("/v1/printers/bench/hold").status_code == 204  # nothing starts
        job = client.post("/v1/printers/bench/jobs", files={"file": ("part.gcode", gcode(2000))})
        assert job.status_code == 201
        whole = planned(client, "part.gcode")
        assert whole > 10

        def estimate() -> dict[str, Any] | None:
            jobs = queued(client)
            return jobs[0] if jobs and jobs[0]["estimated_time"] is not None else None

        first = wait_for(estimate, what="the estimate")
        assert first["estimated_time"] == pytest.approx(whole, abs=1)
        assert first["estimated_start"] is None  # held

        # The printer's past jobs took twice their plans (their median: one odd job does
        # not sway it).
        past_paces(server, 2.0, 2.0, 5.0)
        assert queued(client)[0]["estimated_time"] == pytest.approx(2 * whole, abs=1)

        # From line 1001 of 2001: the planned time after line 1000, at the same pace.
        again = client.post(
            "/v1/printers/bench/queue", json={"file": "part.gcode", "from_line": 1001}
        )
        assert again.status_code == 201, again.text
        recovered = queued(client)[1]
        assert recovered["id"] == again.json()["id"]
        assert not recovered["estimated_time_whole_file"]
        assert recovered["estimated_time"] == pytest.approx(whole, rel=0.1)  # half, twice


@pytest.mark.timeout(60)
def test_a_queued_jobs_file_planned_in_the_background_tells_its_printer_so_a_page_lists_it(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"bench": bench().port})
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
        assert client.post("/v1/printers/bench/hold").status_code == 204  # nothing starts
        with client.stream("GET", "/v1/events", params={"printer": "bench"}) as stream:
            lines = stream.iter_lines()
            job = client.post("/v1/printers/bench/jobs", files={"file": ("a.gcode", gcode(3000))})
            job_id = job.json()["id"]
            # The first listing starts its planning; it has no estimate yet.
            assert queued(client)[0]["estimated_time"] is None
            told = 0
            for line in lines:
                if line.startswith("data: "):
                    event = json.loads(line[len("data: ") :])
                    if event["type"] == "job" and event["job"]["id"] == job_id:
                        told += 1
                        if told == 2:  # queued, then planned
                            break
        assert event["job"]["state"] == "queued"
        assert queued(client)[0]["estimated_time"] > 0
