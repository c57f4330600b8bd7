"""The host's side of Hyrel's link against the simulated Hyrel controller, on simulated time."""

from __future__ import annotations

from typing import Any

import pytest

from repetrel_host.protocol.dialects.hyrel import (
    ACK_GRACE,
    KEEPALIVE,
    STATUS_AFTER,
    HyrelDialect,
)
from repetrel_host.protocol.events import ControllerReady, Failed, FailureKind, LineAcknowledged
from repetrel_host.protocol.flow import FlowControl
from repetrel_host.pump import Outcome
from repetrel_host.testing.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.testing.loopback import LoopbackResult, run_loopback
from repetrel_host.testing.simulator import ControllerSettings, ControllerSimulator

# The controller's headroom, not its buffer: it ACKs while 2 KB of its 8 KB are free.
HYREL_WINDOW = FlowControl(rx_buffer=2048, max_lines=256)


def stream(commands: list[str], **settings: Any) -> LoopbackResult:
    controller_settings = ControllerSettings(rx_buffer=8192, banner=False, **settings)
    return run_loopback(
        commands,
        dialect=HyrelDialect(HYREL_WINDOW),
        controller=HyrelControllerSimulator(controller_settings),
    )


def test_a_job_streams_exactly_once_within_the_controllers_headroom() -> None:
    commands = [f"G1 X{i % 200} Y{i % 7}" for i in range(5000)]
    result = stream(commands, move_time=0.002)
    assert result.failure is None and result.run.outcome is Outcome.COMPLETED
    assert result.executed == [*commands, "M115"]  # the M115 that confirmed the end
    link = result.controller.link
    assert link.bytes_dropped == 0
    assert result.acknowledged == list(range(5000))


def test_the_job_ends_once_the_controller_ran_it_not_when_it_was_received() -> None:
    commands = [f"G1 X{i}" for i in range(300)]
    result = stream(commands, move_time=0.05)
    summary = result.run.summary
    # Received in well under a second; processed (planned: the last 16 moves in the
    # planner) after 284 moves of 0.05 s.
    assert summary is not None and summary.seconds >= (300 - 16) * 0.05


def test_a_long_heat_up_keeps_the_link_alive_and_the_watchdog_quiet() -> None:
    commands = ["G28", "M109 S200", "G1 X1", "G4 S40", "M104 S0"]
    result = stream(commands, heat_rate=179 / 60)  # 60 s from 21 to 200 degrees
    controller = result.controller
    assert isinstance(controller, HyrelControllerSimulator)
    assert result.run.outcome is Outcome.COMPLETED and controller.watchdog_trips == 0
    summary = result.run.summary
    assert summary is not None and summary.seconds >= 100 > 3 * KEEPALIVE


def test_a_controller_that_never_answers_the_ping_fails_the_greeting() -> None:
    marlin = ControllerSimulator(ControllerSettings(banner=False))
    result = run_loopback(["G28"], dialect=HyrelDialect(HYREL_WINDOW), controller=marlin)
    assert result.failure is not None and result.failure.kind is FailureKind.TIMEOUT
    assert "no answer to 5 pings (0x07)" in result.failure.reason
    assert result.executed == []


def test_a_line_the_controller_refuses_fails_the_stream_naming_it() -> None:
    dialect = HyrelDialect(HYREL_WINDOW, checksum=True)
    dialect.start(0.0)
    assert dialect.data_to_send(0.0) == b"\x07"
    dialect.receive_data(b">Hy: Hydra_5.1\n", 0.0)
    assert isinstance(dialect.next_event(), ControllerReady)
    dialect.send("G28", "first")
    dialect.send("G1 X5", "second")
    assert dialect.data_to_send(0.0) == b"N1 G28*336\nN2 G1 X5*453\n"
    # Both received (ACKed on arrival); the controller reads line 2 out later, and refuses it.
    dialect.receive_data(b"\x06\x06>ER: checksum mismatch (line 2): not run\n", 0.1)
    assert dialect.next_event() == LineAcknowledged(1, "G28", "first", "")
    assert dialect.next_event() == LineAcknowledged(2, "G1 X5", "second", "")
    failed = dialect.next_event()
    assert isinstance(failed, Failed) and failed.kind is FailureKind.CONTROLLER
    assert failed.tag == "second"
    assert failed.reason == "the controller says: >ER: checksum mismatch (line 2): not run"


@pytest.mark.parametrize("quiet", [KEEPALIVE, 25.0])
def test_a_quiet_host_sends_the_watchdog_byte(quiet: float) -> None:
    dialect = HyrelDialect(HYREL_WINDOW)
    dialect.start(0.0)
    dialect.data_to_send(0.0)
    dialect.receive_data(b">Hy: Hydra\n", 0.0)
    deadline = dialect.next_deadline()
    assert deadline == KEEPALIVE
    dialect.handle_timeout(quiet)
    assert dialect.data_to_send(quiet) == b"\x0e"
    assert dialect.next_deadline() == quiet + KEEPALIVE


@pytest.mark.parametrize("checksum", [False, True])
def test_the_window_never_holds_more_than_the_headroom(checksum: bool) -> None:
    dialect = HyrelDialect(FlowControl(rx_buffer=100, max_lines=50), checksum=checksum)
    dialect.start(0.0)
    dialect.data_to_send(0.0)
    dialect.receive_data(b">Hy: Hydra\n", 0.0)
    for i in range(20):
        dialect.send(f"G1 X{i}.125")
    sent = dialect.data_to_send(0.0)
    assert 0 < len(sent) <= 99  # the byte limit: the buffer less one
    dialect.receive_data(b"\x06", 0.1)  # one line received: room for one more
    more = dialect.data_to_send(0.1)
    assert more.count(b"\n") == 1 and len(sent) - len(sent.split(b"\n")[0]) - 1 + len(more) <= 99


def test_a_jobs_own_m115_does_not_end_it_early() -> None:
    commands = ["G28", "M115", "G4 S20", "G1 X1", "M104 S0"]
    result = stream(commands)
    summary = result.run.summary
    assert result.executed == [*commands, "M115"] and summary is not None
    assert summary.seconds >= 20  # the dwell ran before the job was done


def test_an_ack_lost_on_the_way_does_not_hold_the_end_forever() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "one")
    dialect.send("G1 X2", "two")
    dialect.request_sync()
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 G1 X2\n"
    dialect.receive_data(b"\x06", 0.1)  # the other ACK was lost
    assert dialect.next_event() == LineAcknowledged(1, "G1 X1", "one", "")
    assert dialect.data_to_send(0.1) == b""  # the sync waits for every line's ACK...
    assert dialect.next_deadline() == pytest.approx(0.1 + STATUS_AFTER)
    dialect.handle_timeout(0.1 + STATUS_AFTER)  # ...or until one is overdue
    assert dialect.data_to_send(5.1) == b"\x05N3 M115\n"
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra_5 PROTOCOL_VERSION:1.0\n", 5.2)
    assert dialect.is_done and dialect.next_event() is None  # the answer is the host's own
    # Line 2 ran, so it was received: its ACK is taken as lost unless it comes soon (the
    # ACK that comes now is the sync's, by the order the controller sends them in).
    dialect.receive_data(b"\x06", 5.3)
    assert dialect.next_event() == LineAcknowledged(2, "G1 X2", "two", "")
    dialect.handle_timeout(5.2 + ACK_GRACE)
    assert dialect.stats.lost_acks == 1 and dialect.next_deadline() == 5.1 + KEEPALIVE


def test_lines_after_a_quiet_spell_get_their_full_time_before_a_status_request() -> None:
    dialect = greeted()
    dialect.handle_timeout(KEEPALIVE)
    assert dialect.data_to_send(KEEPALIVE) == b"\x0e"
    dialect.send("G28")
    assert dialect.data_to_send(19.9) == b"N1 G28\n"
    assert dialect.next_deadline() == pytest.approx(19.9 + STATUS_AFTER)


def greeted() -> HyrelDialect:
    dialect = HyrelDialect(HYREL_WINDOW)
    dialect.start(0.0)
    dialect.data_to_send(0.0)
    dialect.receive_data(b">Hy: Hydra\n", 0.0)
    assert isinstance(dialect.next_event(), ControllerReady)
    return dialect
