"""A node's server stopped (SIGTERM) or killed (``kill -9``) and started again, in every
state its farm job can be in: the farm's record after tells what happened, the job is
never printed twice, and what did not complete stays resumable (once)."""

from __future__ import annotations

import asyncio
import re
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from repetrel_host.server.farm.db import FarmDB
from repetrel_host.server.farm.needs import capabilities
from repetrel_host.server.printers.service import STOPPED_SAFELY
from repetrel_host.server.store import CRASHED_SENT
from tests.support.farm import Farm, Node, loadout, part, start_node, where_ran
from tests.support.pg import needs_postgres

pytestmark = [pytest.mark.timeout(180), needs_postgres]

MOVES = 3000  # a job that streams for about 12 s at 4 ms a move
SLOW = ("--move-time", "0.004")


def _moves(node: Node, mark: str) -> list[str]:
    return [line for line in node.ran("a1") if f" Y{mark} " in line]


def _other_node_printer(farm: Farm) -> None:
    """A node z whose printer z1 never claims (no server drives it): a job for it stays
    queued, whatever happens to node a."""

    async def register() -> None:
        db = FarmDB(farm.url)
        await db.open()
        has = capabilities("z1", "z", None, "reprap", [])
        node = "00000000-0000-4000-8000-00000000000f"
        await db.register(node, "z", "http://z", "test", 600, [("z1", has, None)], 5)
        await db.close()

    asyncio.run(register())


def _reached(farm: Farm, a: Node, state: str) -> int:
    """Node a's farm job in ``state`` (the interrupted one: through a kill -9 and a
    restart first); its number."""
    if state == "queued":
        _other_node_printer(farm)
        answer = farm.submit("a", part("520"), "z.gcode", "printer=z1")
        assert answer.status_code == 201, answer.text
        (job,) = answer.json()["jobs"]
        return int(job)
    if state == "completed":
        (job,) = farm.submit("a", part("510"), "short.gcode", "printer=a1").json()["jobs"]
        farm.wait(lambda: farm.jobs()[job]["state"] == "completed", what="the job to complete")
        return int(job)
    long = part("500", moves=MOVES, unique=True)
    (job,) = farm.submit("a", long, "long.gcode", "printer=a1").json()["jobs"]
    farm.wait(
        lambda: (j := farm.jobs()[job])["state"] == "printing" and j["lines"] > 50,
        what="the job to stream",
    )
    if state == "paused":
        with a.client() as client:
            assert client.post("/v1/printers/a1/pause").status_code == 204
        farm.wait(lambda: farm.jobs()[job]["state"] == "paused", what="the farm to see it paused")
    elif state == "interrupted":
        a.server.stop(signal.SIGKILL)
        start_node(farm, "a", {"a1": {"loadout": farm.tmp / "pla.toml"}}, SLOW)
        farm.wait(
            lambda: (j := farm.jobs()[job])["state"] == "interrupted" and j["safe_stop"] == "sent",
            what="the job interrupted, its safe stop sent",
        )
    return int(job)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "kill-9"])
@pytest.mark.parametrize("state", ["queued", "printing", "paused", "interrupted", "completed"])
def test_a_restarted_node_leaves_its_farm_job_as_it_should(
    farm: Farm, tmp_path: Path, state: str, signum: int
) -> None:
    loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    a = start_node(farm, "a", {"a1": {"loadout": tmp_path / "pla.toml"}}, SLOW)
    job = _reached(farm, a, state)
    before = farm.jobs()[job]
    ran_before = _moves(farm.nodes["a"], "500")
    farm.nodes["a"].server.stop(signum)
    a = start_node(farm, "a", {"a1": {"loadout": tmp_path / "pla.toml"}}, SLOW)
    with a.client() as client:  # a1 answers again: its safe stop, if owed, went
        farm.wait(lambda: client.get("/v1/printers/a1").json()["state"] == "ready", what="a1")
    time.sleep(2.0)  # the node's reports (each second) and any claim it would make
    after = farm.jobs()[job]
    assert after["expected_end"] is None
    if state == "queued":
        assert (after["state"], after["node"], after["printer"]) == ("queued", None, None)
        assert where_ran(farm, "520") == []
        return
    if state == "completed":
        assert (after["state"], after["lines"], after["resume_command"]) == ("completed", 32, None)
        assert len(_moves(a, "510")) == 30  # once, not again
        return
    # It was streaming (or was interrupted already): interrupted, its part on a1's bed.
    after = _settled(farm, job, state, signum, before)
    ran = _moves(a, "500")
    assert 50 < after["last_line"] < MOVES + 2 and 0 < len(ran) < MOVES
    xs = [float(re.search(r"X(\S+)", line).group(1)) for line in ran]  # type: ignore[union-attr]
    assert xs == sorted(set(xs)), "a move ran twice"
    if state == "interrupted":
        assert ran == ran_before  # nothing more ran after the restart
        assert after["last_line"] == before["last_line"]
    assert after["resume_from_line"] == after["last_line"] + 1
    assert after["resume_command"] and after["resumed_by"] is None
    with a.client() as client:
        assert client.get("/v1/printers/a1").json()["held"] is True


def _settled(
    farm: Farm, job: int, state: str, signum: int, before: dict[str, Any]
) -> dict[str, Any]:
    """The job's record once its node reported it after the restart, checked for what each
    stop leaves: SIGTERM stops it with its safe stop confirmed; kill -9 leaves the safe stop
    owed, sent as soon as a1 answers (and the record says so)."""
    if state == "interrupted":  # it ended before this stop: the record stays as it was
        after = farm.jobs()[job]
        assert (after["state"], after["error"], after["safe_stop"]) == (
            "interrupted",
            CRASHED_SENT,
            "sent",
        )
        return after
    if signum == signal.SIGTERM:
        after = farm.wait(lambda: (j := farm.jobs()[job])["state"] == "interrupted" and j)
        assert (after["error"], after["safe_stop"]) == (STOPPED_SAFELY, None)
        return after
    after = farm.wait(
        lambda: (
            (j := farm.jobs()[job])["state"] == "interrupted" and j["safe_stop"] == "sent" and j
        ),
        what="the restarted node's record of the job, its safe stop sent",
    )
    assert after["error"] == CRASHED_SENT
    return after
