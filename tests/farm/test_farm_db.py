"""The farm's queue in a real PostgreSQL, driven directly: claims that race, fencing
tokens, leases that run out, the schema's versions, files in chunks."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import uuid
from pathlib import Path
from typing import Any

import psycopg
import pytest
import pytest_asyncio

from repetrel_host.errors import ConfigError
from repetrel_host.server.farm import needs
from repetrel_host.server.farm.db import CHUNK, FarmDB, LeaseLost
from repetrel_host.server.farm.schema import MIGRATIONS
from tests.support.pg import needs_postgres

pytestmark = [pytest.mark.timeout(60), pytest.mark.asyncio, needs_postgres]

T = 5.0  # each call's timeout


def caps(name: str, node: str, material: str = "PLA", tags: tuple[str, ...] = ()) -> Any:
    heads = [{"tool": 0, "slot": 1, "head": "MK1-250", "material": material, "nozzle": 0.5}]
    return needs.capabilities(name, node, "hydra-16a", "reprap", heads, tags)


async def node(db: FarmDB, name: str, printers: dict[str, Any], lease: float = 30) -> str:
    made = str(uuid.uuid4())
    await db.register(made, name, f"http://{name}", "test", lease, [
        (printer, has, None) for printer, has in printers.items()
    ], T)  # fmt: skip
    return made


async def queue(db: FarmDB, tmp_path: Path, count: int, **wanted: Any) -> list[int]:
    path = tmp_path / "part.gcode"
    path.write_text("G28\nG1 X10\n")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    await db.store_file(path, digest, T)
    return await db.submit("part.gcode", digest, wanted, 0, count, 2, None, T)


@pytest_asyncio.fixture
async def db(farm_db: str) -> Any:
    farm = FarmDB(farm_db, size=30)
    await farm.open()
    yield farm
    await farm.close()


async def test_printers_racing_for_one_job_one_wins(db: FarmDB, tmp_path: Path) -> None:
    printers = {f"p{n}": caps(f"p{n}", "a") for n in range(20)}
    a = await node(db, "a", printers)
    (job,) = await queue(db, tmp_path, 1)
    claims = await asyncio.gather(*(db.claim(a, name, has, T) for name, has in printers.items()))
    won = [claim for claim in claims if claim is not None]
    assert len(won) == 1 and won[0]["id"] == job and won[0]["state"] == "claimed"


async def test_many_claimers_take_every_job_exactly_once(db: FarmDB, tmp_path: Path) -> None:
    printers = {f"p{n}": caps(f"p{n}", "a") for n in range(10)}
    a = await node(db, "a", printers)
    jobs = await queue(db, tmp_path, 60)
    taken: list[int] = []

    async def claimer(name: str) -> None:
        while (row := await db.claim(a, name, printers[name], T)) is not None:
            taken.append(row["id"])
            assert await db.start(row["id"], row["fence"], T)

    await asyncio.gather(*(claimer(name) for name in printers))
    assert sorted(taken) == jobs


async def test_only_matching_printers_claim_and_priority_goes_first(
    db: FarmDB, tmp_path: Path
) -> None:
    printers = {"pla": caps("pla", "a"), "abs": caps("abs", "a", "ABS", ("enclosed",))}
    a = await node(db, "a", printers)
    (low,) = await queue(db, tmp_path, 1, materials=["ABS"])
    path = tmp_path / "part.gcode"
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    (high,) = await db.submit("urgent.gcode", digest, {"tags": ["enclosed"]}, 5, 1, 2, None, T)
    assert await db.claim(a, "pla", printers["pla"], T) is None
    first = await db.claim(a, "abs", printers["abs"], T)
    second = await db.claim(a, "abs", printers["abs"], T)
    assert first is not None and second is not None
    assert (first["id"], second["id"]) == (high, low)


async def test_a_report_without_the_current_fence_is_refused(db: FarmDB, tmp_path: Path) -> None:
    printers = {"p": caps("p", "a")}
    a = await node(db, "a", printers)
    (job,) = await queue(db, tmp_path, 1)
    claim = await db.claim(a, "p", printers["p"], T)
    assert claim is not None
    fields = {
        "state": "completed", "lines": 2, "last_line": 2, "started": 1.0, "ended": 2.0,
        "error": None, "report": None, "filament": None, "safe_stop": None, "local_id": 7,
    }  # fmt: skip
    assert not await db.report(job, claim["fence"] - 1, fields, T)
    assert (await db.job(job, T))["state"] == "claimed"
    assert await db.report(job, claim["fence"], fields, T)
    done = await db.job(job, T)
    assert done["state"] == "completed" and done["local_id"] == 7


async def test_an_estimate_is_told_and_a_recovered_job_starts_with_the_whole_files(
    db: FarmDB, tmp_path: Path
) -> None:
    printers = {"p": caps("p", "a")}
    a = await node(db, "a", printers)
    jobs = await queue(db, tmp_path, 2)
    assert [(await db.job(job, T))["estimated_time"] for job in jobs] == [None, None]
    listener = await db.listen()
    async with listener:
        await db.estimated(jobs, 2520.0, "file", T)
        notice = await anext(listener.notifies(timeout=T))
    assert json.loads(notice.payload) == {"kind": "job", "jobs": jobs, "estimated": True}
    listed = {job["id"]: job for job in await db.jobs(T)}
    assert [(listed[job]["estimated_time"], listed[job]["estimate_of"]) for job in jobs] == [
        (2520.0, "file"),
        (2520.0, "file"),
    ]
    # A printing job's expected end comes with its progress; its end clears it.
    claim = await db.claim(a, "p", printers["p"], T)
    assert claim is not None and await db.start(claim["id"], claim["fence"], T)
    fields = {
        "state": "printing", "lines": 1, "last_line": 1, "started": 1.0, "ended": None,
        "error": None, "report": None, "filament": None, "safe_stop": None, "local_id": 1,
        "expected_end": 2_000_000_000.0,
    }  # fmt: skip
    assert await db.report(claim["id"], claim["fence"], fields, T)
    assert (await db.job(claim["id"], T))["expected_end"] == 2_000_000_000.0
    fields |= {"state": "cancelled", "ended": 2.0, "expected_end": None}
    assert await db.report(claim["id"], claim["fence"], fields, T)
    assert (await db.job(claim["id"], T))["expected_end"] is None
    # Its rest: the whole file's estimate until the rest is planned.
    rest = await db.recover(claim["id"], 2, 1, T)
    recovered = await db.job(rest, T)
    assert (recovered["estimated_time"], recovered["estimate_of"]) == (2520.0, "file")
    await db.estimated([rest], 1200.0, "rest", T)
    recovered = await db.job(rest, T)
    assert (recovered["estimated_time"], recovered["estimate_of"]) == (1200.0, "rest")


async def test_a_lost_lease_interrupts_its_printing_jobs_and_requeues_its_claims(
    db: FarmDB, tmp_path: Path
) -> None:
    printers = {"p1": caps("p1", "a"), "p2": caps("p2", "a")}
    a = await node(db, "a", printers, lease=1)
    b = await node(db, "b", {"q": caps("q", "b")}, lease=30)
    printing, claimed = await queue(db, tmp_path, 2)
    one = await db.claim(a, "p1", printers["p1"], T)
    two = await db.claim(a, "p2", printers["p2"], T)
    assert one is not None and two is not None
    assert await db.start(one["id"], one["fence"], T)
    await asyncio.sleep(1.5)
    interrupted = await db.heartbeat(b, 30, T)  # b ends a's lease
    assert [row["id"] for row in interrupted] == [printing]
    job = await db.job(printing, T)
    assert job["state"] == "interrupted" and "node a stopped answering" in job["error"]
    assert (await db.job(claimed, T))["state"] == "queued"
    # The lost node learns it when it beats again; it cannot claim until it joins again.
    with pytest.raises(LeaseLost):
        await db.heartbeat(a, 1, T)
    assert await db.claim(a, "p2", printers["p2"], T) is None
    # Its report with its token is taken: its printer is the authority on what ran.
    fields = {
        "state": "completed", "lines": 2, "last_line": 2, "started": 1.0, "ended": 2.0,
        "error": None, "report": None, "filament": None, "safe_stop": None, "local_id": 1,
    }  # fmt: skip
    assert await db.report(printing, one["fence"], fields, T)
    assert (await db.job(printing, T))["state"] == "completed"


async def test_a_newer_schema_is_refused_in_one_sentence(farm_db: str) -> None:
    db = FarmDB(farm_db)
    await db.open()
    await db.close()
    with psycopg.connect(farm_db) as connection:
        connection.execute("INSERT INTO farm_schema VALUES (%s)", (len(MIGRATIONS) + 1,))
    newer = FarmDB(farm_db)
    with pytest.raises(ConfigError, match="newer than this repetrel-host knows"):
        await newer.open()  # refused before its pool opens


async def test_a_file_goes_in_and_out_in_chunks(db: FarmDB, tmp_path: Path) -> None:
    path = tmp_path / "big.gcode"
    path.write_bytes(os.urandom(CHUNK * 2 + 123))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    await db.store_file(path, digest, T)
    await db.store_file(path, digest, T)  # once, however often it is sent
    back = tmp_path / "back.gcode"
    await db.fetch_file(digest, back, T)
    assert back.read_bytes() == path.read_bytes()
    async with db.pool.connection() as connection:
        cursor = await connection.execute("SELECT count(*) AS n FROM file_chunks")
        assert (await cursor.fetchone())["n"] == 3


async def test_an_older_schema_is_migrated_once_in_order(farm_db: str) -> None:
    with psycopg.connect(farm_db) as connection:  # a farm made by the first version
        connection.execute("CREATE TABLE farm_schema (version integer)")
        connection.execute(MIGRATIONS[0])
        connection.execute("INSERT INTO farm_schema VALUES (1)")
    for _ in range(2):  # the second time, nothing is left to do
        db = FarmDB(farm_db)
        assert await db.open() == len(MIGRATIONS)
        await db.close()
    with psycopg.connect(farm_db) as connection:
        versions = [row[0] for row in connection.execute("SELECT version FROM farm_schema")]
        columns = {
            row[0]
            for row in connection.execute(
                "SELECT column_name FROM information_schema.columns WHERE table_name = 'jobs'"
            )
        }
    assert versions == list(range(1, len(MIGRATIONS) + 1))
    assert {"from_line", "resumes", "estimated_time", "estimate_of", "expected_end"} <= columns


def done(state: str, **more: Any) -> dict[str, Any]:
    """A node's report of a job (its record's fields)."""
    return {
        "state": state, "lines": 1, "last_line": 1, "started": 1.0, "ended": 2.0,
        "error": None, "report": None, "filament": None, "safe_stop": None, "local_id": 1,
        **more,
    }  # fmt: skip


async def printing_on_a_short_lease(db: FarmDB, tmp_path: Path) -> tuple[str, int, dict[str, Any]]:
    """A job printing on node a, whose lease is 1 s, beside node b (whose heartbeat ends
    a's lease once it ran out): b, the job and its claim."""
    printers = {"p": caps("p", "a")}
    a = await node(db, "a", printers, lease=1)
    b = await node(db, "b", {"q": caps("q", "b")})
    (job,) = await queue(db, tmp_path, 1)
    claim = await db.claim(a, "p", printers["p"], T)
    assert claim is not None and await db.start(job, claim["fence"], T)
    return b, job, claim


async def test_a_lost_lease_is_told_with_its_state_and_ends_the_expected_end(
    db: FarmDB, tmp_path: Path
) -> None:
    b, job, claim = await printing_on_a_short_lease(db, tmp_path)
    printing = done("printing", ended=None, expected_end=2_000_000_000.0)
    assert await db.report(job, claim["fence"], printing, T)
    assert (await db.job(job, T))["expected_end"] == 2_000_000_000.0
    await asyncio.sleep(1.5)
    listener = await db.listen()
    async with listener:
        await db.heartbeat(b, 30, T)
        told = [json.loads(n.payload) async for n in listener.notifies(timeout=1.0)]
    said = next(m for m in told if m.get("job") == job)
    assert said["state"] == "interrupted" and "node a stopped answering" in said["error"]
    ended = await db.job(job, T)
    assert ended["state"] == "interrupted" and ended["expected_end"] is None


async def test_a_job_is_resumed_once_even_by_two_at_once(db: FarmDB, tmp_path: Path) -> None:
    from repetrel_host.server.farm.states import MoveRefused

    printers = {"p": caps("p", "a")}
    a = await node(db, "a", printers)
    (job,) = await queue(db, tmp_path, 1)
    claim = await db.claim(a, "p", printers["p"], T)
    assert claim is not None and await db.start(job, claim["fence"], T)
    assert await db.report(job, claim["fence"], done("interrupted"), T)
    both = await asyncio.gather(
        db.recover(job, 2, 1, T), db.recover(job, 2, 1, T), return_exceptions=True
    )
    made = [answer for answer in both if isinstance(answer, int)]
    refused = [answer for answer in both if isinstance(answer, MoveRefused)]
    assert len(made) == 1 and len(refused) == 1, both
    rest = made[0]
    assert str(refused[0]) == (
        f"farm job {job} was resumed already, as farm job {rest}: that job prints its rest "
        "(resume that one if it did not complete)"
    )
    resumed = await db.job(job, T)
    assert (resumed["state"], resumed["resumed_by"]) == ("resumed", rest)
    assert (await db.job(rest, T))["total_lines"] == 1  # the rest's lines, not the file's
    # Its node's later word that it ended (its record, after a restart) keeps "resumed",
    # and what it says of the safe stop is taken.
    went = "the server ended while the job was streaming (its safe stop went once ...)"
    assert await db.report(
        job, claim["fence"], done("interrupted", error=went, safe_stop="sent"), T
    )
    after = await db.job(job, T)
    assert (after["state"], after["safe_stop"], after["error"]) == ("resumed", "sent", went)
    with pytest.raises(MoveRefused, match="resumed already"):
        await db.recover(job, 2, 1, T)
    with psycopg.connect(db.url) as connection, pytest.raises(psycopg.errors.CheckViolation):
        connection.execute("UPDATE jobs SET state = 'resuming' WHERE id = %s", (job,))


async def test_a_resumed_job_whose_node_went_on_cancels_its_queued_rest(
    db: FarmDB, tmp_path: Path
) -> None:
    """A node cut from the database, not stopped: the farm took its job for interrupted and
    someone resumed it; the node comes back saying it completed. Its rest must not print
    on the finished part."""
    b, job, claim = await printing_on_a_short_lease(db, tmp_path)
    await asyncio.sleep(1.5)
    assert [row["id"] for row in await db.heartbeat(b, 30, T)] == [job]
    rest = await db.recover(job, 2, 1, T)
    assert await db.report(job, claim["fence"], done("completed"), T)
    completed, cancelled = await db.job(job, T), await db.job(rest, T)
    assert (completed["state"], completed["resumed_by"]) == ("completed", None)
    assert cancelled["state"] == "cancelled"
    assert cancelled["error"] == (
        f"farm job {job} went on at its node after all (completed): its rest is not needed"
    )
    # A completed job stays completed whatever comes after.
    assert await db.report(job, claim["fence"], done("interrupted"), T)
    assert (await db.job(job, T))["state"] == "completed"
