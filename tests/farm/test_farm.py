"""A farm for real: hyrel-server processes sharing one queue in a real PostgreSQL, each
with fake controllers on ptys whose executed logs tell which printer ran what."""

from __future__ import annotations

import contextlib
import json
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.support.farm import (
    LEASE,
    Farm,
    loadout,
    part,
    start_node,
    where_ran,
)
from tests.support.helpers import hyrel_send, run_server_cli
from tests.support.pg import needs_postgres
from tests.support.server import KEY, Server

pytestmark = [pytest.mark.timeout(180), needs_postgres]


def test_jobs_go_to_the_printers_that_match_their_needs_each_exactly_once(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    abs_ = loadout(tmp_path, "abs", (1, "MK1-250", "ABS"))
    start_node(farm, "alpha", {"p1": {"loadout": pla}})
    start_node(farm, "beta", {"a1": {"loadout": abs_, "tags": ["enclosed"]}})
    ids = {}
    for number, material in ((101, "PLA"), (102, "ABS"), (103, "PLA"), (104, "ABS")):
        name, material = f"part{number}.gcode", f"material={material}"
        answer = farm.submit("alpha", part(str(number)), name, material)
        assert answer.status_code == 201, answer.text
        ids[number] = answer.json()["jobs"][0]
    farm.wait(
        lambda: all(farm.jobs()[i]["state"] == "completed" for i in ids.values()),
        what="every job to complete",
    )
    assert where_ran(farm, "101") == [("alpha", "p1")]
    assert where_ran(farm, "103") == [("alpha", "p1")]
    assert where_ran(farm, "102") == [("beta", "a1")]
    assert where_ran(farm, "104") == [("beta", "a1")]
    jobs = farm.jobs()
    for number, job_id in ids.items():
        job = jobs[job_id]
        expected = ("alpha", "p1") if number in (101, 103) else ("beta", "a1")
        assert (job["node_name"], job["printer"]) == expected
        assert job["lines"] == 32 and job["last_line"] == 32
        # Exactly once: the job's 30 moves, each once, on that printer's fake.
        node, printer = expected
        moves = [line for line in farm.nodes[node].ran(printer) if f" Y{number} " in line]
        assert len(moves) == 30
    view = farm.view("beta")
    printers = {p["name"]: p for p in view["printers"]}
    assert printers["a1"]["capabilities"]["materials"] == ["ABS"]
    assert printers["a1"]["capabilities"]["tags"] == ["enclosed"]
    assert printers["p1"]["url"].endswith("/printers/p1")


def test_a_job_no_printer_can_print_is_refused_saying_what_is_missing(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    start_node(farm, "alpha", {"p1": {"loadout": pla}})
    answer = farm.submit("alpha", part("201"), "part.gcode", "material=PETG")
    assert answer.status_code == 400
    error = answer.json()["error"]
    assert "no printer of the farm can print part.gcode" in error
    assert "p1 on alpha: no material PETG" in error
    # A tool the printer has no head on: the lint says so.
    answer = farm.submit("alpha", part("202", tool=3), "t3.gcode")
    assert answer.status_code == 400
    assert "T3 selects yoke 1, slot 4, which has no head loaded" in answer.json()["error"]
    answer = farm.submit("alpha", part("203"), "x.gcode", "colour=red")
    assert answer.status_code == 400
    assert "'colour' is not something a printer has" in answer.json()["error"]
    assert farm.jobs() == {}


def test_forty_jobs_through_three_nodes_each_once_on_a_printer_that_matches(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    abs_ = loadout(tmp_path, "abs", (1, "MK1-250", "ABS"))
    two = loadout(tmp_path, "two", (1, "MK1-250", "PLA"), (2, "SDS-05", "PETG"))
    start_node(farm, "a", {"a1": {"loadout": pla}, "a2": {"loadout": abs_, "tags": ["enclosed"]}})
    start_node(farm, "b", {"b1": {"loadout": pla, "tags": ["big"]}, "b2": {"loadout": two}})
    start_node(farm, "c", {"c1": {"loadout": abs_}, "c2": {"loadout": pla}})
    everyone = {"a1", "a2", "b1", "b2", "c1", "c2"}
    kinds: list[tuple[tuple[str, ...], set[str], int]] = [
        (("material=PLA",), {"a1", "b1", "b2", "c2"}, 0),
        (("material=ABS",), {"a2", "c1"}, 0),
        (("tag=big",), {"b1"}, 0),
        (("T1.material=PETG",), {"b2"}, 1),
        (("printer=c2",), {"c2"}, 0),
        (("material=abs", "tag=enclosed"), {"a2"}, 0),
        ((), everyone, 0),
    ]
    submitted: dict[int, tuple[str, set[str]]] = {}
    for number in range(40):
        requires, allowed, tool = kinds[number % len(kinds)]
        mark = str(1000 + number)
        answer = farm.submit("abc"[number % 3], part(mark, tool=tool), f"p{mark}.gcode", *requires)
        assert answer.status_code == 201, answer.text
        submitted[answer.json()["jobs"][0]] = (mark, allowed)
    farm.wait(
        lambda: (
            all(job["state"] == "completed" for job in farm.jobs().values())
            and len(farm.jobs()) == 40
        ),
        timeout=150,
        what="forty jobs to complete",
    )
    jobs = farm.jobs()
    for job_id, (mark, allowed) in submitted.items():
        job = jobs[job_id]
        ran = where_ran(farm, mark)
        assert ran == [(job["node_name"], job["printer"])], (job_id, ran)
        assert job["printer"] in allowed, (job_id, job["requires"], job["printer"])
        node, printer = ran[0]
        moves = [line for line in farm.nodes[node].ran(printer) if f" Y{mark} " in line]
        assert len(moves) == 30


def _printing(farm: Farm, job_id: int, lines: int = 50) -> bool:
    job = farm.jobs()[job_id]
    return bool(job["state"] == "printing" and job["lines"] > lines)


def test_a_node_killed_mid_job_leaves_it_interrupted_and_rejoins(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    start_node(farm, "a", {"a1": {"loadout": pla}}, fake_args=("--move-time", "0.004"))
    b = start_node(farm, "b", {"b1": {"loadout": pla}})
    source = tmp_path / "long.gcode"
    source.write_bytes(part("500", moves=3000, unique=True))
    # Followed from a terminal, through node b: told when a is lost, not "printing".
    follower = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", str(source), "--server", b.server.url,
         "--api-key", KEY, "--farm", "--require", "printer=a1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    long_job = 1  # the farm's first
    farm.wait(lambda: _printing(farm, long_job), what="the long job to stream on a1")
    farm.nodes["a"].server.stop(signal.SIGKILL)
    others = [
        farm.submit("b", part(str(600 + n)), f"o{n}.gcode").json()["jobs"][0] for n in range(3)
    ]
    # After a's lease, b ends it: the job is interrupted, never handed to b1.
    interrupted = farm.wait(
        lambda: (job := farm.jobs()[long_job])["state"] == "interrupted" and job,
        what="the long job to be interrupted",
    )
    assert "node a stopped answering" in interrupted["error"]
    assert interrupted["last_line"] > 50 and interrupted["expected_end"] is None
    try:
        followed, _ = follower.communicate(timeout=30)
    finally:
        follower.kill()
    assert follower.returncode == 4, followed  # a controller error's: it did not complete
    assert (
        "farm job 1 was interrupted: node a stopped answering (its lease ran out): the job "
        "was streaming there; the part may be on its bed"
    ) in followed
    assert "--farm --resume 1" in followed.splitlines()[-1]
    farm.wait(lambda: all(farm.jobs()[j]["state"] == "completed" for j in others))
    assert where_ran(farm, "500") == [("a", "a1")]
    for n in range(3):
        assert where_ran(farm, str(600 + n)) == [("b", "b1")]
    # Restarted, a rejoins: its own record (interrupted as the server died, through at
    # least the line it had recorded) is the farm's now; a1 holds its queue.
    node = start_node(farm, "a", {"a1": {"loadout": pla}})
    job = farm.wait(
        lambda: (j := farm.jobs()[long_job])["error"] != interrupted["error"] and j,
        what="a's own report of the job",
    )
    assert job["state"] == "interrupted" and "server ended" in job["error"]
    assert job["last_line"] >= interrupted["last_line"]
    assert job["resume_from_line"] == job["last_line"] + 1
    # Its owed safe stop went once a1 answered: the farm's record says so, as a's log does.
    job = farm.wait(lambda: (j := farm.jobs()[long_job])["safe_stop"] == "sent" and j)
    assert job["error"] == (
        "the server ended while the job was streaming (its safe stop went once the printer "
        "answered again)"
    )
    assert f"job {job['local_id']}'s safe stop went" in node.server.stderr.read_text()
    with node.client() as client:
        assert client.get("/v1/printers/a1").json()["held"] is True
        local = client.get(f"/v1/jobs/{job['local_id']}").json()
        assert local["farm_job"] == long_job and local["state"] == "interrupted"
    # Back once it answered and its owed safe stop went (before the session is ready).
    farm.wait(
        lambda: {p["name"]: p["state"] for p in farm.view()["printers"]}["a1"] != "offline",
        what="a1 back",
    )
    # Its resume command: the rest of the file, on a1 (its part is on that bed), once the
    # person who looked at it releases a1.
    line = job["last_line"] + 1
    # (farm.jobs() asks node a, the first running: its own URL is in the command)
    assert job["resume_command"] == (
        f"hyrel-send --server {node.server.url} --farm --resume {long_job}"
    )
    with node.client() as client:
        assert client.post("/v1/printers/a1/release").status_code == 204
    went_on = hyrel_send("--server", node.server.url, "--api-key", KEY, "--farm",
                         "--resume", str(long_job))  # fmt: skip
    assert went_on.returncode == 0, went_on.stdout + went_on.stderr
    assert f"farm job {long_job}: the rest, from line {line}, queued as farm job" in went_on.stdout
    assert "completed on a1 at node a" in went_on.stdout
    rest = max(farm.jobs())
    assert farm.jobs()[rest]["resumes"] == long_job and farm.jobs()[rest]["from_line"] == line
    # The rest's lines are what it printed of its own: all of them.
    assert farm.jobs()[rest]["lines"] == farm.jobs()[rest]["total_lines"] == 3003 - line
    # Resumed: not offered again, and refused in a sentence if asked.
    resumed = farm.jobs()[long_job]
    assert (resumed["state"], resumed["resumed_by"], resumed["resume_command"]) == (
        "resumed",
        rest,
        None,
    )
    again = hyrel_send("--server", node.server.url, "--api-key", KEY, "--farm",
                       "--resume", str(long_job))  # fmt: skip
    assert again.returncode != 0 and "Traceback" not in again.stderr
    assert (
        f"farm job {long_job} was resumed already, as farm job {rest}: that job prints its "
        "rest (resume that one if it did not complete) (HTTP 409)"
    ) in again.stderr
    moves = [entry for entry in node.ran("a1") if " Y500 " in entry]
    expected = [f"G1 X{i * 0.1:.1f} Y500 F6000" for i in range(line - 3, 3000)]
    assert moves[-len(expected) :] == expected


def test_postgresql_restarting_mid_run_stops_no_stream_and_claims_resume(
    farm: Farm, tmp_path: Path, postgres: Any
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    slow = ("--move-time", "0.008")  # a job of 600 moves streams for about 5 s
    start_node(farm, "a", {"a1": {"loadout": pla}}, slow)
    start_node(farm, "b", {"b1": {"loadout": pla}}, slow)
    first = [
        farm.submit("a", part(str(700 + n), moves=600), f"f{n}.gcode").json()["jobs"][0]
        for n in range(4)
    ]
    farm.wait(lambda: sum(_printing(farm, j, 20) for j in first) == 2, what="two streams")
    postgres.restart()
    second: list[int] = []
    for n in range(4):  # the nodes' connections come back by themselves
        answer = farm.wait(
            lambda n=n: (
                (a := farm.submit("b", part(str(710 + n)), f"s{n}.gcode")).status_code == 201 and a
            ),
            what="the database to take jobs again",
        )
        second.append(answer.json()["jobs"][0])
    farm.wait(
        lambda: all(farm.jobs()[j]["state"] == "completed" for j in first + second),
        timeout=120,
        what="every job to complete",
    )
    for mark in [*range(700, 704), *range(710, 714)]:
        ran = where_ran(farm, str(mark))
        assert len(ran) == 1, (mark, ran)
        node, printer = ran[0]
        moves = [line for line in farm.nodes[node].ran(printer) if f" Y{mark} " in line]
        assert len(moves) == (600 if mark < 710 else 30)


def test_a_node_cut_from_the_database_past_its_lease_finishes_and_reports_after(
    farm: Farm, tmp_path: Path, postgres: Any
) -> None:
    from tests.support.pg import Cut

    cut = Cut(postgres.port)
    try:
        pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
        start_node(farm, "a", {"a1": {"loadout": pla}}, ("--move-time", "0.004"), cut.url(farm.url))
        start_node(farm, "b", {"b1": {"loadout": pla}})
        (long_job,) = farm.submit("b", part("800", moves=2500), "l.gcode", "printer=a1").json()[
            "jobs"
        ]
        farm.wait(lambda: _printing(farm, long_job), what="the long job to stream on a1")
        cut.cut()
        # b ends a's lease: the farm shows the job interrupted, a1 offline.
        farm.wait(
            lambda: farm.view("b")["jobs"][0]["state"] == "interrupted",
            what="the farm to mark the job interrupted",
        )
        assert {p["name"]: p["state"] for p in farm.view("b")["printers"]}["a1"] == "offline"
        # A job for a1 waits: a claims nothing while it cannot reach the database.
        (waiting,) = farm.submit("b", part("801"), "w.gcode", "printer=a1").json()["jobs"]
        # The stream goes on to its end all the same.
        farm.wait(
            lambda: sum(" Y800 " in line for line in farm.nodes["a"].ran("a1")) == 2500,
            timeout=60,
            what="the cut node's stream to complete",
        )
        assert farm.jobs("b")[waiting]["state"] == "queued"
        cut.mend()
        # Back, a reports with its token: the farm takes its word; then it claims again.
        farm.wait(
            lambda: farm.jobs("b")[long_job]["state"] == "completed", what="a's report of the job"
        )
        done = farm.jobs("b")[long_job]
        assert done["error"] is None and done["lines"] == 2502
        farm.wait(lambda: farm.jobs("b")[waiting]["state"] == "completed", what="the waiting job")
        assert where_ran(farm, "800") == [("a", "a1")]
        assert where_ran(farm, "801") == [("a", "a1")]
    finally:
        cut.close()


def test_hyrel_send_and_a_slicers_upload_feed_the_farm_and_a_held_printer_waits(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    node = start_node(farm, "a", {"a1": {"loadout": pla}}, automatic=False)
    url = node.server.url
    job = tmp_path / "cube.gcode"
    job.write_bytes(part("900"))
    with node.client() as client, client.stream("GET", "/v1/farm/events") as events:
        lines = events.iter_lines()
        hello = next(lines)
        assert hello.startswith("data: ") and '"hello"' in hello
        sent = hyrel_send(str(job), "--server", url, "--api-key", KEY, "--farm",
                          "--require", "material=pla")  # fmt: skip
        assert sent.returncode == 0, sent.stdout + sent.stderr
        told = [json.loads(line[6:]) for line in _lines_until(lines, '"completed"')]
    assert "cube.gcode: queued in the farm as job 1 (material=PLA)" in sent.stdout
    assert "farm job 1 (cube.gcode): printing on a1 at node a" in sent.stdout
    assert "farm job 1: 32 lines (to line 32)" in sent.stdout
    assert {"kind": "job", "jobs": [1], "queued": True, "state": "queued", "type": "farm"} in told
    # The part is on a1's bed: a slicer's "Upload and Print" waits in the farm's queue.
    octoprint = httpx.Client(base_url=f"{url}/farm", headers={"X-Api-Key": KEY}, timeout=30)
    with octoprint:
        version = octoprint.get("/api/version").json()
        assert version["text"].startswith("OctoPrint")
        answer = octoprint.post(
            "/api/files/local",
            data={"print": "true", "path": ""},
            files={"file": ("sliced.gcode", part("901"), "application/octet-stream")},
        )
        assert answer.status_code == 201, answer.text
        assert answer.json()["farm"]["jobs"] == [2]
        upload_only = octoprint.post(
            "/api/files/local", files={"file": ("x.gcode", part("902"), "text/plain")}
        )
        assert upload_only.status_code == 409
    time.sleep(2)
    assert farm.jobs()[2]["state"] == "queued"
    listed = hyrel_send("--server", url, "--api-key", KEY, "--farm", "--list")
    assert listed.returncode == 0
    rows = listed.stdout.splitlines()
    assert rows[0].split()[:2] == ["2", "queued"] and "sliced.gcode" in rows[0]
    assert rows[1].split()[:3] == ["1", "completed", "a1@a"]
    with node.client() as client:
        assert client.post("/v1/printers/a1/release").status_code == 204
    farm.wait(lambda: farm.jobs()[2]["state"] == "completed", what="the slicer's job")
    assert where_ran(farm, "900") == [("a", "a1")] and where_ran(farm, "901") == [("a", "a1")]
    with node.client() as client:  # what cannot be resumed is refused in a sentence
        done = client.post("/v1/farm/jobs/1/resume")
        assert done.status_code == 409
        assert done.json()["error"] == "farm job 1 is completed: nothing to resume"
        assert client.post("/v1/farm/jobs/99/resume").json()["error"] == "the farm has no job 99"
    # Held again; a queued job cancelled from the command line never runs.
    (third,) = farm.submit("a", part("903"), "third.gcode").json()["jobs"]
    cancelled = hyrel_send("--server", url, "--api-key", KEY, "--farm", "--cancel", str(third))
    assert cancelled.returncode == 0 and f"farm job {third}: cancelled" in cancelled.stdout
    assert farm.jobs()[third]["state"] == "cancelled"
    refused = hyrel_send(str(job), "--server", url, "--api-key", KEY, "--farm",
                         "--require", "material=ABS")  # fmt: skip
    assert refused.returncode == 2
    assert "no printer of the farm can print cube.gcode" in refused.stderr
    # A job that only held printers could take: hyrel-send says what it waits for.
    waiting = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", str(job), "--server", url,
         "--api-key", KEY, "--farm"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert waiting.stdout is not None
        said = [waiting.stdout.readline() for _ in range(3)]
    finally:
        waiting.kill()
        waiting.wait(10)
    assert said[1].strip().endswith(": queued")
    assert said[2].strip() == (
        f"farm job {third + 1} waits: the printers that can print it are held, a part on the "
        f"bed (a1 at a); once a bed is clear, release it (hyrel-send --server {url} "
        "--printer a1 --release, or its page)"
    )
    # SIGTERM stops a node at once (its loops never take the stop for an outage).
    began = time.monotonic()
    assert node.server.stop() == 0
    assert time.monotonic() - began < 10


def _lines_until(lines: Iterator[str], text: str) -> list[str]:
    found = []
    for line in lines:
        if line.startswith("data: "):
            found.append(line)
            if text in line:
                return found
    raise AssertionError(f"the stream ended before {text}")


def test_a_printer_whose_lint_refuses_a_claimed_job_gives_it_back(
    farm: Farm, tmp_path: Path
) -> None:
    one = loadout(tmp_path, "one", (1, "MK1-250", "PLA"))
    two = loadout(tmp_path, "two", (1, "MK1-250", "PLA"), (2, "SDS-05", "PLA"))
    start_node(farm, "a", {"a1": {"loadout": one}})
    b = start_node(farm, "b", {"b1": {"loadout": two}})
    b.server.stop()  # b1 stays registered: the farm knows a printer with T1
    answer = farm.submit("a", part("400", tool=1), "t1.gcode")
    assert answer.status_code == 201, answer.text
    assert answer.json()["eligible"] == ["b1 on b"]
    assert "T1 selects yoke 1, slot 2" in answer.json()["not_eligible"]["a1 on a"]
    (job_id,) = answer.json()["jobs"]
    # a1 matches the needs (none) and claims it; its lint refuses; the job goes back.
    given = farm.wait(lambda: (job := farm.jobs()[job_id])["given_back"] and job)
    assert given["state"] == "queued"
    assert "has no head loaded" in next(iter(given["given_back"].values()))
    start_node(farm, "b", {"b1": {"loadout": two}})
    farm.wait(lambda: farm.jobs()[job_id]["state"] == "completed", what="b1 to print it")
    assert where_ran(farm, "400") == [("b", "b1")]


def test_a_printing_farm_job_cancelled_from_another_node_stops_with_its_safe_stop(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    a = start_node(farm, "a", {"a1": {"loadout": pla}}, ("--move-time", "0.005"))
    start_node(farm, "b", {"b1": {"loadout": pla}})
    (job_id,) = farm.submit("b", part("450", moves=3000), "l.gcode", "printer=a1").json()["jobs"]
    farm.wait(lambda: _printing(farm, job_id), what="the job to stream")
    with farm.nodes["b"].client() as client:
        answer = client.delete(f"/v1/farm/jobs/{job_id}")
    assert answer.status_code == 200 and answer.json()["cancelling"] is True
    job = farm.wait(lambda: (j := farm.jobs()[job_id])["state"] == "cancelled" and j)
    assert 0 < job["lines"] < 3002
    ran = a.ran("a1")
    assert sum(" Y450 " in line for line in ran) < 3000
    # The safe stop ran after the job's last move: the head's heater off (by its address).
    assert "M104 T47 S0" in ran[-8:] and "G0 Z10" in ran[-8:]
    assert where_ran(farm, "450") == [("a", "a1")]


def test_farm_settings_are_checked_in_one_sentence(farm_db: str, tmp_path: Path) -> None:
    with_password = farm_db.replace("farm@", "farm:secret@")
    refused = run_server_cli("--data-dir", str(tmp_path / "d"), "--printer", "x=fake",
                             "--farm", with_password)  # fmt: skip
    assert refused.returncode == 2
    assert refused.stderr.strip() == (
        "hyrel-server: --farm: give the database's password in PGPASSWORD or ~/.pgpass, not "
        "in the URL (a URL shows in ps and in logs)"
    )
    garbled = run_server_cli("--data-dir", str(tmp_path / "d"), "--printer", "x=fake",
                             "--farm", "postgresql://farm@host:notaport/db")  # fmt: skip
    assert garbled.returncode == 2
    assert garbled.stderr.strip() == (
        "hyrel-server: --farm postgresql://farm@host:notaport/db: the port 'notaport' is not "
        "a number"
    )
    assert "Traceback" not in garbled.stderr


def test_a_node_refuses_a_newer_schema_and_starts_without_its_database(
    farm_db: str, tmp_path: Path, postgres: Any
) -> None:
    import psycopg

    from repetrel_host.server.farm.schema import MIGRATIONS

    with psycopg.connect(farm_db) as connection:
        connection.execute("CREATE TABLE farm_schema (version integer)")
        connection.execute("INSERT INTO farm_schema VALUES (%s)", (len(MIGRATIONS) + 1,))
    newer = run_server_cli("--data-dir", str(tmp_path / "d"), "--printer", "x=fake",
                           "--farm", farm_db)  # fmt: skip
    assert newer.returncode == 2
    assert "newer than this repetrel-host knows" in newer.stderr
    assert "upgrade repetrel-host on this node" in newer.stderr
    # A database that does not answer: the server starts, says so, prints its own queue.
    nowhere = f"postgresql://farm@127.0.0.1:{postgres.port + 1}/x"
    server = Server(tmp_path / "d2", {"x": "fake"}, "--api-key", KEY, "--farm", nowhere)
    server.start()
    try:
        with server.client() as client:
            assert client.get("/v1/farm").status_code == 503
            answer = client.post(
                "/v1/printers/x/jobs", files={"file": ("a.gcode", b"G28\nG1 X1\n", "text/plain")}
            )
            job_id = answer.json()["id"]
            farm_wait = Farm(nowhere, tmp_path)
            farm_wait.wait(
                lambda: client.get(f"/v1/jobs/{job_id}").json()["state"] == "completed",
                what="the local job",
            )
    finally:
        server.stop()
    assert "does not answer" in server.stderr.read_text()


def test_a_node_that_stopped_between_a_claim_and_its_record_reconciles(
    farm: Farm, tmp_path: Path
) -> None:
    """The farm says this node holds two jobs it has no record of: one claimed (it stopped
    before writing it down: nothing ran, the job goes back to the queue and is printed),
    one started (its data folder was replaced: interrupted, never printed again by itself)."""
    import asyncio

    from repetrel_host.server.farm.db import FarmDB
    from repetrel_host.server.farm.needs import capabilities

    node_id = "00000000-0000-4000-8000-000000000001"
    data = tmp_path / "data-a"
    data.mkdir()
    (data / "farm-node-id").write_text(node_id + "\n")
    source = tmp_path / "r.gcode"
    source.write_bytes(part("460"))

    async def before() -> tuple[int, int]:
        import hashlib

        db = FarmDB(farm.url)
        await db.open()
        has = capabilities("a1", "a", None, "reprap", [])
        await db.register(node_id, "a", "http://a", "test", LEASE * 10, [("a1", has, None)], 5)
        digest = hashlib.sha256(source.read_bytes()).hexdigest()
        await db.store_file(source, digest, 5)
        first, second = await db.submit("r.gcode", digest, {}, 0, 2, 32, None, 5)
        claimed = await db.claim(node_id, "a1", has, 5)
        started = await db.claim(node_id, "a1", has, 5)
        assert claimed and started and (claimed["id"], started["id"]) == (first, second)
        assert await db.start(second, started["fence"], 5)
        await db.close()
        return first, second

    claimed_id, started_id = asyncio.run(before())
    start_node(farm, "a", {"a1": {}})
    farm.wait(lambda: farm.jobs()[claimed_id]["state"] == "completed", what="the claimed job")
    started = farm.wait(lambda: (job := farm.jobs()[started_id])["state"] == "interrupted" and job)
    assert started["error"] == "node a has no record of the job"
    assert where_ran(farm, "460") == [("a", "a1")]
    assert sum(" Y460 " in line for line in farm.nodes["a"].ran("a1")) == 30  # once


def test_farm_options_without_a_server_get_one_sentence(tmp_path: Path) -> None:
    job = tmp_path / "j.gcode"
    job.write_bytes(part("1"))
    for args in (("--require", "material=PLA"), ("--farm",), ("--copies", "2")):
        done = hyrel_send(str(job), *args)
        assert done.returncode == 2, args
        assert done.stderr.strip() == (
            "error: --farm, --require, --priority, --copies and --resume go with --server URL"
        )
    done = hyrel_send(str(job), "--server", "http://127.0.0.1:9", "--farm", "--printer", "x")
    assert done.returncode == 2
    assert "--printer and --release name one printer: not with --farm" in done.stderr


def test_a_job_gets_its_estimate_and_a_printing_printer_its_free_time(
    farm: Farm, tmp_path: Path
) -> None:
    from repetrel_host.gcode.analysis import analyse

    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    a = start_node(farm, "a", {"a1": {"loadout": pla}}, ("--move-time", "0.005"))
    source = tmp_path / "long.gcode"
    source.write_bytes(part("470", moves=4000))
    planned = analyse(source, planned=True).summary
    assert planned is not None and planned.planned_seconds
    answer = farm.submit("a", source.read_bytes(), "long.gcode")
    assert answer.status_code == 201, answer.text
    (job_id,) = answer.json()["jobs"]
    # Planned after the submit answered, by the node that received the file.
    job = farm.wait(lambda: (j := farm.jobs()[job_id])["estimated_time"] is not None and j)
    # Planned as a1 plans its jobs: its loadout's header first (a few commands, no motion).
    assert job["estimated_time"] == pytest.approx(planned.planned_seconds, abs=0.01)
    assert job["estimate_of"] == "file"
    # Printing: a1 is free at its job's expected end.
    farm.wait(lambda: _printing(farm, job_id), what="the job to stream")
    printer = farm.wait(lambda: (p := _printer(farm, "a1"))["free_at"] is not None and p)
    assert printer["state"] == "printing" and printer["job"] == job_id
    assert printer["free_at"] > farm.jobs()[job_id]["started"]
    # Paused: its end waits for a person, so a1 has no free time.
    with a.client() as client:
        assert client.post("/v1/printers/a1/pause").status_code == 204
    farm.wait(lambda: _printer(farm, "a1")["state"] == "paused", what="a1 to pause")
    assert _printer(farm, "a1")["free_at"] is None
    farm.wait(lambda: farm.jobs()[job_id]["expected_end"] is None, what="the end withdrawn")
    with a.client() as client:
        assert client.delete(f"/v1/farm/jobs/{job_id}").status_code == 200
    cut = farm.wait(lambda: (j := farm.jobs()[job_id])["state"] == "cancelled" and j)
    assert _printer(farm, "a1")["free_at"] is None
    # Its rest, from a line: the whole file's estimate at once, the rest's once planned.
    with a.client() as client:
        resumed = client.post(f"/v1/farm/jobs/{job_id}/resume")
    assert resumed.status_code == 201, resumed.text
    (rest_id,) = resumed.json()["jobs"]
    rest = farm.wait(lambda: (j := farm.jobs()[rest_id])["estimate_of"] == "rest" and j)
    assert rest["from_line"] == cut["last_line"] + 1
    assert 0 < rest["estimated_time"] < job["estimated_time"]


def _printer(farm: Farm, name: str) -> dict[str, Any]:
    printer: dict[str, Any] = next(p for p in farm.view()["printers"] if p["name"] == name)
    return printer


def test_a_jobs_estimate_is_at_the_pace_of_the_printers_that_print_it(
    farm: Farm, tmp_path: Path
) -> None:
    from repetrel_host.gcode.analysis import analyse
    from repetrel_host.gcode.timeline import learned_pace
    from repetrel_host.server.store import Store

    # a1 has printed before: one job at half its plan's time. b1 never printed.
    store = tmp_path / "data-a" / "jobs.sqlite"
    store.parent.mkdir()
    Store(store).close()
    with contextlib.closing(sqlite3.connect(store)) as db:
        db.execute(
            "INSERT INTO jobs (printer, name, file, state, position, submitted, started, ended,"
            " pace) VALUES ('a1', 'old.gcode', 'files/old.gcode', 'completed', 0, 1, 2, 3, 0.5)"
        )
        db.commit()
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    a = start_node(farm, "a", {"a1": {"loadout": pla}}, ("--move-time", "0.005"))
    b = start_node(farm, "b", {"b1": {"loadout": pla}})
    for node, name in ((a, "a1"), (b, "b1")):  # nothing is claimed until asked
        farm.wait(lambda name=name: _printer(farm, name)["state"] == "ready", what=name)
        with node.client() as client:
            assert client.post(f"/v1/printers/{name}/hold").status_code == 204
    assert _printer(farm, "a1")["pace"] == 0.5 and _printer(farm, "b1")["pace"] is None
    source = tmp_path / "long.gcode"
    source.write_bytes(part("480", moves=4000))
    summary = analyse(source, planned=True).summary
    assert summary is not None and summary.planned_seconds
    plan = summary.planned_seconds  # the nodes plan it with a1's header first: 1 ms more
    ids = {}
    for requires in ("printer=a1", "printer=b1", "material=PLA"):
        answer = farm.submit("a", source.read_bytes(), "long.gcode", requires)
        assert answer.status_code == 201, answer.text
        ids[requires] = answer.json()["jobs"][0]
    farm.wait(
        lambda: all(farm.jobs()[i]["estimated_time"] is not None for i in ids.values()),
        what="the estimates",
    )
    jobs = farm.jobs()
    # Queued for a1 alone: at its pace; for b1 alone: the plan; for either: their median.
    for requires, pace, pace_from in (
        ("printer=a1", 0.5, "printer"),
        ("printer=b1", 1.0, "plan"),
        ("material=PLA", 0.75, "printers"),
    ):
        job = jobs[ids[requires]]
        assert job["planned_time"] == pytest.approx(plan, abs=0.01), requires
        assert job["estimated_time"] == pytest.approx(plan * pace, abs=0.01), requires
        assert (job["estimated_pace"], job["estimated_pace_from"]) == (pace, pace_from), requires
        assert job["time_left"] is None
    # Printing on a1: at a1's pace, and its time left is a1's own (what its node reports).
    with a.client() as client:
        assert client.post("/v1/printers/a1/release").status_code == 204
    first = ids["printer=a1"]
    farm.wait(lambda: _printing(farm, first), what="the job to stream")
    job = farm.wait(lambda: (j := farm.jobs()[first])["time_left"] is not None and j)
    assert job["estimated_time"] == pytest.approx(plan * 0.5, abs=0.01)
    assert job["estimated_pace_from"] == "printer"
    assert 0 < job["time_left"] <= round(job["expected_end"] - job["started"])
    # Once it ends, a1's pace is what its own store learned, this run's with the one before.
    farm.wait(lambda: farm.jobs()[first]["state"] == "completed", what="the job to end")
    with contextlib.closing(sqlite3.connect(store)) as db:
        paces = [p for (p,) in db.execute("SELECT pace FROM jobs WHERE pace IS NOT NULL")]
    assert len(paces) == 2, "the run was too short to measure its pace"
    learned = farm.wait(lambda: (p := _printer(farm, "a1")["pace"]) != 0.5 and p)
    assert learned == pytest.approx(learned_pace(paces))
    assert farm.jobs()[first]["estimated_pace"] == pytest.approx(learned, abs=1e-4)
