"""The fake behaves as Marlin 2.1 does (its queue.cpp, gcode.cpp and temperature.cpp, read for
this and written here in the project's words): what it answers, when, and what it drops.

Expected bytes are written by hand from Marlin's strings: ``Error:`` + the message +
``Last Line: <n>``, then ``Resend: <n + 1>`` and ``ok``; ``echo:busy: processing``; a
heat wait's `` T:... W:?``."""

from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.protocol.framing import frame
from tests.support.simulated import started, wire


def run(sim: ControllerSimulator, until: float, step: float = 0.05) -> bytes:
    """Everything the fake says up to ``until``, as a host reading all along would."""
    out, now = b"", 0.0
    while now < until:
        now = min(until, now + step)
        sim.advance(now)
        out += sim.take_output(now)
    return out


def test_a_line_error_is_answered_in_marlins_words_counted_and_empties_the_buffer() -> None:
    sim = started(ControllerSettings(move_time=1.0, planner=1, slots=1))
    # Line 3's checksum is wrong; lines 4 and 5 wait behind it in the receive buffer while
    # the controller is busy with lines 1 and 2.
    lines = wire("G1 X1", "G1 X2") + b"N3 G1 X3*99\n" + wire("G1 X4", "G1 X5", first=4)
    sim.receive(lines, 0.0)
    assert run(sim, 1.5) == b"ok\nok\nError:checksum mismatch, Last Line: 2\nResend: 3\nok\n"
    assert sim.executed == ["M110 N0", "G1 X1", "G1 X2"]  # 4 and 5 went with the buffer
    assert sim.link.errors == 1 and sim.counts.flushed_bytes == len(wire("G1 X4", "G1 X5", first=4))


def test_a_line_out_of_order_is_refused_and_a_copy_of_the_last_is_dropped_in_silence() -> None:
    sim = started(ControllerSettings())
    sim.receive(wire("G1 X1", "G1 X2"), 0.0)
    sim.receive(frame(2, "G1 X2") + frame(1, "G1 X1"), 0.0)  # copies: no reply at all
    sim.advance(0.0)
    assert sim.take_output(0.0) == b"ok\nok\n" and sim.link.errors == 0
    sim.receive(frame(5, "G1 X5"), 0.1)
    sim.advance(0.1)
    assert sim.take_output(0.1) == (
        b"Error:Line Number is not Last Line Number+1, Last Line: 2\nResend: 3\nok\n"
    )
    assert sim.link.errors == 1


def test_a_move_is_answered_once_the_planner_has_room_for_it() -> None:
    sim = started(ControllerSettings(move_time=1.0))
    sim.receive(wire(*(f"G1 X{i}" for i in range(20))), 0.0)
    sim.advance(0.0)
    # 16 planner blocks and 4 command slots: 16 oks at once, then one as each move ends.
    assert sim.take_output(0.0) == b"ok\n" * 16
    sim.advance(0.99)
    assert sim.take_output(0.99) == b""
    sim.advance(1.0)
    assert sim.take_output(1.0) == b"ok\n"


def test_a_command_that_holds_the_queue_says_busy_every_two_seconds() -> None:
    sim = started(ControllerSettings(move_time=1.0))
    # A dwell behind 3 s of moves: the queue is held from the moment it is read.
    sim.receive(wire("G1 X1", "G1 X2", "G1 X3", "G4 S4"), 0.0)
    said = run(sim, 7.5)
    assert said == b"ok\nok\nok\n" + b"echo:busy: processing\n" * 3 + b"ok\n"
    sim.receive(wire("M113 S1", first=5) + wire("G4 S3", first=6), 7.5)
    said = run(sim, 11.0)
    assert said.count(b"busy") == 2 and said.endswith(b"ok\n")  # every second now


def test_a_move_waiting_for_the_planner_says_busy_too() -> None:
    sim = started(ControllerSettings(move_time=3.0))
    sim.receive(wire(*(f"G1 X{i}" for i in range(17))), 0.0)
    said = run(sim, 3.5)
    assert said == b"ok\n" * 16 + b"echo:busy: processing\n" + b"ok\n"


def test_a_heat_wait_reports_every_second_and_says_no_busy() -> None:
    sim = started(ControllerSettings(heat_rate=10.0, residency=3.0))
    sim.receive(wire("M190 S41"), 0.0)  # 2 s to get there, then 3 s of residency
    said = run(sim, 5.2, step=0.01).decode()
    lines = said.splitlines()
    assert "busy" not in said and lines[-1] == "ok"
    reports = lines[:-1]
    assert len(reports) == 5 and all(line.startswith(" T:21.00 /0.00 B:") for line in reports)
    assert [line.split(" W:")[1] for line in reports] == ["?", "?", "3", "2", "1"]
    assert reports[0].split(" B:")[1].startswith("21.00 /41.00")


def test_a_heat_wait_lets_the_moves_before_it_run_on() -> None:
    sim = started(ControllerSettings(move_time=2.0, heat_rate=10.0))
    sim.receive(wire("G1 X1", "M109 S31"), 0.0)  # a second to heat, the move takes two
    said = run(sim, 1.5)
    assert said.count(b"ok\n") == 2  # the wait ended while the move still ran


def test_m410_drops_the_planned_moves_as_it_arrives() -> None:
    sim = started(ControllerSettings(move_time=10.0))
    sim.receive(wire(*(f"G1 X{i}" for i in range(5))), 0.0)
    sim.advance(0.0)
    sim.take_output(0.0)
    sim.receive(b"M410\n", 1.0)
    sim.receive(wire("M400", first=6), 1.0)
    sim.advance(1.0)
    assert sim.take_output(1.0) == b"ok\nok\n"  # M410's, and M400's: nothing left to run


def test_the_receive_ring_loses_what_does_not_fit() -> None:
    sim = started(ControllerSettings(move_time=10.0))
    lines = wire(*(f"G1 X{i}.123456 Y{i}.654321" for i in range(40)))
    sim.receive(lines, 0.0)
    sim.advance(0.0)
    assert sim.link.bytes_dropped > 0  # 16 + 4 taken, the ring's 127 bytes kept, the rest lost
