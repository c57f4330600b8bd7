"""HostProtocol, byte for byte, with replies written by hand from Marlin's strings."""

import pytest

from repetrel_host.errors import ProtocolError
from repetrel_host.protocol.host import (
    HELLO_ATTEMPTS,
    HELLO_TIMEOUT,
    ControllerMessage,
    ControllerReady,
    Event,
    Failed,
    FlowControl,
    FlowMode,
    HostProtocol,
    LineAcknowledged,
    ResendRequested,
)

HELLO = b"N0 M110 N0*125\n"


def events(host: HostProtocol) -> list[Event]:
    out = []
    while (event := host.next_event()) is not None:
        out.append(event)
    return out


def greeted(flow: FlowControl | None = None, **kwargs: object) -> HostProtocol:
    host = HostProtocol(flow, **kwargs)  # type: ignore[arg-type]
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO
    host.receive_data(b"ok\n", 0.0)
    assert events(host) == [ControllerReady()]
    return host


def acked(host: HostProtocol) -> list[int]:
    return [e.number for e in events(host) if isinstance(e, LineAcknowledged)]


def test_opening_line_goes_alone_and_waits_for_its_ok() -> None:
    host = HostProtocol()
    host.send("G28", "a")
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO
    assert host.data_to_send(0.0) == b""
    host.receive_data(b"start\n", 0.1)  # a boot banner is not an answer
    assert host.data_to_send(0.1) == b""
    host.receive_data(b"ok\n", 0.2)
    assert host.data_to_send(0.2) == b"N1 G28*18\n"


def test_buffered_window_counts_bytes_against_the_receive_buffer() -> None:
    # 40-byte buffer: 39 usable; "N1 G92 E1*xx\n" is 13 bytes, so three fit.
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=40, max_lines=8))
    for i in range(5):
        host.send(f"G92 E{i + 1}", i)
    sent = host.data_to_send(0.0)
    assert sent.count(b"\n") == 3
    assert sent.startswith(b"N1 G92 E1*")
    host.receive_data(b"ok\n", 0.0)
    assert acked(host) == [1]
    assert host.data_to_send(0.0).startswith(b"N4 G92 E4*")


def test_buffered_window_counts_lines_too() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=1000, max_lines=2))
    for i in range(4):
        host.send("G28", i)
    assert host.data_to_send(0.0).count(b"\n") == 2


def test_unbuffered_sends_one_line_per_ok() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    for i in range(3):
        host.send(f"G1 X{i}", i)
    assert host.data_to_send(0.0) == b"N1 G1 X0*97\n"
    assert host.data_to_send(0.0) == b""
    host.receive_data(b"ok\n", 0.0)
    assert host.data_to_send(0.0) == b"N2 G1 X1*99\n"


def test_a_line_longer_than_the_buffer_goes_alone() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=16))
    host.send("M117 " + "x" * 40, 0)
    assert host.data_to_send(0.0).startswith(b"N1 M117 xxxx")


def test_resend_goes_back_and_absorbs_the_storm() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=40))
    for i in range(3):
        host.send(f"G92 E{i + 1}", i)
    first = host.data_to_send(0.0)
    lines = first.splitlines(keepends=True)
    assert len(lines) == 3
    # Line 1 accepted, line 2 corrupted, line 3 refused as out of sequence.
    host.receive_data(b"ok\n", 0.0)
    host.receive_data(b"Error:checksum mismatch, Last Line: 1\nResend: 2\nok\n", 0.0)
    got = events(host)
    assert [type(e) for e in got] == [LineAcknowledged, ControllerMessage, ResendRequested]
    assert got[2] == ResendRequested(2, "G92 E2", 1)
    # Line 3's stale bytes still occupy the buffer: 13 + 26 = 39 fits exactly.
    assert host.data_to_send(0.0) == lines[1] + lines[2]
    host.receive_data(
        b"Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\nok\n", 0.0
    )
    assert not [e for e in events(host) if isinstance(e, ResendRequested)]
    assert host.stats.ignored_resend_requests == 1
    host.receive_data(b"ok\nok\n", 0.0)
    assert acked(host) == [2, 3]
    assert host.is_done
    assert host.stats.retransmissions == 2


def test_a_second_failure_of_the_resent_line_is_honoured() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", 0)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    for _ in range(2):
        host.receive_data(b"Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
        assert host.data_to_send(0.0) == b"N1 G28*18\n"
    host.receive_data(b"ok\n", 0.0)
    assert acked(host) == [1]
    assert host.stats.resend_requests == 2


def test_resend_of_a_line_not_held_stops_rather_than_guessing() -> None:
    host = greeted()
    host.send("G28", 0)
    host.data_to_send(0.0)
    host.receive_data(b"Resend: 77\n", 0.0)
    failure = host.failure
    assert failure is not None and failure.kind == "protocol"
    assert "77" in failure.reason
    host.send("G28", 1)
    assert host.data_to_send(0.0) == b""


def test_reset_mid_job_stops_at_once_and_never_resends() -> None:
    host = greeted()
    for i in range(3):
        host.send("G28", i)
    host.data_to_send(0.0)
    host.receive_data(b"ok\nstart\nok\n", 0.0)
    got = events(host)
    assert [type(e) for e in got] == [LineAcknowledged, Failed]
    failure = host.failure
    assert failure is not None and failure.kind == "controller"
    assert "reset" in failure.reason
    assert host.data_to_send(0.0) == b""  # the ok after 'start' released nothing


def test_controller_error_fails_the_stream() -> None:
    host = greeted()
    host.receive_data(b"Error:MINTEMP triggered, system stopped!\n", 0.0)
    assert host.failure is not None
    assert "MINTEMP" in host.failure.reason


def test_renumbers_with_m110_after_draining_at_the_limit() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=1000), line_number_limit=2)
    for i in range(3):
        host.send("G28", i)
    assert host.data_to_send(0.0) == b"N1 G28*18\nN2 G28*17\n"
    host.receive_data(b"ok\n", 0.0)
    assert host.data_to_send(0.0) == b""  # line 2 still in flight
    host.receive_data(b"ok\n", 0.0)
    assert host.data_to_send(0.0) == HELLO
    host.receive_data(b"ok\n", 0.0)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    host.receive_data(b"ok\n", 0.0)
    assert acked(host) == [1, 2, 1]
    assert host.is_done


def test_silence_on_a_buffered_line_times_out() -> None:
    host = greeted(reply_timeout=3.0)
    host.send("G1 X1", 0)
    host.data_to_send(1.0)
    assert host.next_deadline() == 4.0
    host.handle_timeout(3.9)
    assert host.failure is None
    host.handle_timeout(4.0)
    assert host.failure is not None and host.failure.kind == "timeout"


def test_unbuffered_command_has_no_reply_deadline() -> None:
    host = greeted(reply_timeout=3.0)
    host.send("M109 S200", 0)
    host.data_to_send(1.0)
    assert host.next_deadline() is None


def test_opening_line_is_repeated_when_unanswered() -> None:
    host = HostProtocol()
    host.start(0.0)
    now = 0.0
    for attempt in range(HELLO_ATTEMPTS):
        assert host.data_to_send(now) == HELLO, attempt
        now += HELLO_TIMEOUT
        host.handle_timeout(now)
    assert host.failure is not None and "M110" in host.failure.reason


def test_unexpected_ok_is_ignored() -> None:
    host = greeted()
    host.receive_data(b"ok\n", 0.0)
    assert host.stats.unexpected_oks == 1
    assert host.failure is None


def test_replies_split_across_reads() -> None:
    host = greeted()
    host.send("G28", 0)
    host.data_to_send(0.0)
    host.receive_data(b"o", 0.0)
    host.receive_data(b"k\r", 0.0)
    assert acked(host) == []
    host.receive_data(b"\n", 0.0)
    assert acked(host) == [1]


def test_m110_cannot_be_queued() -> None:
    with pytest.raises(ProtocolError):
        HostProtocol().send("M110 N5")


def test_failure_names_the_oldest_unacknowledged_line() -> None:
    host = greeted()
    for tag in ("job.gcode:1", "job.gcode:2", "job.gcode:3"):
        host.send("G28", tag)
    host.data_to_send(0.0)
    host.receive_data(b"ok\nError:Printer halted. kill() called!\n", 0.0)
    assert host.failure is not None
    assert host.failure.tag == "job.gcode:2"


def test_a_line_acknowledged_again_after_a_resend_is_reported_once() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", "a")
    host.send("G1 X1", "b")
    host.data_to_send(0.0)
    host.receive_data(b"ok\n", 0.0)
    host.data_to_send(0.0)
    # A controller that lost line 1 after acknowledging it asks for it again.
    host.receive_data(b"Resend: 1\nok\n", 0.0)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    host.receive_data(b"ok\n", 0.0)
    host.data_to_send(0.0)
    host.receive_data(b"ok\n", 0.0)
    assert [e.tag for e in events(host) if isinstance(e, LineAcknowledged)] == ["a", "b"]
