"""The temperature history a chart loads (``GET /v1/printers/NAME/temperatures``): the
reports the server kept, oldest first, a heater's new target in the reports after it was
set, ``since`` for what came after a time, and the event stream's reports carrying their
time so that a page appends them where the history ends. A real server on the fake."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import pytest

from tests.support.server import Server, wait_for

pytestmark = pytest.mark.timeout(90)


@pytest.mark.slow
def test_the_history_holds_the_reports_oldest_first_and_since_a_time(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake", "other": "fake"})
    with server.client() as client:

        def samples(**params: float) -> list[dict]:
            answer = client.get("/v1/printers/demo/temperatures", params=params)
            assert answer.status_code == 200, answer.text
            assert answer.json()["printer"] == "demo"
            return answer.json()["samples"]

        wait_for(lambda: client.get("/v1/printers/demo").json()["state"] == "ready")
        wait_for(lambda: samples(), what="a first report")
        asked_at = time.time()
        sent = client.post("/v1/printers/demo/command", json={"command": "M104 S150"})
        assert sent.status_code == 200, sent.text
        assert sent.json()["ok"] is True and sent.json()["ok_line"].startswith("ok"), sent.json()
        answered_at = time.time()

        def heated_reports() -> list[dict]:
            kept = samples()
            heated = [s for s in kept if s["readings"]["T"]["target"] == 150]
            return kept if len(heated) >= 2 else []

        kept = wait_for(heated_reports, what="two reports with the new target")
        times = [s["time"] for s in kept]
        assert times == sorted(times) and len(set(times)) == len(times)
        assert all(set(s["readings"]["T"]) == {"actual", "target"} for s in kept)
        # The new target is in every report made after it was set, and in none before.
        assert all(s["readings"]["T"]["target"] == 150 for s in kept if s["time"] > answered_at)
        before = [s for s in kept if s["time"] < asked_at]
        assert before and all(s["readings"]["T"]["target"] in (0, None) for s in before)
        after = samples(since=times[-2])
        assert after[0]["time"] == times[-1] and all(s["time"] > times[-2] for s in after)
        assert samples(since=time.time() + 60) == []
        # Each printer has its own: the other's heater was not set.
        other = client.get("/v1/printers/other/temperatures").json()["samples"]
        assert other and all(s["readings"]["T"]["target"] in (0, None) for s in other)
        assert client.get("/v1/printers/nobody/temperatures").status_code == 404
        bad = client.get("/v1/printers/demo/temperatures", params={"since": "yesterday"})
        assert bad.status_code == 400
        client.post("/v1/printers/demo/command", json={"command": "M104 S0"})


@pytest.mark.slow
def test_the_event_streams_reports_carry_their_time(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake"})
    with server.client() as client:
        with client.stream("GET", "/v1/events", params={"printer": "demo"}) as events:
            lines = events.iter_lines()
            for line in lines:
                if line.startswith("event: temperatures"):
                    data = json.loads(next(lines).removeprefix("data: "))
                    break
        assert data["printer"] == "demo" and abs(data["time"] - time.time()) < 30
        kept = client.get("/v1/printers/demo/temperatures").json()["samples"]
        assert data["time"] in [s["time"] for s in kept]
