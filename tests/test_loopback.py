"""Host against the simulated controller in memory: exactly once, in order, on simulated time."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from repetrel_host.protocol.host import FlowControl, FlowMode
from repetrel_host.testing.loopback import run_loopback
from repetrel_host.testing.simulator import ControllerSettings

UART = ControllerSettings(bandwidth=11_520, latency=0.002, rx_buffer=128)


@pytest.mark.parametrize("mode", list(FlowMode))
def test_slicer_job_is_executed_exactly_once(mode: FlowMode, cone_commands: list[str]) -> None:
    result = run_loopback(cone_commands, FlowControl(mode), UART)
    assert result.failure is None
    assert result.executed == cone_commands
    assert result.acknowledged == list(range(len(cone_commands)))
    assert result.controller.bytes_dropped == 0


@pytest.mark.parametrize("mode", list(FlowMode))
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_corrupted_lines_are_resent_never_repeated(
    mode: FlowMode, seed: int, cone_commands: list[str]
) -> None:
    commands = cone_commands[:5000]
    result = run_loopback(commands, FlowControl(mode), UART, corruption=0.03, seed=seed)
    assert result.failure is None
    assert result.executed == commands
    assert result.host.stats.resend_requests > 50


def test_buffered_mode_fills_the_wire() -> None:
    commands = [f"G1 X{i % 200}.5 Y{i % 150}.25 E{i}.125" for i in range(3000)]
    result = run_loopback(commands, FlowControl(FlowMode.BUFFERED), UART)
    wire_seconds = result.host.stats.bytes_sent / 11_520
    assert result.executed == commands
    # Character counting keeps the wire busy: within 5 % of the time the bytes need.
    assert result.seconds < wire_seconds * 1.05
    unbuffered = run_loopback(commands, FlowControl(FlowMode.UNBUFFERED), UART)
    assert unbuffered.seconds > result.seconds * 1.2


def test_long_jobs_renumber_without_losing_a_line() -> None:
    commands = [f"G1 X{i}" for i in range(1000)]
    result = run_loopback(
        commands, FlowControl(), UART, line_number_limit=97, corruption=0.02, seed=5
    )
    assert result.failure is None
    assert result.executed == commands
    m110 = [c for c in result.controller.executed if c.startswith("M110")]
    assert len(m110) >= 1000 // 97


def test_small_buffer_with_slow_moves_never_overflows() -> None:
    settings = ControllerSettings(
        bandwidth=11_520, latency=0.002, rx_buffer=64, slots=2, planner=4, move_time=0.01
    )
    commands = [f"G1 X{i} Y{i}" for i in range(500)] + ["M400", "G4 P10", "M105"]
    result = run_loopback(commands, FlowControl(FlowMode.BUFFERED, rx_buffer=64), settings)
    assert result.executed == commands
    assert result.controller.bytes_dropped == 0


@settings(max_examples=40, deadline=None)
@given(
    commands=st.lists(
        st.sampled_from(["G1 X1 Y2 E3", "G28", "M105", "G4 P1", "G92 E0", "M400", "T1"]),
        min_size=1,
        max_size=120,
    ),
    mode=st.sampled_from(list(FlowMode)),
    corruption=st.sampled_from([0.0, 0.01, 0.1, 0.3]),
    seed=st.integers(0, 2**16),
    rx_buffer=st.integers(40, 256),
    limit=st.integers(5, 500),
)
def test_any_job_under_corruption_is_executed_exactly_once(
    commands: list[str], mode: FlowMode, corruption: float, seed: int, rx_buffer: int, limit: int
) -> None:
    settings_ = ControllerSettings(latency=0.001, rx_buffer=rx_buffer, bandwidth=20_000)
    result = run_loopback(
        commands,
        FlowControl(mode, rx_buffer=rx_buffer),
        settings_,
        corruption=corruption,
        seed=seed,
        line_number_limit=limit,
    )
    assert result.failure is None
    assert result.executed == commands
