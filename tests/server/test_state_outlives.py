"""What must outlive a server process (issue 48): one connect loop per printer, a safe stop
a stop could not finish left owed and said by the exit code, and the "part on the bed" hold
kept across SIGTERM and ``kill -9``. A real server on the pty fake, read at the fake: its
heater targets and executed log, not the server's account."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import TWO_HOTENDS, executed
from tests.support.helpers import heater_targets as targets
from tests.support.server import Server, job_state, server_config, wait_for

pytestmark = pytest.mark.timeout(150)
HEATING = "M140 S60\nM104 T0 S200\nM104 T1 S210\nT1\n"
MOVES = "".join(f"G1 X{i % 50} F600\n" for i in range(3000))
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}
EXIT_SAFE_STOP_OWED = 75
OFFLINE = 12  # seconds the link stays away in the "owing, offline" state


def ran(fake: BuiltInFake, command: str) -> bool:
    fake.request("status")  # the log is flushed before the answer
    return command in executed(fake.log_path)


def queue(client: httpx.Client, text: str, name: str = "two.gcode") -> int:
    answer = client.post("/v1/printers/bench/jobs", files={"file": (name, text)})
    assert answer.status_code == 201, answer.text
    return int(answer.json()["id"])


def printer(client: httpx.Client) -> dict[str, Any]:
    answer: dict[str, Any] = client.get("/v1/printers/bench").json()
    return answer


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_a_connect_asked_for_while_offline_starts_no_second_connect_loop(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path, protocol: str
) -> None:
    """OctoPrint's connect and Moonraker's restart while the port is away join the one
    connect loop: nothing else takes the port, so the job's session sends its own safe
    stop after a lost link, and the record says so only once it went."""
    fake = bench("--protocol", protocol, *TWO_HOTENDS, "--move-time", "0.01")
    assert fake.request("link_drop 3")["ok"]
    config = server_config(tmp_path, bench={"port": fake.port, "protocol": protocol})
    server = servers({}, "--config", str(config))
    with server.client() as client:
        for _ in range(3):
            connect = client.post("/api/connection", json={"command": "connect"})
            assert connect.status_code == 204, connect.text
            restart = client.post("/printer/firmware_restart")  # Moonraker's
            assert restart.status_code == 200, restart.text
        server.wait_ready("bench")
        job = queue(client, HEATING + MOVES)
        wait_for(lambda: ran(fake, "G1 X20 F600"), what="the moves")
        assert fake.request("link_drop 2")["ok"]
        wait_for(lambda: job_state(client, job)["state"] != "printing", 60, "the job's end")
        wait_for(lambda: targets(fake) == ALL_OFF, what=f"every heater off: {targets(fake)}")
        record = job_state(client, job)
    log = server.stderr.read_text()
    assert "the port is busy" not in log, log
    assert log.count("connected on") == 1, log
    assert record["safe_stop"] != "owed", record


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_the_hold_after_a_job_outlives_sigterm_and_kill_9(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path, protocol: str
) -> None:
    fake = bench("--protocol", protocol)
    config = server_config(tmp_path, bench={"port": fake.port, "protocol": protocol})
    server = servers({}, "--config", str(config))
    with server.client() as client:
        first = queue(client, "G1 X1 F600\nG1 X2 F600\n", "first.gcode")
        wait_for(lambda: job_state(client, first)["state"] == "completed", what="the first job")
        held = printer(client)
        assert held["held"] and f"job {first} completed" in held["hold_reason"], held
    for signum in (signal.SIGTERM, signal.SIGKILL):
        server.stop(signum)
        server = servers({}, "--config", str(config)).wait_ready("bench")
        with server.client() as client:
            after = printer(client)
            assert after["held"] and after["hold_reason"] == held["hold_reason"], (signum, after)
    with server.client() as client:
        second = queue(client, "G1 X7 F600\n", "second.gcode")
        time.sleep(2)  # it would have started by now
        assert job_state(client, second)["state"] == "queued"
        assert not ran(fake, "G1 X7 F600")  # nothing printed onto the last part
        assert client.post("/v1/printers/bench/release").status_code == 204
        wait_for(lambda: job_state(client, second)["state"] == "completed", what="the release")
        assert ran(fake, "G1 X7 F600")
    server.stop(signal.SIGKILL)
    server = servers({}, "--config", str(config)).wait_ready("bench")
    with server.client() as client:  # held again by the second job, not by the first
        assert f"job {second} completed" in printer(client)["hold_reason"]


def in_a_heat_wait(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    heat_rate: float,
    stop_timeout: float,
) -> tuple[BuiltInFake, Path, Server, int]:
    """A server whose job waits for its bed (M190) on a fake with no emergency parser
    (nothing breaks the wait); the fake, the server's TOML file, the server, the job."""
    fake = bench("--heat-rate", str(heat_rate), "--no-emergency-parser")
    config = server_config(tmp_path, bench={"port": fake.port})
    server = servers({}, "--config", str(config), "--stop-timeout", str(stop_timeout))
    with server.client() as client:
        job = queue(client, "M104 S200\nM140 S60\nM190 S60\n" + MOVES)
        wait_for(lambda: ran(fake, "M140 S60"), what="the heat wait")
    return fake, config, server, job


@pytest.mark.slow
def test_a_stop_held_up_by_a_heat_wait_exits_75_and_the_next_start_sends_the_safe_stop(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    """No emergency parser: nothing breaks the M190 before the bed is there. The stop waits
    --stop-timeout, leaves the safe stop owed, says so and exits 75 (systemd's
    Restart=on-failure starts it again); the next start sends it."""
    fake, config, server, job = in_a_heat_wait(bench, servers, tmp_path, 1, 2)
    assert server.stop(signal.SIGTERM) == EXIT_SAFE_STOP_OWED
    log = server.stderr.read_text()
    assert "exiting with 75: the safe stop of printer bench is owed" in log, log
    assert targets(fake)["T"] == 200.0  # still on: the stop did not go
    restarted = servers({}, "--config", str(config))
    with restarted.client() as client:
        wait_for(lambda: targets(fake) == {"T": 0.0, "B": 0.0}, 90, "the owed safe stop")
        wait_for(lambda: job_state(client, job)["safe_stop"] == "sent", what="its record")
        assert printer(client)["held"]  # the interrupted job's part may be on the bed
    assert restarted.stop(signal.SIGTERM) == 0


@pytest.mark.slow
def test_a_stop_timeout_long_enough_finishes_the_safe_stop_behind_a_heat_wait(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake, config, server, job = in_a_heat_wait(bench, servers, tmp_path, 10, 60)
    assert server.stop(signal.SIGTERM) == 0
    assert targets(fake) == {"T": 0.0, "B": 0.0}
    restarted = servers({}, "--config", str(config))
    with restarted.client() as client:
        assert job_state(client, job)["safe_stop"] is None


def put_in(state: str, client: httpx.Client, fake: BuiltInFake) -> int | None:
    """The printer brought to ``state``; its job's number, if one."""
    if state == "idle":
        return None
    if state == "held":
        job = queue(client, HEATING + "G1 X5 F600\n")
        wait_for(lambda: job_state(client, job)["state"] == "completed", what="the job")
        return job
    job = queue(client, HEATING + MOVES)
    wait_for(lambda: ran(fake, "G1 X20 F600"), what="the moves")
    if state == "paused":
        assert client.post("/v1/printers/bench/pause").status_code == 204
        wait_for(lambda: job_state(client, job)["state"] == "paused", what="the pause")
    elif state == "owing, offline":  # the link lost mid-job, and not back
        # The fake answers no request while its pty is away: none goes till it is back.
        assert fake.request(f"link_drop {OFFLINE}")["ok"]
        wait_for(lambda: printer(client)["state"] != "printing", what="the lost link")
    return job


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL], ids=lambda s: s.name)
@pytest.mark.parametrize("state", ["idle", "held", "printing", "paused", "owing, offline"])
@pytest.mark.slow
def test_a_restart_in_every_state_keeps_the_hold_and_the_owed_stop(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    state: str,
    signum: signal.Signals,
) -> None:
    fake = bench(*TWO_HOTENDS, "--move-time", "0.01")
    config = server_config(tmp_path, bench={"port": fake.port})
    server = servers({}, "--config", str(config), "--stop-timeout", "3").wait_ready("bench")
    with server.client() as client:
        job = put_in(state, client, fake)
    code = server.stop(signum)
    if signum == signal.SIGTERM:  # 75 only when the stop was left owed
        assert code == (EXIT_SAFE_STOP_OWED if state == "owing, offline" else 0), code
    restarted = servers({}, "--config", str(config))
    with restarted.client() as client:
        if state == "owing, offline":  # its port is back (the symlink made again)
            wait_for(lambda: Path(fake.port).exists(), OFFLINE + 10, "the port back")
            time.sleep(0.5)
        if state in ("printing", "paused", "owing, offline"):  # every heater off, once it can
            wait_for(lambda: targets(fake) == ALL_OFF, 60, f"heaters off: {targets(fake)}")
        if job is not None:
            record = wait_for(
                lambda: (found := job_state(client, job))["safe_stop"] != "owed" and found,
                what="the record's safe stop",
            )
            assert record["state"] == ("completed" if state == "held" else "interrupted")
        restarted.wait_ready("bench")
        after = printer(client)
        assert after["held"] is (state != "idle"), after  # a part may be on the bed
        before = len(executed(fake.log_path))
        time.sleep(1.5)  # nothing starts, nothing is sent again
        fake.request("status")  # the log is flushed before the answer
        assert not [c for c in executed(fake.log_path)[before:] if c.startswith("G")]
