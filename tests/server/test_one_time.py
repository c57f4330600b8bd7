"""One print time on every face, for real (a hyrel-server process, HTTP over loopback, the
fake controller on a pty): a file's whole time at the printer's learned pace is the same in
the native list, OctoPrint's, Moonraker's metadata and the queue; a running job has a time
left from its first look on, and its whole time is one figure on /v1 and OctoPrint's face."""

from __future__ import annotations

import contextlib
import json
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import Server, past_paces, wait_for

CONE = Path(__file__).parent.parent / "data" / "cone-prusaslicer.gcode"
pytestmark = pytest.mark.timeout(180)


def analysis(client: httpx.Client, path: str) -> dict[str, Any]:
    """The file's analysis on /v1, once its print time is planned."""

    def found() -> dict[str, Any] | None:
        for entry in client.get("/v1/files").json():
            planned: dict[str, Any] | None = entry["analysis"]
            if entry["path"] == path and planned and planned["estimatedPrintTime"] is not None:
                return planned
        return None

    result: dict[str, Any] = wait_for(found, what=f"the print time of {path}")
    return result


@pytest.mark.slow
def test_a_files_whole_time_is_one_figure_at_the_printers_pace_on_every_face(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    server = servers({"bench": bench().port})
    server.wait_ready("bench")
    with server.client() as client:
        upload = {"file": ("cone.gcode", CONE.read_bytes())}
        assert client.post("/v1/files", files=upload).is_success
        plan = analysis(client, "cone.gcode")
        # The plan split: its parts add up to the whole (as planned: pace 1, no history).
        parts = plan["estimatedMoving"] + plan["estimatedHeating"] + plan["estimatedToolChanges"]
        assert plan["estimatedPrintTime"] == pytest.approx(parts)
        assert plan["estimatedHeating"] > 0  # the cone heats its hotend first (M109)
        assert plan["estimatedPace"] == 1

        past_paces(server, 0.5, 0.5, 3.0)  # the median: one odd job does not sway it
        paced = analysis(client, "cone.gcode")
        whole = paced["estimatedMoving"] * 0.5 + paced["estimatedHeating"]
        assert paced["estimatedPace"] == 0.5
        assert paced["estimatedPrintTime"] == pytest.approx(whole)  # heat waits as planned

        octoprint = client.get("/api/files/local/cone.gcode").json()["gcodeAnalysis"]
        assert octoprint["estimatedPrintTime"] == pytest.approx(whole)
        metadata = client.get("/server/files/metadata", params={"filename": "cone.gcode"})
        assert metadata.json()["result"]["estimated_time"] == pytest.approx(whole, abs=0.1)
        assert client.post("/v1/printers/bench/hold").status_code == 204
        queued = client.post("/v1/printers/bench/queue", json={"file": "cone.gcode"}).json()

        def estimate() -> float | None:
            for job in client.get("/v1/printers/bench/jobs").json():
                if job["id"] == queued["id"] and job["estimated_time"] is not None:
                    seconds: float = job["estimated_time"]
                    return seconds
            return None

        assert wait_for(estimate, what="the queued job's estimate") == pytest.approx(whole, abs=1)


@pytest.mark.slow
def test_a_running_job_has_its_time_left_from_the_first_look_and_one_whole_time(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--time-scale", "20")  # the cone's 14 planned minutes in some 45 s
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    with server.client() as client:
        upload = {"file": ("cone.gcode", CONE.read_bytes())}
        assert client.post("/v1/files", files=upload).is_success
        analysis(client, "cone.gcode")  # analysed at its upload, as a sent file is
        past_paces(server, 0.05, 0.05)  # the printer runs at 1/20 of the plan, and knows it
        job = client.post("/v1/printers/bench/queue", json={"file": "cone.gcode"}).json()
        seen: list[tuple[float, float | None, str | None]] = []
        started = time.monotonic()
        while time.monotonic() - started < 8:
            running = client.get("/v1/printers/bench").json()["job"]
            if running is not None and running["id"] == job["id"]:
                seen.append((running["lines"], running["time_left"], running["time_left_from"]))
                progress = client.get("/api/job").json()
                after = client.get("/v1/printers/bench").json()["job"] or running
                # The same figure, a moment apart (the job's own plan may land between).
                wholes = (running["estimated_time"], after["estimated_time"])
                octoprint = progress["job"]["estimatedPrintTime"]
                assert any(octoprint == pytest.approx(w, rel=0.05) for w in wholes), wholes
                assert progress["progress"]["printTimeLeft"] is not None
            time.sleep(0.1)
        client.delete(f"/v1/jobs/{job['id']}")
    assert seen, "the job never showed as running"
    # From the first look, in the heat-up too: a time left, the plan's at the learned pace
    # (never the rate's, which the heat-up sends sky-high).
    assert all(left is not None and how == "estimate" for _, left, how in seen), seen[:5]
    first = seen[0][1]
    assert first is not None and first < 14 * 60 * 0.2  # the learned pace's, not the plan's


@pytest.mark.slow
def test_a_jobs_heaters_climbs_are_kept_with_it_for_the_printers_next_jobs(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--heat-rate", "20")  # ten times the plan's 2 degrees a second
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    moves = "".join(f"G1 X{i % 50} Y{i % 40} F3000\n" for i in range(200))
    with server.client() as client:
        upload = {"file": ("hot.gcode", "M104 S210\nM109 S210\n" + moves)}
        job = client.post("/v1/printers/bench/jobs", files=upload).json()

        def ended() -> dict[str, Any] | None:
            found: dict[str, Any] = client.get(f"/v1/jobs/{job['id']}").json()
            return found if found["state"] == "completed" else None

        record = wait_for(ended, timeout=60, what="the job's end")
    # Timed from the reports a second or two apart: far above the plan's 2 a second.
    assert record["heat_rates"] is not None and record["heat_rates"]["hotend"] > 5
    with contextlib.closing(sqlite3.connect(server.data_dir / "jobs.sqlite")) as db:
        (kept,) = db.execute("SELECT heat_rates FROM jobs WHERE id = ?", (job["id"],)).fetchone()
    assert json.loads(kept) == record["heat_rates"]  # kept for the next job's plan


@pytest.mark.slow
def test_an_upload_printed_at_once_is_planned_at_once(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """Its file's plan is not there yet (an upload's analysis plans later): the job's own is
    made at once, not after the 3 s a job with its file's plan waits."""
    fake = bench("--time-scale", "20")
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    # Its first 4,000 lines: planned in a moment even on a busy machine, well inside the 3 s.
    head = CONE.read_text().splitlines(True)[:4000]
    no_slicer = "".join(line for line in head if ";" not in line)
    with server.client() as client:
        upload = {"file": ("plain.gcode", no_slicer)}
        assert client.post("/v1/printers/bench/jobs", files=upload).status_code == 201

        def running() -> dict[str, Any] | None:
            found: dict[str, Any] | None = client.get("/v1/printers/bench").json()["job"]
            return found

        wait_for(running, what="the job")
        seen = time.monotonic()
        known = wait_for(lambda: (job := running()) and job["time_left"] is not None and job)
        assert time.monotonic() - seen < 2.5, "planned only after the 3 s wait"
        assert known["time_left_from"] == "estimate" or known["time_left_from"] == "plan"
        client.delete(f"/v1/jobs/{known['id']}")
