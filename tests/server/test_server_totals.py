"""A printer's totals (``/v1/printers/NAME/totals``): jobs by outcome, the time printed, and
the filament each tool used, kept with each job as it ends (``filament`` in the job): the
file's figure for a completed job, the share of it that ran for a cancelled one. A real
server on the fake."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from tests.support.server import Server, wait_for

pytestmark = pytest.mark.timeout(120)

SHORT = "G28\nG92 E0\nG1 X1 E4 F3000\nG1 X2 E3\nG1 X3 E10\n"  # 10 mm (a retraction inside)
LONG = "G28\nM83\n" + "".join(f"G1 X{i / 10:.1f} E1 F600\n" for i in range(1, 3001))  # 3000 mm


@pytest.mark.slow
def test_totals_add_up_each_jobs_filament_and_time(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake", "other": "fake"})
    with server.client() as client:

        def ended(job_id: int) -> dict:
            def done() -> dict | None:
                job = client.get(f"/v1/jobs/{job_id}").json()
                return job if job["ended"] else None

            return wait_for(done, 60, what=f"job {job_id}'s end")

        def submit(text: str) -> int:
            files = {"file": ("part.gcode", text.encode())}
            answer = client.post("/v1/printers/demo/jobs", files=files)
            assert answer.status_code == 201, answer.text
            return int(answer.json()["id"])

        wait_for(lambda: client.get("/v1/printers/demo").json()["state"] == "ready")
        first = ended(submit(SHORT))
        assert first["state"] == "completed"
        assert first["filament"]["tool0"]["length"] == pytest.approx(10.0)
        client.post("/v1/printers/demo/release")
        second = ended(submit(SHORT))
        client.post("/v1/printers/demo/release")
        long_id = submit(LONG)
        wait_for(lambda: client.get(f"/v1/jobs/{long_id}").json()["lines"] > 200)
        assert client.delete(f"/v1/jobs/{long_id}").status_code in (200, 202, 204)
        cancelled = ended(long_id)
        assert cancelled["state"] == "cancelled"
        share = cancelled["filament"]["tool0"]["length"]
        assert 150 < share < 3000  # what ran of it, roughly: not nothing, not all

        totals = client.get("/v1/printers/demo/totals").json()
        assert totals["printer"] == "demo"
        assert totals["jobs"] == {"completed": 2, "cancelled": 1, "failed": 0, "interrupted": 0}
        assert totals["filament"]["tool0"]["length"] == pytest.approx(20.0 + share)
        seconds = sum(job["ended"] - job["started"] for job in (first, second, cancelled))
        assert totals["print_seconds"] == pytest.approx(seconds)
        assert totals["lines"] == first["lines"] + second["lines"] + cancelled["lines"]
        other = client.get("/v1/printers/other/totals").json()
        assert other["jobs"]["completed"] == 0 and other["filament"] == {}
        assert client.get("/v1/printers/nobody/totals").status_code == 404
