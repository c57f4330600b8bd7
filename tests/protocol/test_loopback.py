"""Host against the simulated controller in memory, on simulated time: exactly once, in order."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.protocol.events import FailureKind, ProbeKind
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.session.loopback import (
    NOISE_COMMANDS,
    NOISE_FAULTS,
    NOISE_RATES,
    run_loopback,
    run_noise_case,
    run_noisy_job,
    wire_preview,
)

UART = ControllerSettings(bandwidth=11_520, latency=0.002, rx_buffer=128)
NOISE = "corrupt=0.02 garble=0.01 drop_ok=0.01 duplicate_ok=0.01 spurious_resend=0.005"
# NOISE alone is on Marlin 2.1's ways; these are another firmware's.
MARLIN = " flush_on_error=0 drop_duplicates=0 resend_without_ok=1"


def noisy(faults: str, seed: int) -> ControllerSettings:
    return ControllerSettings(latency=0.001, faults=Faults.parse(f"{faults} seed={seed}"))


@pytest.mark.parametrize("mode", list(FlowMode))
def test_slicer_job_is_executed_exactly_once(mode: FlowMode, cone_commands: list[str]) -> None:
    result = run_loopback(cone_commands, FlowControl(mode), UART)
    assert result.failure is None
    assert result.executed == cone_commands
    assert result.acknowledged == list(range(len(cone_commands)))
    assert result.controller.link.bytes_dropped == 0


@pytest.mark.parametrize("mode", list(FlowMode))
@pytest.mark.parametrize(("faults", "seed"), [(NOISE, 1), (NOISE, 2), (NOISE + MARLIN, 3)])
@pytest.mark.slow
def test_noise_never_loses_or_repeats_a_line(
    mode: FlowMode, faults: str, seed: int, cone_commands: list[str]
) -> None:
    result = run_loopback(cone_commands, FlowControl(mode), noisy(faults, seed))
    assert result.failure is None
    assert result.executed == cone_commands
    counts = result.controller.counts
    assert counts.corrupted_lines > 100 and counts.dropped_oks > 50 and counts.garbled_replies > 50
    assert sorted(set(result.acknowledged)) == list(range(len(cone_commands)))


def test_buffered_mode_fills_the_wire() -> None:
    commands = [f"G1 X{i % 200}.5 Y{i % 150}.25 E{i}.125" for i in range(3000)]
    result = run_loopback(commands, FlowControl(FlowMode.BUFFERED), UART)
    wire_seconds = result.host.stats.bytes_sent / 11_520
    assert result.executed == commands
    # Character counting keeps the wire busy: within 5 % of the time the bytes need.
    assert result.seconds < wire_seconds * 1.05
    unbuffered = run_loopback(commands, FlowControl(FlowMode.UNBUFFERED), UART)
    assert unbuffered.seconds > result.seconds  # several lines in flight beat one


def test_long_jobs_renumber_without_losing_a_line() -> None:
    commands = [f"G1 X{i}" for i in range(1000)]
    result = run_loopback(commands, FlowControl(), noisy(NOISE, 5), line_number_limit=97)
    assert result.failure is None
    assert result.executed == commands
    m110 = [c for c in result.controller.executed if c.startswith("M110")]
    assert len(m110) >= 1000 // 97


def test_small_buffer_with_slow_moves_never_overflows() -> None:
    settings_ = ControllerSettings(
        bandwidth=11_520, latency=0.002, rx_buffer=64, slots=2, planner=4, move_time=0.01
    )
    commands = [f"G1 X{i} Y{i}" for i in range(500)] + ["M400", "G4 P10", "M105"]
    result = run_loopback(commands, FlowControl(FlowMode.BUFFERED, rx_buffer=64), settings_)
    assert result.executed == commands
    assert result.controller.link.bytes_dropped == 0


def test_a_reset_mid_job_stops_within_one_reply() -> None:
    commands = [f"G1 X{i}" for i in range(100)]
    commands[40] = "!!DEBUG:reset"
    result = run_loopback(commands, FlowControl(), noisy("", 0))
    assert result.failure is not None and "reset" in result.failure.reason
    # Nothing is resent across the reset: the controller ran each line once, then stopped.
    assert result.executed == commands[:40]
    assert result.host.stats.bytes_sent < 60 * 16


def test_a_silent_controller_fails_with_a_timeout() -> None:
    commands = ["G28", "G1 X1", "!!DEBUG:hang", "G1 X2", "G1 X3"]
    result = run_loopback(commands, FlowControl(), noisy("", 0))
    assert result.failure is not None and result.failure.kind is FailureKind.TIMEOUT
    assert result.executed == commands[:2]


def test_the_framed_preview_is_the_clean_wire() -> None:
    wire = b"".join(wire_preview(["G28", "G1 X1"]))
    # The greeting: M110 and a probe behind it (a real M105, its "ok T:..." the answer),
    # the job, and the two probes that confirm it (one answer said twice cannot pass for
    # both). XOR checksums worked by hand: "N1 M105" is 0x4E^0x31^0x20^0x4D^0x31^0x30^0x35.
    assert wire == (b"N0 M110 N0*125\nN1 M105*38\nN2 G28*17\nN3 G1 X1*98\nN4 M105*35\nN5 M105*34\n")


@pytest.mark.parametrize("case", [1171, 1229, 1276, 3003])
def test_refusals_queued_behind_a_slow_reply_link_end(case: int) -> None:
    """Jobs drawn as ``bench/noise_loops.py`` draws its case ``case`` (buffered, 15 % of
    oks said twice, a 20 kB/s link on which each refusal takes 3.5 ms to come back). The
    refusals of lines sent before a resend queue up behind each other; those of the line
    asked for (not only of the last line sent again) within a round trip are older answers,
    and each ignored one is an echo counted off. They used to end in "asked for line N 10
    times in a row", or in a silence once the request after the echoes went unheard."""
    commands, result = run_noise_case(case)
    assert result.failure is None
    assert result.executed == commands
    assert result.host.is_done


@settings(max_examples=60, deadline=None)
@given(
    commands=st.lists(st.sampled_from(NOISE_COMMANDS), min_size=1, max_size=150),
    mode=st.sampled_from(list(FlowMode)),
    rates=st.lists(
        st.sampled_from(NOISE_RATES), min_size=len(NOISE_FAULTS), max_size=len(NOISE_FAULTS)
    ),
    marlin=st.tuples(st.booleans(), st.booleans(), st.booleans()),
    seed=st.integers(0, 2**16),
    rx_buffer=st.integers(40, 256),
    limit=st.integers(5, 500),
)
def test_any_job_under_any_faults_is_executed_exactly_once(
    commands: list[str],
    mode: FlowMode,
    rates: list[float],
    marlin: tuple[bool, bool, bool],
    seed: int,
    rx_buffer: int,
    limit: int,
) -> None:
    result = run_noisy_job(commands, mode, rates, marlin, seed, rx_buffer, limit)
    assert result.failure is None
    assert result.executed == commands
    assert result.host.is_done


def test_advanced_ok_fills_the_command_slots_without_overflow() -> None:
    commands = [f"G1 X{i} Y{i}" for i in range(300)]
    peak_slots = {}
    for advanced in (False, True):
        controller = ControllerSettings(
            bandwidth=11_520, slots=16, planner=1, move_time=0.002, advanced_ok=advanced
        )
        result = run_loopback(commands, FlowControl(max_lines=8), controller)
        assert result.executed == commands
        assert result.controller.link.bytes_dropped == 0
        peak_slots[advanced] = result.controller.link.peak_slots
    # Counting oks alone, lines waiting in the slots count against the 8 in flight;
    # with the controller's N they do not, and its 16 slots fill up.
    assert peak_slots[False] <= 8
    assert peak_slots[True] == 16
    one_at_a_time = run_loopback(commands, FlowControl(FlowMode.UNBUFFERED), controller)
    assert one_at_a_time.executed == commands
    assert one_at_a_time.controller.link.peak_slots == 1  # unbuffered stays one line


@pytest.mark.parametrize("mode", list(FlowMode))
def test_advanced_ok_under_noise_never_loses_or_repeats_a_line(
    mode: FlowMode, cone_commands: list[str]
) -> None:
    controller = ControllerSettings(
        latency=0.001, advanced_ok=True, faults=Faults.parse(f"{NOISE + MARLIN} seed=4")
    )
    result = run_loopback(cone_commands, FlowControl(mode), controller)
    assert result.failure is None
    assert result.executed == cone_commands


OCTOPRINT = "counted_resend=1 spurious_resend=0.005 drop_with_error=0.005"


@pytest.mark.parametrize("mode", list(FlowMode))
def test_a_controller_counting_lines_its_own_way_runs_every_line_once(
    mode: FlowMode, cone_commands: list[str]
) -> None:
    result = run_loopback(cone_commands, FlowControl(mode), noisy(OCTOPRINT, 6))
    assert result.failure is None
    assert result.host.probe is ProbeKind.COMMAND
    assert result.executed == cone_commands
    probes = result.controller.executed.count("M105")  # the job has none
    assert 0 < probes <= result.host.stats.pings


@pytest.mark.parametrize("mode", list(FlowMode))
def test_with_the_usual_probe_such_a_controller_ends_in_one_sentence_never_a_repeat(
    mode: FlowMode, cone_commands: list[str]
) -> None:
    result = run_loopback(
        cone_commands, FlowControl(mode), noisy(OCTOPRINT, 6), probe=ProbeKind.CHECKSUM
    )
    assert result.failure is not None and result.failure.kind is FailureKind.PROTOCOL
    assert "which the host never sent" in result.failure.reason
    assert result.executed == cone_commands[: len(result.executed)]


@pytest.mark.parametrize("mode", list(FlowMode))
def test_lines_dropped_with_only_an_error_are_sent_again(
    mode: FlowMode, cone_commands: list[str]
) -> None:
    result = run_loopback(
        cone_commands, FlowControl(mode), noisy(f"{NOISE}{MARLIN} drop_with_error=0.005", 7)
    )
    assert result.failure is None
    assert result.executed == cone_commands
    assert result.controller.counts.dropped_with_error > 50
