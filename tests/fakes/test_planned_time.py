"""The fake whose moves take their planned time (``time_scale``): a job's simulated time is
its estimate divided by the scale, on both dialects, and the fake never waits forever for
a move's time."""

from __future__ import annotations

import os
import select
import subprocess
import sys
import time
import tty
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.settings import ControllerSettings, Overflow
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.gcode.estimate import DEFAULT_LIMITS, Estimator
from repetrel_host.protocol.hyrel import Control, HostReceiver, frame

CONE = Path(__file__).resolve().parents[1] / "data" / "cone-prusaslicer.gcode"
# Four 100 mm sides at 100 mm/s (Marlin's defaults: 3000 mm/s², 10 mm/s jerk). Each corner
# is a right angle, so each side starts and ends at the jerk's 10 mm/s: 0.03 s to reach
# 100 mm/s over 1.65 mm, 96.7 mm at 100 mm/s (0.967 s), 0.03 s to slow down: 1.027 s.
SQUARE = ["G1 X100 F6000", "G1 Y100", "G1 X0", "G1 Y0"]
SQUARE_SECONDS = 4 * 1.027


def settings(scale: float) -> ControllerSettings:
    return ControllerSettings(
        time_scale=scale, overflow=Overflow.BLOCK, rx_buffer=256, banner=False
    )


class Host:
    """Writes lines as the receive buffer has room for them, and notes when each reply came,
    on the simulator's clock."""

    def __init__(self, controller: ControllerSimulator) -> None:
        self.controller = controller
        self.wire = bytearray()
        self.now = 0.0
        self.replies: list[tuple[float, bytes]] = []

    def send(self, *commands: str) -> None:
        self.wire += b"".join(command.encode() + b"\n" for command in commands)

    def run(self, until: float | None = None) -> None:
        """Until ``until``, or until nothing more happens (and nothing more can be written)."""
        controller = self.controller
        while True:
            controller.receive_from(self.wire, self.now)
            controller.advance(self.now)
            output = controller.take_output(self.now)
            self.replies += [(self.now, line) for line in output.splitlines()]
            if self.wire and controller.room() > 0:
                continue
            wakeup = controller.next_wakeup()
            if wakeup is None or (until is not None and wakeup > until):
                break
            self.now = max(self.now, wakeup)
        if until is not None:
            self.now = until
            controller.advance(until)

    def ok_times(self) -> list[float]:
        return [at for at, line in self.replies if line.startswith(b"ok")]


def stream(commands: list[str], scale: float) -> list[float]:
    """When each command's ok came, streamed to a fake at ``scale``."""
    host = Host(ControllerSimulator(settings(scale)))
    host.send(*commands)
    host.run()
    return host.ok_times()


def test_a_square_takes_its_trapezoids_time_divided_by_the_scale() -> None:
    oks = stream([*SQUARE, "M400"], 100.0)
    assert oks[:4] == [0.0] * 4  # each move answered as it is planned, as before
    assert oks[4] == pytest.approx(SQUARE_SECONDS / 100, abs=1e-9)  # M400: when moves end
    assert stream([*SQUARE, "M400"], 50.0)[4] == pytest.approx(SQUARE_SECONDS / 50, abs=1e-9)


def test_moves_in_line_run_on_without_stopping_between() -> None:
    # The planner looks ahead: the second move is entered at full speed, 100 mm/s from
    # 1.65 mm in to 1.65 mm before the end: 0.03 + 1.9670 + 0.03 s.
    oks = stream(["G1 X100 F6000", "G1 X200", "M400"], 100.0)
    assert oks[2] == pytest.approx(2.027 / 100, abs=1e-9)


def test_moves_stop_before_a_command_that_waits_for_them() -> None:
    # The move after M400 is in the queue before the first ends, but the firmware stops
    # for M400: the first move slows to the jerk's speed, 1.027 s, not 1.0135 s as when
    # it runs on into the next.
    oks = stream(["G1 X100 F6000", "M400", "G1 X200", "M400"], 100.0)
    assert oks[1] == pytest.approx(1.027 / 100, abs=1e-9)


def test_the_planner_limits_are_the_settings_then_the_jobs_own() -> None:
    slow = replace(DEFAULT_LIMITS, max_feedrate={**DEFAULT_LIMITS.max_feedrate, "X": 50.0})
    host = Host(ControllerSimulator(replace(settings(100.0), limits=slow)))
    host.send("G1 X100 F6000", "M400", "M203 X25", "G1 X0", "M400")
    host.run()
    # 100 mm/s asked, 50 allowed: from the jerk's 10 mm/s to 50 in 0.0133 s over 0.4 mm,
    # each way, and 99.2 mm at 50 mm/s. Then 25 allowed: 10 to 25 in 0.005 s over
    # 0.0875 mm each way, and 99.825 mm at 25 mm/s.
    first, second = host.ok_times()[1], host.ok_times()[4]
    assert first == pytest.approx((2 * 40 / 3000 + 99.2 / 50) / 100, abs=1e-9)
    assert second - first == pytest.approx((2 * 15 / 3000 + 99.825 / 25) / 100, abs=1e-9)


def test_a_dwell_is_part_of_the_plan_and_scaled() -> None:
    oks = stream(["G1 X100 F6000", "G4 P500", "M400"], 100.0)
    assert oks[1] == pytest.approx((1.027 + 0.5) / 100, abs=1e-9)  # G4 answered as it ends


def cone_commands(count: int) -> list[str]:
    commands = []
    with CONE.open(encoding="utf-8") as file:
        for line in file:
            command = line.split(";", 1)[0].strip()
            if command:
                commands.append(command)
            if len(commands) == count:
                break
    return commands


def test_a_sliced_file_takes_its_estimate_divided_by_the_scale() -> None:
    commands = cone_commands(3000)
    estimator = Estimator()  # Marlin's defaults, as the fake's; the file sets no M201-M205
    for number, command in enumerate(commands):
        estimator.feed(number, command)
    planned = estimator.finish().moving  # the fake times its heat wait itself (at once here)
    assert planned > 100  # thousands of short moves, not a handful
    at_100 = stream([*commands, "M400"], 100.0)
    assert len(at_100) == len(commands) + 1
    # Not to the millisecond: the estimate looks 64 moves ahead, the fake only over what
    # its planner holds (16 blocks), so it may slow a move for a corner it cannot yet see
    # past (here it comes within 0.01 %).
    assert at_100[-1] * 100 == pytest.approx(planned, rel=0.01)
    at_50 = stream([*commands, "M400"], 50.0)
    assert at_50[-1] == pytest.approx(2 * at_100[-1], rel=1e-9)


@pytest.mark.parametrize("commands", [["G1 X100 F6000"], SQUARE], ids=["one move", "ends on moves"])
def test_moves_at_the_end_of_a_stream_still_run(commands: list[str]) -> None:
    host = Host(ControllerSimulator(settings(100.0)))
    host.send(*commands)
    host.run()
    assert len(host.ok_times()) == len(commands)
    host.run(until=1.0)  # long after the moves' planned time
    host.send("M400")
    host.run()
    # Answered at once: the moves ran without anything after them to settle their plan.
    assert host.ok_times()[-1] == 1.0


def test_a_pause_after_moves_waits_for_them() -> None:
    oks = stream([*SQUARE, "M0"], 100.0)
    assert oks[4] == pytest.approx(SQUARE_SECONDS / 100, abs=1e-9)


def hyrel_host(scale: float) -> Host:
    return Host(
        HyrelControllerSimulator(ControllerSettings(time_scale=scale, rx_buffer=8192, banner=False))
    )


def notices(host: Host, notice: bytes) -> list[float]:
    return [at for at, line in host.replies if line.endswith(notice)]


def test_hyrels_link_runs_moves_in_their_planned_time() -> None:
    host = hyrel_host(100.0)
    host.wire += b"".join(frame(command) for command in [*SQUARE, "M0"])
    host.run()
    # M0 waits for the moves to end, then says so.
    assert notices(host, b">MC:M0:") == [pytest.approx(SQUARE_SECONDS / 100, abs=1e-9)]


def test_hyrels_pause_byte_does_not_hold_the_moves_planned_before_it() -> None:
    host = hyrel_host(100.0)
    host.wire += b"".join(frame(command) for command in SQUARE) + bytes([Control.PAUSE_AT_MOVE_END])
    host.run(until=1.0)
    host.wire += bytes([Control.END_WAIT]) + frame("M109 S0")
    host.run()
    # Its notice comes as it runs: at once, the planner long empty.
    assert notices(host, b">MC:M109: S0:") == [1.0]


def test_time_scale_is_refused_below_zero_and_with_a_move_time() -> None:
    with pytest.raises(ValueError, match="time_scale must be above zero"):
        ControllerSettings(time_scale=0.0)
    with pytest.raises(ValueError, match="give one"):
        ControllerSettings(time_scale=10.0, move_time=0.01)


def read_until(port: int, done: Callable[[bytes], bool], seconds: float) -> bytes:
    received = b""
    deadline = time.monotonic() + seconds
    while not done(received) and time.monotonic() < deadline:
        if select.select([port], [], [], 0.2)[0]:
            received += os.read(port, 4096)
    return received


@pytest.mark.timeout(60)
@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_the_command_line_fake_runs_moves_in_their_planned_time(protocol: str) -> None:
    arguments = ["--time-scale", "10", "--protocol", protocol]
    with BuiltInFake(None, arguments) as fake:
        port = os.open(fake.port, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(port)
            sent = time.monotonic()
            if protocol == "hyrel":
                receiver = HostReceiver()
                os.write(port, b"".join(frame(command) for command in [*SQUARE, "M0"]))
                received = read_until(port, lambda got: b">MC:M0:" in got, 30)
                assert receiver.feed(received) == [">MC:M0:"]
            else:
                os.write(port, b"".join(f"{c}\n".encode() for c in [*SQUARE, "M400"]))
                received = read_until(port, lambda got: got.count(b"ok") == 5, 30)
                # ("start" may have been said before the port was opened.)
                assert received.removeprefix(b"start\n") == b"ok\n" * 5
            elapsed = time.monotonic() - sent
        finally:
            os.close(port)
    assert elapsed >= SQUARE_SECONDS / 10  # never sooner than the plan (later on a slow host)


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    ("arguments", "sentence"),
    [
        (["--time-scale", "100", "--move-time", "0.01"], "each say how long a move takes"),
        (["--time-scale", "0"], "--time-scale must be above zero"),
    ],
)
def test_the_command_line_refuses_a_bad_time_scale(arguments: list[str], sentence: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "repetrel_host.fakes.fake_controller", *arguments],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert result.returncode != 0
    assert sentence in result.stderr and "Traceback" not in result.stderr
