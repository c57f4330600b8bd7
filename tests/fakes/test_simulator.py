"""The simulated controller: slots, planner, unbuffered waits, buffer overflow."""

import pytest

from repetrel_host.fakes.settings import ControllerSettings, Overflow
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.protocol.framing import frame
from tests.support.simulated import started, wire


def test_buffered_moves_are_acknowledged_when_planned_not_when_done() -> None:
    sim = started(ControllerSettings(move_time=1.0, planner=16))
    sim.receive(wire("G1 X1", "G1 X2", "G1 X3"), 0.0)
    sim.advance(0.0)
    assert sim.take_output(0.0) == b"ok\nok\nok\n"
    assert sim.executed == ["M110 N0", "G1 X1", "G1 X2", "G1 X3"]


def test_full_planner_holds_the_acknowledgement_back() -> None:
    sim = started(ControllerSettings(move_time=1.0, planner=2))
    sim.receive(wire("G1 X1", "G1 X2", "G1 X3"), 0.0)
    sim.advance(0.0)
    assert sim.take_output(0.0) == b"ok\nok\n"
    assert sim.next_wakeup() == 1.0
    sim.advance(1.0)
    assert sim.take_output(1.0) == b"ok\n"


def test_unbuffered_command_waits_for_the_planner_to_drain() -> None:
    sim = started(ControllerSettings(move_time=0.5))
    sim.receive(wire("G1 X1", "G1 X2", "G4 P250", "M105"), 0.0)
    sim.advance(0.0)
    assert sim.take_output(0.0) == b"ok\nok\n"
    sim.advance(0.99)
    assert sim.take_output(0.99) == b""
    sim.advance(1.25)  # moves end at 1.0, the dwell lasts 0.25 s
    assert sim.take_output(1.25) == b"ok\nok T:21.00 /0.00 B:21.00 /0.00 @:0 B@:0\n"
    assert sim.executed[-2:] == ["G4 P250", "M105"]


def test_latency_and_bandwidth_delay_replies() -> None:
    sim = ControllerSimulator(ControllerSettings(latency=0.01, bandwidth=1000.0, banner=False))
    line = frame(0, "M110 N0")  # 16 bytes: 16 ms on the wire
    sim.receive(line, 0.0)
    sim.advance(0.025)
    assert sim.take_output(0.025) == b""
    sim.advance(0.026)  # arrives at 0.026, "ok\n" takes 3 ms and 10 ms back
    sim.advance(0.039)
    assert sim.take_output(0.039) == b"ok\n"


def test_uart_drops_bytes_that_do_not_fit() -> None:
    sim = started(ControllerSettings(rx_buffer=32, slots=1, planner=1, move_time=1.0))
    # The first move is planned, the second waits in the one slot, the rest queue
    # in 31 bytes of buffer: of 4 lines of 12 bytes, 17 bytes do not fit.
    data = wire("G1 X1", "G1 X2", "G1 X3", "G1 X4", "G1 X5", "G1 X6")
    sim.receive(data, 0.0)
    sim.advance(0.0)
    assert sim.link.bytes_dropped == 17


def test_usb_back_pressure_reports_room() -> None:
    sim = started(ControllerSettings(rx_buffer=32, overflow=Overflow.BLOCK, slots=1))
    assert sim.room() == 31
    sim.receive(b"N1 G28*18\n", 0.0)
    assert sim.room() == 21
    sim.advance(0.0)
    assert sim.link.peak_rx_buffer == 15  # the M110 line, the longest so far


def test_counters_measure_peak_buffer_and_starvation() -> None:
    sim = started(ControllerSettings(move_time=0.010, planner=16))
    sim.receive(wire("G1 X1", "G1 X2"), 0.0)  # 20 ms of moves, planned at once
    sim.advance(0.0)
    sim.receive(wire("G1 X3", first=3), 0.015)  # in time: the planner still has 5 ms
    sim.advance(0.015)
    sim.receive(wire("G1 X4", first=4), 0.050)  # late: idle from 0.030 to 0.050
    sim.advance(0.050)
    link = sim.link
    assert link.commands == 5  # the M110 and four moves
    assert link.starved == pytest.approx(0.020)
    assert link.peak_rx_buffer == 15  # lines are read out as they land; M110's is longest
    assert link.bytes_dropped == 0


def test_time_before_the_first_command_is_not_starvation() -> None:
    sim = ControllerSimulator(ControllerSettings())
    sim.receive(frame(0, "M110 N0"), 5.0)
    sim.advance(5.0)
    assert sim.link.starved == 0.0
    assert sim.link.first_command_at == 5.0


def test_advanced_ok_reports_last_line_planner_and_slots() -> None:
    settings = ControllerSettings(move_time=1.0, planner=2, slots=4, advanced_ok=True)
    sim = ControllerSimulator(settings)
    sim.receive(frame(0, "M110 N0") + wire("G1 X1", "G1 X2", "G1 X3"), 0.0)
    sim.advance(0.0)
    # The third move waits for a planner block, holding a slot: its ok comes later.
    assert sim.take_output(0.0) == b"start\nok N0 P2 B4\nok N1 P1 B4\nok N2 P0 B4\n"
    sim.advance(1.0)
    assert sim.take_output(1.0) == b"ok N3 P0 B4\n"
