"""The printer is known before a job, and its temperatures during one (issue 22, item 6):
a real hyrel-server process on a fake controller that takes 14 s to answer its first M115
(past the session's patience), printing a job that heats to 200 °C. OctoPrint's
``/api/printer`` shows what the fake itself says of its heaters (its control channel), the
firmware is known on ``/v1/printers/NAME``, and the fake's log shows each job line once,
in order, whatever polls went between them."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import Server, wait_for

pytestmark = pytest.mark.timeout(150)

IDENTIFY_TIME = "14"  # seconds: more than the session's FIRMWARE_PATIENCE (12 s)
HEAT = ["M104 S200", "M140 S60", "M109 S200"]
MOVES = [f"G1 X{i % 200} Y{i % 7} F3000" for i in range(2000)]
# The session's own lines: its greeting, M115s (who are you; Hyrel's syncs), polls, M155.
OWN = ("M110", "M115", "M105", "M155")


def heaters_agree(client: httpx.Client, fake: BuiltInFake) -> bool:
    """While the job prints, /api/printer's hotend and bed are the fake's own (at 200 and
    60 °C once heated): reported as the job goes, not the 21 °C of before it."""
    response = client.get("/api/printer")  # 409 until the printer is operational
    answer = response.json()
    if response.status_code != 200 or not answer["state"]["flags"]["printing"]:
        return False
    real: dict[str, Any] = fake.request("status")["temperatures"]
    shown = answer["temperature"]
    pairs = [(shown["tool0"], real["T"], 200.0), (shown["bed"], real["B"], 60.0)]
    return all(
        heater["target"] == target == wanted
        and heater["actual"] is not None
        and abs(heater["actual"] - actual) <= 0.5
        for heater, (actual, target), wanted in pairs
    )


MARLIN = "repetrel-host fake controller (Marlin replies)"


@pytest.mark.parametrize(
    ("protocol", "fake_args", "firmware"),
    [
        ("reprap", [], MARLIN),  # its M155, sent mid-job
        ("reprap", ["--no-autoreport"], MARLIN),  # M105 polls between the job's lines
        ("hyrel", ["--protocol", "hyrel"], ">Hy: repetrel-host-fake_1.0"),  # its status byte
    ],
    ids=["autoreport", "polled", "hyrel"],
)
@pytest.mark.slow
def test_a_heated_job_shows_the_controllers_temperatures_though_it_was_slow_to_say_who_it_is(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    protocol: str,
    fake_args: list[str],
    firmware: str,
) -> None:
    slow = ["--identify-time", IDENTIFY_TIME, "--heat-rate", "40", "--move-time", "0.004"]
    fake = bench(*slow, *fake_args)
    config = tmp_path / "server.toml"
    config.write_text(f'[printers.bench]\nport = "{fake.port}"\nprotocol = "{protocol}"\n')
    server = servers({}, "--config", str(config))
    text = "".join(f"{line}\n" for line in HEAT + MOVES)
    with server.client() as client:
        # Queued at once: it starts as soon as the session is ready, its M115 unanswered.
        files = {"file": ("heated.gcode", text.encode())}
        answer = client.post("/v1/printers/bench/jobs", files=files)
        assert answer.status_code == 201, answer.text
        job_id = answer.json()["id"]
        wait_for(lambda: heaters_agree(client, fake), 60, "the fake's temperatures, mid-job")
        printer = client.get("/v1/printers/bench").json()
        assert printer["firmware"] == firmware
        assert printer["temperatures"]["T"]["target"] == 200.0
        wait_for(
            lambda: client.get(f"/v1/jobs/{job_id}").json()["state"] == "completed", 60, "the end"
        )
        record = client.get(f"/v1/jobs/{job_id}").json()
        assert record["lines"] == len(HEAT + MOVES) and record["error"] is None
        time.sleep(2.0)  # the server's polls of an idle printer
        # A healthy link draws no error: not the greeting, the job, its end, nor the polls.
        assert fake.request("status")["errors"] == 0
    fake.request("status")  # the log is complete
    assert fake.log_path is not None
    ran = fake.log_path.read_text().splitlines()
    assert [line for line in ran if not line.startswith(OWN)] == HEAT + MOVES
    if "--no-autoreport" in fake_args:
        assert "M105" in ran and not any(line.startswith("M155") for line in ran)
    elif protocol == "reprap":
        assert ran.count("M155 S2") == 1
    else:
        assert "M105" not in ran  # Hyrel's link: the status byte, no line
