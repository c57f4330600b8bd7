"""The server killed (``kill -9``) mid-job and started again: the safe stop it owes turns off
every heater the job turned on, on both links and whatever the job was doing (issue 35).
Read at the fake controller: its heater targets, not the server's account."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import TWO_HOTENDS, executed
from tests.support.helpers import heater_targets as targets
from tests.support.server import Server, job_state, server_config, wait_for

pytestmark = pytest.mark.timeout(120)
HEATING = "M140 S60\nM104 T0 S200\nM104 T1 S210\nT1\n"
MOVES = "".join(f"G1 X{i % 50} F600\n" for i in range(3000))
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}


def ran(fake: BuiltInFake, command: str) -> bool:
    fake.request("status")  # the log is flushed before the answer
    return command in executed(fake.log_path)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("phase", ["printing", "heat wait", "paused"])
@pytest.mark.slow
def test_a_restart_after_kill_9_turns_off_every_heater_the_job_turned_on(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    protocol: str,
    phase: str,
) -> None:
    args = ["--protocol", protocol, *TWO_HOTENDS, "--move-time", "0.01"]
    if phase == "heat wait":
        args += ["--heat-rate", "1"]
    fake = bench(*args)
    config = server_config(tmp_path, bench={"port": fake.port, "protocol": protocol})
    text = HEATING + ("M109 T1 S210\n" if phase == "heat wait" else "") + MOVES
    server = servers({}, "--config", str(config))
    with server.client() as client:
        job = client.post("/v1/printers/bench/jobs", files={"file": ("two.gcode", text)})
        assert job.status_code == 201, job.text
        if phase == "heat wait":
            wait_for(lambda: ran(fake, "T1"), what="the heat wait")
            time.sleep(0.5)
        else:
            wait_for(lambda: ran(fake, "G1 X20 F600"), what="the moves")
        if phase == "paused":
            assert client.post("/v1/printers/bench/pause").status_code == 204
            wait_for(lambda: job_state(client, job.json()["id"])["state"] == "paused")
        assert targets(fake)["T1"] == 210.0
    server.stop(signal.SIGKILL)
    assert targets(fake)["T"] == 200.0  # still on: nobody turned it off

    restarted = servers({}, "--config", str(config))
    with restarted.client() as client:
        wait_for(lambda: targets(fake) == ALL_OFF, what=f"every heater off: {targets(fake)}")
        wait_for(
            lambda: job_state(client, job.json()["id"])["safe_stop"] == "sent",
            what="the record saying the safe stop went",
        )
    done = executed(fake.log_path)
    assert done.count("G0 Z10") == 1, done[-20:]  # lifted once


@pytest.mark.parametrize(
    ("signum", "protocol"),
    [
        (signal.SIGTERM, "reprap"),
        (signal.SIGTERM, "hyrel"),
        (signal.SIGHUP, "reprap"),
        (signal.SIGQUIT, "hyrel"),
    ],
    ids=["SIGTERM-reprap", "SIGTERM-hyrel", "SIGHUP-reprap", "SIGQUIT-hyrel"],
)
@pytest.mark.slow
def test_a_stop_signal_stops_the_servers_job_with_every_heater_off(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    signum: signal.Signals,
    protocol: str,
) -> None:
    """SIGTERM (systemd), SIGHUP (the terminal or ssh session it ran in, gone) and SIGQUIT
    (Ctrl-\\) stop the server as Ctrl-C does: the job's safe stop, then exit 0."""
    fake = bench("--protocol", protocol, *TWO_HOTENDS, "--move-time", "0.01")
    config = server_config(tmp_path, bench={"port": fake.port, "protocol": protocol})
    server = servers({}, "--config", str(config))
    with server.client() as client:
        job = client.post("/v1/printers/bench/jobs", files={"file": ("two.gcode", HEATING + MOVES)})
        assert job.status_code == 201, job.text
        wait_for(lambda: ran(fake, "G1 X20 F600"), what="the moves")
    assert server.stop(signum) == 0
    assert targets(fake) == ALL_OFF


@pytest.mark.slow
def test_a_cancel_held_up_by_a_heat_wait_reads_cancelling_until_it_ends(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    # No emergency parser: nothing breaks the M190, the safe stop waits for it.
    fake = bench("--heat-rate", "5", "--no-emergency-parser")
    server = servers({"bench": fake.port})
    text = "M140 S60\nM190 S60\nM104 S200\n" + MOVES
    with server.client() as client:
        job = client.post("/v1/printers/bench/jobs", files={"file": ("wait.gcode", text)})
        assert job.status_code == 201, job.text
        wait_for(lambda: ran(fake, "M140 S60"), what="the heat wait")
        cancel = client.post("/api/job", json={"command": "cancel"})
        assert cancel.status_code == 204
        state = client.get("/api/printer").json()["state"]
        assert state["text"] == "Cancelling" and state["flags"]["cancelling"], state
        assert client.get("/api/job").json()["state"] == "Cancelling"
        assert client.get("/v1/printers/bench").json()["job"]["stopping"] is True
        wait_for(lambda: client.get("/api/job").json()["state"] != "Cancelling", timeout=30)
        assert job_state(client, job.json()["id"])["state"] == "cancelled"
    assert targets(fake) == {"T": 0.0, "B": 0.0}
