"""An emergency stop during a print (issue 48), from each face that can send one: it goes
whatever surrounds it, no job line follows it, and the safe stop's heater-off lines follow
it once the controller answers again. What a controller's own M112 does is its own: the
Marlin fake halts (heaters off) until a reset; the Hyrel fake drops what it holds and keeps
its heaters, as nothing in Hyrel's documents says otherwise. Read at the fake."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.gcode.heaters import turns_off
from tests.support.helpers import TWO_HOTENDS, executed
from tests.support.helpers import heater_targets as targets
from tests.support.server import Server, job_state, server_config, wait_for

pytestmark = pytest.mark.timeout(120)
HEATING = "M140 S60\nM104 T0 S200\nM104 T1 S210\nT1\n"
MOVES = "".join(f"G1 X{i % 50} F600\n" for i in range(3000))
ALL_OFF = {"T": 0.0, "T1": 0.0, "B": 0.0}
GREETING = {"M110 N0", "M105", "M115", "M155 S2", "M108"}  # the host's own lines


def ran(fake: BuiltInFake) -> list[str]:
    fake.request("status")  # the log is flushed before the answer
    return executed(fake.log_path)


def emergency(client: httpx.Client, how: str) -> None:
    if how == "moonraker":
        answer = client.post("/printer/emergency_stop")
    elif how == "moonraker script":  # the M112 between two lines a print refuses
        answer = client.post("/printer/gcode/script", json={"script": "G1 X1\nM112\nM104 S0"})
    else:  # OctoPrint's commands, the M112 after a line a print refuses
        answer = client.post("/api/printer/command", json={"commands": ["G1 X1", "M112"]})
    assert answer.status_code in (200, 204), answer.text


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.parametrize("how", ["moonraker", "moonraker script", "octoprint commands"])
@pytest.mark.slow
def test_an_emergency_stop_goes_and_the_heater_off_lines_follow_it(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    protocol: str,
    how: str,
) -> None:
    fake = bench("--protocol", protocol, *TWO_HOTENDS, "--move-time", "0.01")
    config = server_config(tmp_path, bench={"port": fake.port, "protocol": protocol})
    server = servers({}, "--config", str(config)).wait_ready("bench")
    with server.client() as client:
        job = client.post("/v1/printers/bench/jobs", files={"file": ("two.gcode", HEATING + MOVES)})
        assert job.status_code == 201, job.text
        wait_for(lambda: "G1 X20 F600" in ran(fake), what="the moves")
        emergency(client, how)
        record = wait_for(
            lambda: (found := job_state(client, job.json()["id"]))["state"] != "printing" and found,
            what="the job's end",
        )
        if protocol == "reprap":
            assert fake.request("reset")["ok"]  # a halted Marlin answers again once reset
        # Hyrel's safe stop turns every head and bed off by its group address.
        offs = {"M104 T47 S0", "M140 T46 S0"} if protocol == "hyrel" else {"M104 T1 S0", "M140 S0"}
        wait_for(lambda: offs <= set(ran(fake)[-20:]), what=f"{offs} after the M112")
        assert targets(fake) == ALL_OFF
        done = ran(fake)
    assert "emergency stop" in record["error"], record
    assert "heaters off)" not in record["error"]  # not said: not known of every controller
    after = done[done.index("M112") + 1 :]
    assert not [line for line in after if line.startswith("G")], after  # no move after it
    assert all(turns_off(line) or line in GREETING for line in after), after
