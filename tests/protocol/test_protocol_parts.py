"""Each state part of the core on its own, and the pump over a scripted controller."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from repetrel_host.errors import JobError, SafeStopError
from repetrel_host.protocol.dialects.reprap import RepRapDialect
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import frame
from repetrel_host.protocol.history import History, Line
from repetrel_host.protocol.resend import ResendGuard
from repetrel_host.protocol.rtt import INITIAL_RTO, MAX_RTO, MIN_RTO, RoundTrip
from repetrel_host.protocol.window import Transmission, Window
from repetrel_host.session.job import ActionKind, HostAction, JobItem, JobLine
from repetrel_host.session.pump import JobRun, Listener, Outcome, Pump

# --- History ---------------------------------------------------------------------


def line(number: int, command: str = "G1 X1") -> Line:
    return Line(number, command, None, frame(number, command), False)


def test_history_numbers_from_the_reset_line_and_prunes_behind_acknowledgements() -> None:
    history = History(margin=2)
    history.restart(Line(5, "M110 N5", None, b"", True, is_reset=True, is_host_line=True))
    assert (history.floor, history.cursor, history.next_number) == (5, 5, 6)
    assert history.cursor < history.next_number  # the reset line has yet to go
    for number in range(6, 12):
        history.append(line(number))
    history.cursor = history.next_number
    assert history.cursor == history.next_number and history.held() == "5..11"
    history.prune(acknowledged_through=10)
    assert history.floor == 8 and history.get(7) is None and history.get(8) is not None


# --- Window --------------------------------------------------------------------------


def sent(number: int, size: int = 10, at: float = 0.0) -> Transmission:
    return Transmission(line(number), b"x" * size, at, number)


def test_window_counts_bytes_and_lines_and_lets_a_long_line_go_alone() -> None:
    window = Window(FlowControl(FlowMode.BUFFERED, rx_buffer=31, max_lines=2))
    assert window.has_room(100, 0.0)  # empty: even a line longer than the buffer goes
    window.push(sent(1, 20))
    assert window.has_room(10, 0.0) and not window.has_room(11, 0.0)  # 30 bytes usable
    window.push(sent(2, 5))
    assert not window.has_room(1, 0.0)  # two lines in flight: the line limit
    assert window.pop_oldest().number == 1
    assert (window.live, window.bytes) == (1, 5)


def test_window_unbuffered_keeps_one_line_in_flight() -> None:
    window = Window(FlowControl(FlowMode.UNBUFFERED, rx_buffer=1000))
    window.push(sent(1))
    assert not window.has_room(1, 0.0)


def test_stale_transmissions_stop_holding_the_window_after_they_expire() -> None:
    window = Window(FlowControl(FlowMode.BUFFERED, rx_buffer=31))
    window.push(sent(1, 25))
    window.mark_stale(expire_at=1.0)
    assert window.live == 0 and window.oldest_live() is None
    assert not window.has_room(10, 0.5)  # refused bytes may still sit in the buffer
    assert window.has_room(10, 1.0)


def test_advanced_ok_frees_lines_read_out_of_the_receive_buffer() -> None:
    window = Window(FlowControl(FlowMode.BUFFERED, rx_buffer=31, max_lines=8))
    for number in (1, 2, 3):
        window.push(sent(number, 10))
    assert not window.has_room(10, 0.0)
    window.read_through = 2
    assert window.has_room(20, 0.0)


def test_drop_through_and_discard() -> None:
    window = Window(FlowControl())
    first, second, third = sent(1), sent(2), sent(3)
    for transmission in (first, second, third):
        window.push(transmission)
    window.drop_through(second)
    assert list(window.in_flight) == [third]
    window.discard(first)  # already gone: nothing happens
    window.discard(third)
    assert window.bytes == window.live == 0


# --- RoundTrip -----------------------------------------------------------------------


def test_round_trip_estimate_clamps_and_backs_off() -> None:
    rtt = RoundTrip()
    assert rtt.rto == INITIAL_RTO and rtt.trailing_ok_window > 0
    assert rtt.sample(0.002)
    assert rtt.rto == MIN_RTO  # 2 ms measured: the floor
    assert rtt.backed_off(1) == 2 * MIN_RTO and rtt.backed_off(10) == 16 * MIN_RTO
    assert not rtt.sample(0.0001)  # an outlier only nudges the estimate
    assert rtt.srtt is not None and rtt.srtt < 0.002
    for _ in range(50):
        rtt.sample(20.0)
    assert rtt.rto == MAX_RTO


# --- ResendGuard -----------------------------------------------------------------------


def test_resend_guard_counts_echoes_rounds_and_unheld_requests() -> None:
    guard = ResendGuard()
    guard.expect_echoes(7, 2)
    assert guard.is_echo(7) and guard.is_echo(7) and not guard.is_echo(7)
    assert guard.rounds(7) == 1
    assert guard.rounds(7) == 0  # not sent again since: not another round
    guard.sent_again(7, now=1.0)
    assert guard.rounds(7) == 2
    assert guard.just_sent_again(7, now=1.01, round_trip=0.025)
    assert not guard.just_sent_again(7, now=1.03, round_trip=0.025)
    assert guard.unheld(99) == 1 and guard.unheld(99) == 2
    guard.progress(8)
    assert guard.unheld(99) == 1  # progress clears the count
    assert not guard.just_sent_again(7, now=1.01, round_trip=0.025)
    guard.sent_again(7, now=2.0)
    assert guard.rounds(7) == 1  # a new run of requests after progress


def test_a_request_for_any_line_just_sent_again_is_an_older_answer() -> None:
    guard = ResendGuard()
    for number in (7, 8, 9):  # a request for 7 obeyed: 7 and the lines after it went again
        guard.sent_again(number, now=1.0)
    assert guard.just_sent_again(7, now=1.01, round_trip=0.025)  # the line asked for too
    assert guard.just_sent_again(9, now=1.01, round_trip=0.025)
    assert not guard.just_sent_again(10, now=1.01, round_trip=0.025)
    guard.progress(7)
    assert not guard.just_sent_again(7, now=1.01, round_trip=0.025)
    assert guard.just_sent_again(8, now=1.01, round_trip=0.025)


# --- the pump over a scripted Marlin ---------------------------------------------------


class Recorder(Listener):
    def __init__(self) -> None:
        self.actions: list[HostAction] = []
        self.markers: list[HostAction] = []
        self.paused_count = 0
        self.runs: list[JobRun] = []

    def action_due(self, action: HostAction) -> None:
        self.actions.append(action)

    def marker_reached(self, action: HostAction) -> None:
        self.markers.append(action)

    def paused(self) -> None:
        self.paused_count += 1

    def finished(self, run: JobRun) -> None:
        self.runs.append(run)


def job_line(index: int, command: str = "G1 X1") -> JobLine:
    return JobLine(index, index, command, index, "job.gcode")


def greeted_pump(
    items: list[JobItem] | Iterator[JobItem], safe_stop: list[str]
) -> tuple[Pump, JobRun, Recorder]:
    recorder = Recorder()
    pump = Pump(RepRapDialect(FlowControl(FlowMode.UNBUFFERED), probe=ProbeKind.CHECKSUM), recorder)
    run = JobRun(items, safe_stop)
    pump.begin(run)
    pump.start(0.0)
    pump.receive(b"ok\nError:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    return pump, run, recorder


def confirm(pump: Pump, next_number: int) -> None:
    answer = f"Error:checksum mismatch, Last Line: {next_number - 1}\nResend: {next_number}\nok\n"
    pump.receive(answer.encode(), 0.0)


def test_a_host_action_waits_until_every_line_before_it_is_confirmed() -> None:
    action = HostAction(ActionKind.ACTIONS, "", (("BEEP", ""),), 2, "job.gcode")
    pump, run, recorder = greeted_pump([job_line(1), action, job_line(3, "G1 X3")], [])
    assert pump.poke(0.0) == frame(1, "G1 X1")
    pump.receive(b"ok\n", 0.0)
    assert pump.poke(0.0) == b"N2 M105 S0*9999\n"  # the ok is not proof: a probe is
    assert recorder.actions == []
    confirm(pump, 2)
    assert pump.poke(0.0) == b""
    assert recorder.actions == [action]
    pump.action_done(True)
    assert pump.poke(0.0) == frame(2, "G1 X3")
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert run.outcome is Outcome.COMPLETED and recorder.runs == [run]
    assert run.summary is not None and run.summary.lines == 3


def test_a_marker_is_due_as_the_line_before_it_is_acknowledged_and_holds_nothing_up() -> None:
    first = HostAction(ActionKind.SNAPSHOT, "", (), 1, "job.gcode")
    layer = HostAction(ActionKind.LAYER, "", (), 3, "job.gcode")
    items: list[JobItem] = [first, job_line(2), layer, job_line(4, "G1 X4")]
    recorder = Recorder()
    pump = Pump(RepRapDialect(FlowControl(), probe=ProbeKind.CHECKSUM), recorder)
    run = JobRun(items, [])
    pump.begin(run)
    pump.start(0.0)
    pump.receive(b"ok\nError:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    assert recorder.markers == [first]  # nothing of the job before it
    # Both lines go at once: no probe, no wait for the marker between them.
    assert pump.poke(0.0) == frame(1, "G1 X1") + frame(2, "G1 X4")
    assert recorder.markers == [first]
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    assert recorder.markers == [first, layer] and recorder.actions == []
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert run.outcome is Outcome.COMPLETED and run.lines == 4


def test_a_marker_after_the_header_waits_for_the_header_to_be_acknowledged() -> None:
    header = JobLine(0, 0, "M104 S200", 0, "header: head T0")
    marker = HostAction(ActionKind.SNAPSHOT, "", (), 1, "job.gcode")
    recorder = Recorder()
    pump = Pump(RepRapDialect(FlowControl(), probe=ProbeKind.CHECKSUM), recorder)
    run = JobRun([header, marker, job_line(2)], [])
    pump.begin(run)
    pump.start(0.0)
    pump.receive(b"ok\nError:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    assert pump.poke(0.0) == frame(1, "M104 S200") + frame(2, "G1 X1")
    assert recorder.markers == []  # the header's line is not acknowledged yet
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    assert recorder.markers == [marker]


def test_a_pause_after_the_file_was_read_to_its_end_still_sends_every_line() -> None:
    # The last lines were read ahead, not yet sent, when the pause came: they must go
    # after the resume, not be dropped with the job reported complete.
    recorder = Recorder()
    pump = Pump(RepRapDialect(FlowControl(), probe=ProbeKind.CHECKSUM), recorder)
    run = JobRun([job_line(i, f"G1 X{i}") for i in range(1, 11)], ["M104 S0"])
    pump.begin(run)
    pump.start(0.0)
    pump.receive(b"ok\nError:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    sent = pump.poke(0.0).count(b"\n")
    assert run.exhausted and sent < 10
    pump.pause()
    pump.receive(b"ok\n" * sent, 0.0)
    pump.poke(0.0)
    confirm(pump, sent + 1)
    assert pump.poke(0.0) == b"" and recorder.paused_count == 1 and run.outcome is None
    pump.resume()
    rest = pump.poke(0.0)
    assert rest == b"".join(frame(i, f"G1 X{i}") for i in range(sent + 1, 11))
    pump.receive(b"ok\n" * (10 - sent), 0.0)
    pump.poke(0.0)
    confirm(pump, 11)
    pump.poke(0.0)
    assert run.outcome is Outcome.COMPLETED and run.lines == 10


def test_an_action_that_declines_sends_the_safe_stop_and_cancels() -> None:
    action = HostAction(ActionKind.PAUSE, "", (), 2, "job.gcode")
    pump, run, _ = greeted_pump([job_line(1), action, job_line(3)], ["M104 S0"])
    pump.poke(0.0)
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 2)
    pump.poke(0.0)
    pump.action_done(False)
    assert pump.poke(0.0) == frame(2, "M104 S0")
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert run.outcome is Outcome.CANCELLED and run.safe_stop_missing == []


def test_a_second_stop_abandons_the_safe_stop() -> None:
    pump, run, _ = greeted_pump([job_line(i) for i in range(1, 50)], ["M104 S0", "M84"])
    pump.poke(0.0)
    assert not pump.stop(1.0)
    assert pump.poke(1.0) == b""  # line 1 still owes its ok; the safe stop waits its turn
    assert pump.stop(1.1)
    # Never called a clean cancel: the safe stop was not confirmed.
    assert run.outcome is None and isinstance(run.error, SafeStopError)
    assert "abandoned before the controller confirmed M104 S0, M84" in str(run.error)
    assert "still holds the job's lines from job.gcode:1 on" in str(run.error)
    assert run.safe_stop_missing == ["M104 S0", "M84"]


def test_a_pause_is_reached_once_every_line_sent_is_confirmed() -> None:
    pump, run, recorder = greeted_pump([job_line(i) for i in range(1, 5)], [])
    pump.poke(0.0)
    pump.pause()
    pump.receive(b"ok\n", 0.0)
    assert pump.poke(0.0) == b"N2 M105 S0*9999\n"  # no more job lines: confirm what went
    confirm(pump, 2)
    pump.poke(0.0)
    assert recorder.paused_count == 1 and run.lines == 1
    pump.resume()
    assert pump.poke(0.0) == frame(2, "G1 X1")


def test_a_line_that_cannot_go_stops_the_job_after_the_lines_before_it() -> None:
    def items() -> Iterator[JobItem]:
        yield job_line(1)
        raise JobError("job.gcode:2: the command is not ASCII text")

    pump, run, _ = greeted_pump(items(), ["M84"])
    assert pump.poke(0.0) == frame(1, "G1 X1")
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 2)
    assert pump.poke(0.0) == frame(2, "M84")
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert isinstance(run.error, JobError)
    assert str(run.error) == (
        "job.gcode:2: the command is not ASCII text; the last line the controller "
        "acknowledged is job.gcode:1 (command 1 of the job, G1 X1)"
    )


@pytest.mark.parametrize("kind", list(ActionKind))
def test_action_kinds_print_as_their_names(kind: ActionKind) -> None:
    assert f"{kind}" == kind.value


def test_a_file_that_cannot_be_read_on_stops_the_job_safely() -> None:
    def items() -> Iterator[JobItem]:
        yield job_line(1)
        raise OSError(5, "Input/output error")

    pump, run, _ = greeted_pump(items(), ["M84"])
    pump.poke(0.0)
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 2)
    assert pump.poke(0.0) == frame(2, "M84")  # not a completed job: the safe stop
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert isinstance(run.error, JobError) and "could not be read on" in str(run.error)


def test_a_pause_keeps_a_host_action_behind_the_lines_before_it() -> None:
    action = HostAction(ActionKind.ACTIONS, "", (("BEEP", ""),), 3, "job.gcode")
    items: list[JobItem] = [job_line(1), job_line(2, "G1 X2"), action, job_line(4, "G1 X4")]
    recorder = Recorder()
    pump = Pump(RepRapDialect(FlowControl(max_lines=1), probe=ProbeKind.CHECKSUM), recorder)
    run = JobRun(items, [])
    pump.begin(run)
    pump.start(0.0)
    pump.receive(b"ok\nError:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    assert pump.poke(0.0) == frame(1, "G1 X1")  # line 2 and the action are read ahead
    pump.pause()
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 2)
    pump.poke(0.0)
    assert recorder.paused_count == 1 and recorder.actions == []
    pump.resume()
    assert pump.poke(0.0) == frame(2, "G1 X2")  # before the action, as in the file
    pump.receive(b"ok\n", 0.0)
    pump.poke(0.0)
    confirm(pump, 3)
    pump.poke(0.0)
    assert recorder.actions == [action]
