"""The RepRap dialect, byte for byte, with replies written by hand from Marlin's strings."""

from itertools import product

import pytest

from repetrel_host.errors import UsageError
from repetrel_host.protocol import replies
from repetrel_host.protocol.controller import Accepted, ControllerProtocol
from repetrel_host.protocol.dialects.reprap import UNBUFFERED_GRACE, RepRapDialect, RepRapPhase
from repetrel_host.protocol.dialects.reprap_greeting import (
    HELLO_ATTEMPTS,
    HELLO_TIMEOUT,
    NOISY_HELLO_ATTEMPTS,
)
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    DialectFailed,
    Event,
    FailureKind,
    GreetingRetry,
    LineAcknowledged,
    Notice,
    ProbeKind,
    ResendRequested,
)
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import checksum, frame
from repetrel_host.protocol.rtt import MIN_RTO
from repetrel_host.protocol.silence import REPORT_GAP

HELLO = b"N0 M110 N0*125\n"


def ping(number: int) -> bytes:
    """What the host sends to ask where the controller stands (a checksum that never fits):
    the first S<k> whose true checksum one changed character of "9999" cannot reach."""
    for k in range(10):
        body = f"N{number} M105 S{k}".encode()
        if checksum(body) not in (0, 9, 99):
            return body + b"*9999\n"
    raise AssertionError("no safe ping body")


def ping_reply(number: int, trailing_ok: bool = True) -> bytes:
    """Marlin's answer when it has every line before ``number``."""
    ok = b"ok\n" if trailing_ok else b""
    return f"Error:checksum mismatch, Last Line: {number - 1}\nResend: {number}\n".encode() + ok


def dialect(flow: FlowControl | None = None, **kwargs: object) -> RepRapDialect:
    """A dialect that probes with checksum probes, without the greeting's check
    (tested on its own below)."""
    return RepRapDialect(flow, probe=ProbeKind.CHECKSUM, **kwargs)  # type: ignore[arg-type]


def events(host: RepRapDialect) -> list[Event]:
    out = []
    while (event := host.next_event()) is not None:
        out.append(event)
    return out


def greeted(flow: FlowControl | None = None, **kwargs: object) -> RepRapDialect:
    host = dialect(flow, **kwargs)
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO + ping(1)
    host.receive_data(b"ok\n" + ping_reply(1), 0.0)
    assert [e for e in events(host) if not isinstance(e, ControllerMessage)] == [
        ControllerReady(ProbeKind.CHECKSUM)
    ]
    return host


def acked(host: RepRapDialect) -> list[int]:
    return [e.number for e in events(host) if isinstance(e, LineAcknowledged)]


def test_the_ping_never_runs_whatever_single_byte_changes() -> None:
    wire = ping(1234)[:-1]
    for position, value in product(range(len(wire)), range(256)):
        if value == wire[position] or value == 0x0A:
            continue
        corrupted = wire[:position] + bytes([value]) + wire[position + 1 :]
        controller = ControllerProtocol()
        controller.last_line = 1233
        assert not isinstance(controller.handle_line(corrupted), Accepted), corrupted


def test_greeting_waits_for_the_ping_answer() -> None:
    host = dialect()
    host.send("G28", "a")
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO + ping(1)
    host.receive_data(b"start\n", 0.1)  # a boot banner is not an answer
    assert host.data_to_send(0.1) == b""
    host.receive_data(b"ok\n" + ping_reply(1, trailing_ok=False), 0.2)
    assert ControllerReady(ProbeKind.CHECKSUM) in events(host)
    assert host.data_to_send(0.2) == b"N1 G28*18\n"


@pytest.mark.parametrize("trailing_ok", [True, False])
def test_the_ok_that_ends_an_error_is_not_taken_for_the_next_line(trailing_ok: bool) -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G1 X0", 0)  # not G28: an unbuffered command's ok measures the machine
    host.data_to_send(1.0)
    host.receive_data(b"ok\n", 1.010)  # measures a 10 ms round trip
    host.send("G1 X1", 1)
    assert host.data_to_send(1.010) == b"N2 G1 X1*99\n"
    host.receive_data(b"Error:checksum mismatch, Last Line: 1\nResend: 2\n", 1.020)
    assert host.data_to_send(1.020) == b"N2 G1 X1*99\n"
    if trailing_ok:
        host.receive_data(b"ok\n", 1.0201)  # right behind the resend request
    assert acked(host) == [1]
    host.receive_data(b"ok\n", 1.030)  # a round trip later: the answer to line 2
    assert acked(host) == [2]


def test_buffered_window_counts_bytes_against_the_receive_buffer() -> None:
    # 40-byte buffer: 39 usable; "N1 G92 E1*xx" is 13 bytes with its newline, so three fit.
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


def test_done_only_once_the_controller_confirms_every_line() -> None:
    host = greeted()
    host.send("G28", 0)
    host.send("G1 X1", 1)
    host.data_to_send(0.0)
    host.request_sync()
    host.receive_data(b"ok\nok\n", 0.0)
    assert acked(host) == [1, 2]
    assert not host.is_done  # two oks are not proof: they may be duplicates
    assert host.data_to_send(0.0) == ping(3)
    host.receive_data(ping_reply(3), 0.0)
    assert host.is_done


def test_a_final_line_whose_ok_was_faked_by_a_duplicate_is_not_lost() -> None:
    host = greeted()
    host.send("G28", 0)
    host.send("G1 X1", 1)
    host.data_to_send(0.0)
    host.request_sync()
    # Line 1's ok came twice; line 2 was corrupted and its error is still on the way.
    host.receive_data(b"ok\nok\n", 0.0)
    assert host.data_to_send(0.0) == ping(3)
    host.receive_data(b"Error:checksum mismatch, Last Line: 1\nResend: 2\nok\n", 0.0)
    assert not host.is_done
    assert host.data_to_send(0.0) == b"N2 G1 X1*99\n"
    host.receive_data(
        b"Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\n", 0.0
    )
    host.receive_data(b"ok\nok\n", 0.0)  # the ping's echo's ok, then line 2's
    assert host.data_to_send(0.0) == ping(3)
    host.receive_data(ping_reply(3), 0.0)
    assert host.is_done


def test_resend_goes_back_and_absorbs_the_storm() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=40))
    for i in range(3):
        host.send(f"G92 E{i + 1}", i)
    lines = host.data_to_send(0.0).splitlines(keepends=True)
    assert len(lines) == 3
    # Line 1 accepted, line 2 corrupted, line 3 refused as out of sequence.
    host.receive_data(b"ok\n", 0.0)
    host.receive_data(b"Error:checksum mismatch, Last Line: 1\nResend: 2\nok\n", 0.0)
    got = [e for e in events(host) if not isinstance(e, ControllerMessage)]
    assert got == [
        LineAcknowledged(1, "G92 E1", 0, ""),
        ResendRequested(2, "G92 E2", 1),
    ]
    assert host.data_to_send(0.0) == lines[1] + lines[2]
    host.receive_data(
        b"Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\nok\n", 0.0
    )
    assert not [e for e in events(host) if isinstance(e, ResendRequested)]
    assert host.stats.ignored_resend_requests == 1
    host.receive_data(b"ok\nok\n", 0.0)
    assert acked(host) == [2, 3]
    assert host.stats.retransmissions == 2


ROUND_TRIP = 0.05  # past the retransmission timeout (25 ms after a fast greeting)


def test_a_second_failure_of_the_resent_line_is_honoured() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", 0)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    now = 0.0
    for _ in range(2):
        now += ROUND_TRIP
        host.receive_data(b"Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n", now)
        assert host.data_to_send(now) == b"N1 G28*18\n"
    host.receive_data(b"ok\n", now + ROUND_TRIP)
    assert acked(host) == [1]
    assert host.stats.resend_requests == 2


def test_a_request_sooner_than_a_round_trip_after_the_resend_is_an_older_answer() -> None:
    # On a link whose replies queue up (long error lines on a slow wire), answers to
    # older transmissions still arrive after a line went out again: obeying each would
    # add another refusal to the queue, and another request, without end.
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", 0)
    host.send("G1 X1", 1)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    host.receive_data(b"Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.010)
    assert host.data_to_send(0.010) == b"N1 G28*18\n"
    stale = b"Error:Line Number is not Last Line Number+1, Last Line: 0\nResend: 1\nok\n"
    host.receive_data(stale, 0.012)
    assert host.data_to_send(0.012) == b""  # the line that went out again is still in flight
    host.receive_data(b"ok\n", 0.013)
    assert acked(host) == [1]
    assert host.data_to_send(0.013) == frame(2, "G1 X1")


def test_a_garbled_resend_number_is_ignored_not_obeyed() -> None:
    host = greeted()
    for i in range(3):
        host.send("G28", i)
    host.data_to_send(0.0)
    # "Last Line: 1" but "Resend: 9": the two lines disagree, one was garbled.
    host.receive_data(b"Error:checksum mismatch, Last Line: 1\nResend: 9\nok\n", 0.0)
    assert host.failure is None
    assert not [e for e in events(host) if isinstance(e, ResendRequested)]


def test_resend_of_a_line_not_held_stops_when_it_is_repeated() -> None:
    host = greeted()
    host.send("G28", 0)
    host.data_to_send(0.0)
    host.receive_data(b"Resend: 77\n", 0.0)
    assert host.failure is None  # once could be a garbled number
    host.receive_data(b"Resend: 77\n", 0.0)
    failure = host.failure
    assert failure is not None and failure.kind is FailureKind.PROTOCOL
    assert "77" in failure.reason
    host.send("G28", 1)
    assert host.data_to_send(0.0) == b""


def test_the_same_line_requested_again_and_again_is_a_loop() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", 0)
    host.data_to_send(0.0)
    for round_ in range(1, 11):
        now = round_ * ROUND_TRIP
        host.receive_data(b"Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n", now)
        host.data_to_send(now)
    assert host.failure is not None and "10 times" in host.failure.reason


def test_a_high_resend_rate_is_reported_once() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    notices = []
    for i in range(1, 121):
        host.send("G28", i)
        host.data_to_send(0.0)
        if i % 5 == 0:
            reply = f"Error:checksum mismatch, Last Line: {i - 1}\nResend: {i}\nok\n"
            host.receive_data(reply.encode(), 0.0)
            host.data_to_send(0.0)
        host.receive_data(b"ok\n", 0.0)
        notices += [e for e in events(host) if isinstance(e, Notice)]
    assert len(notices) == 1 and "noisy" in notices[0].text


def test_reset_mid_job_stops_at_once_and_never_resends() -> None:
    host = greeted()
    for i in range(3):
        host.send("G28", i)
    host.data_to_send(0.0)
    host.receive_data(b"ok\nstart\nok\n", 0.0)
    got = events(host)
    assert [type(e) for e in got] == [LineAcknowledged, DialectFailed]
    failure = host.failure
    assert failure is not None and failure.kind is FailureKind.RESET
    assert "reset" in failure.reason
    assert failure.tag == 1  # the oldest line not acknowledged
    assert host.data_to_send(0.0) == b""


def test_controller_error_fails_the_stream() -> None:
    host = greeted()
    host.receive_data(b"Error:MINTEMP triggered, system stopped!\n", 1.0)
    assert host.failure is None  # a resend request might still show it was a line error
    deadline = host.next_deadline()
    assert deadline is not None and deadline <= 1.0 + 0.2 + 1e-9
    host.handle_timeout(deadline)
    assert host.failure is not None
    assert "MINTEMP" in host.failure.reason


def test_an_error_line_cut_by_a_garbled_newline_is_not_fatal() -> None:
    host = greeted()
    host.send("G28", 0)
    host.data_to_send(0.0)
    host.receive_data(b"Error:chec\nksum mismatch, Last Line: 0\nResend: 1\nok\n", 0.0)
    host.handle_timeout(1.0)
    assert host.failure is None
    assert host.data_to_send(1.0) == b"N1 G28*18\n"


def test_a_halted_printer_that_keeps_talking_fails_after_three_lines() -> None:
    host = greeted()
    host.receive_data(b"Error:Printer halted. kill() called!\necho:x\necho:y\necho:z\n", 0.0)
    assert host.failure is not None and "halted" in host.failure.reason


def test_renumbers_with_m110_once_the_controller_confirmed_everything() -> None:
    host = greeted(FlowControl(FlowMode.BUFFERED, rx_buffer=1000), line_number_limit=3)
    for i in range(4):
        host.send("G28", i)
    assert host.data_to_send(0.0) == b"N1 G28*18\nN2 G28*17\nN3 G28*16\n"
    host.receive_data(b"ok\nok\nok\n", 0.0)
    assert host.data_to_send(0.0) == ping(4)  # confirm before numbers start again
    host.receive_data(ping_reply(4), 0.0)
    assert host.data_to_send(0.0) == HELLO + ping(1)
    host.receive_data(b"ok\n" + ping_reply(1), 0.0)
    assert host.data_to_send(0.0) == b"N1 G28*18\n"
    host.receive_data(b"ok\n", 0.0)
    assert acked(host) == [1, 2, 3, 1]


def test_a_lost_ok_costs_one_retransmission_timeout_and_a_ping() -> None:
    # (Commands that take no time: nothing explains a silence after them.)
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("M106 S1", 0)
    host.send("M106 S2", 1)
    host.data_to_send(1.0)
    host.receive_data(b"ok\n", 1.002)
    host.data_to_send(1.002)
    # The second ok is lost. After one timeout (from the 2 ms measured, clamped), ping.
    assert host.retransmission_timeout == MIN_RTO
    deadline = host.next_deadline()
    assert deadline is not None and deadline == pytest.approx(1.002 + MIN_RTO)
    host.handle_timeout(deadline)
    assert host.data_to_send(deadline) == ping(3)
    host.receive_data(ping_reply(3), deadline + 0.002)
    assert acked(host) == [1, 2]
    assert host.stats.stalls_recovered == 1


def test_a_command_awaited_for_its_reply_is_probed_only_after_the_grace() -> None:
    # A probe's answer comes before the oks of lines the controller still holds: probing a
    # slow M115 after one round trip would settle it before its reply's lines came.
    host = greeted()
    host.send("M115", "command", confirm=True)
    host.data_to_send(0.0)
    deadline = host.next_deadline()
    assert deadline is not None and deadline >= UNBUFFERED_GRACE
    host.handle_timeout(2.0)
    assert host.data_to_send(2.0) == b""
    host.receive_data(b"FIRMWARE_NAME:Marlin\nok\n", 2.2)
    acknowledged = [e for e in events(host) if isinstance(e, LineAcknowledged)]
    assert [(e.number, e.tag) for e in acknowledged] == [(1, "command")]


def test_a_silent_controller_fails_after_the_reply_timeout() -> None:
    host = greeted(reply_timeout=3.0)
    host.send("G1 X1", 0)
    host.data_to_send(0.0)
    now = 0.0
    while host.failure is None and now < 10:
        deadline = host.next_deadline()
        assert deadline is not None and deadline > now
        now = deadline
        host.handle_timeout(now)
        host.data_to_send(now)
    assert host.failure is not None and host.failure.kind is FailureKind.TIMEOUT
    assert 3.0 <= now < 4.0


def test_an_unbuffered_command_is_not_a_silence_failure() -> None:
    host = greeted(reply_timeout=3.0)
    host.send("M109 S200", 0)
    host.data_to_send(0.0)
    now = 0.0
    while (deadline := host.next_deadline()) is not None and now < 100:
        now = deadline
        host.handle_timeout(now)
        host.data_to_send(now)
    assert host.failure is None  # a few pings wait behind the heating, then it waits
    host.receive_data(b"ok\n", 100.0)
    assert acked(host) == [1]


def test_busy_keepalives_hold_the_pings_back() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G28", 0)
    host.data_to_send(0.0)
    for second in range(1, 30, 2):
        host.receive_data(b"echo:busy: processing\n", float(second))
        host.handle_timeout(float(second))
        assert host.data_to_send(float(second)) == b""
    assert host.stats.pings == 1  # the greeting's only


def test_opening_line_is_repeated_when_unanswered() -> None:
    host = dialect()
    host.start(0.0)
    now = 0.0
    for attempt in range(HELLO_ATTEMPTS):
        reset = frame(attempt, f"M110 N{attempt}")
        assert host.data_to_send(now) == reset + ping(attempt + 1), attempt
        now += HELLO_TIMEOUT
        host.handle_timeout(now)
    assert host.failure is not None and "M110" in host.failure.reason


def test_each_unanswered_greeting_is_told_as_it_goes_again_then_it_fails_naming_it() -> None:
    host = RepRapDialect()  # with the greeting's check, as a session greets
    host.start(0.0)
    host.data_to_send(0.0)
    told: list[Event] = []
    now = 0.0
    while host.failure is None:
        now = host.next_deadline() or now
        host.handle_timeout(now)
        host.data_to_send(now)
        told += events(host)
    assert (HELLO_ATTEMPTS, HELLO_TIMEOUT) == (3, 3.0)  # 9 s of silence, not 20
    assert told[:-1] == [GreetingRetry(2, 3, 3.0), GreetingRetry(3, 3, 6.0)]
    assert told[-1] == host.failure and host.failure.kind is FailureKind.NO_ANSWER
    assert host.failure.reason == "no answer to M110 (line numbering reset), sent 3 times in 9 s"


def test_a_boot_banner_puts_the_next_greeting_off() -> None:
    """A board that resets as the port opens drops the first greeting while it boots; its
    "start" restarts the wait, so the next greeting finds it listening."""
    host = dialect()
    host.start(0.0)
    host.data_to_send(0.0)
    host.receive_data(b"start\n", 2.5)
    host.handle_timeout(HELLO_TIMEOUT)
    assert host.data_to_send(HELLO_TIMEOUT) == b"" and events(host) == [
        ControllerMessage(replies.Start(), "start")
    ]
    host.handle_timeout(2.5 + HELLO_TIMEOUT)
    assert host.data_to_send(2.5 + HELLO_TIMEOUT) == frame(1, "M110 N1") + ping(2)
    # Heard from, the board is there: it gets the patience of a noisy link.
    assert events(host) == [GreetingRetry(2, NOISY_HELLO_ATTEMPTS, 2.5 + HELLO_TIMEOUT)]


def test_a_controller_heard_from_is_greeted_with_more_patience_than_a_silent_port() -> None:
    """Its answers to the greeting lost on a noisy link, a controller that said anything
    of its own (here an error) is greeted NOISY_HELLO_ATTEMPTS times, not failed after 3."""
    host = RepRapDialect()
    host.start(0.0)
    host.data_to_send(0.0)
    host.receive_data(b"Error:Line Number is not Last Line Number+1, Last Line: 7\n", 0.5)
    told: list[Event] = []
    now = 0.0
    while host.failure is None:
        now = host.next_deadline() or now
        host.handle_timeout(now)
        host.data_to_send(now)
        told += events(host)
    retries = [event for event in told if isinstance(event, GreetingRetry)]
    assert [retry.attempt for retry in retries] == list(range(2, NOISY_HELLO_ATTEMPTS + 1))
    assert NOISY_HELLO_ATTEMPTS > HELLO_ATTEMPTS
    assert host.failure.reason.startswith(
        f"no answer to M110 (line numbering reset), sent {NOISY_HELLO_ATTEMPTS} times"
    )


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


@pytest.mark.parametrize("command", ["M110 N5", "m110", "M110N0", "M0110 N1"])
def test_m110_cannot_be_queued(command: str) -> None:
    with pytest.raises(UsageError):
        dialect().send(command)
    dialect().send("M1100")  # another code


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


def test_a_late_answer_to_an_earlier_greeting_is_not_taken_for_the_last() -> None:
    host = dialect()
    host.start(0.0)
    host.data_to_send(0.0)
    host.handle_timeout(HELLO_TIMEOUT)  # no answer: greet again, with other numbers
    assert host.data_to_send(HELLO_TIMEOUT) == frame(1, "M110 N1") + ping(2)
    # The first greeting's answers arrive late; an M110 may still be on its way.
    host.receive_data(b"ok\n" + ping_reply(1), 2.1)
    assert ControllerReady(ProbeKind.CHECKSUM) not in events(host)
    host.send("G28", 0)
    assert host.data_to_send(2.1) == b""
    host.receive_data(b"ok\n" + ping_reply(2), 2.2)
    assert ControllerReady(ProbeKind.CHECKSUM) in events(host)
    assert host.data_to_send(2.2) == frame(2, "G28")


# --- the usual probe: a numbered M105 that runs --------------------------------------

TEMPERATURES = b"ok T:21.00 /0.00 B:21.00 /0.00 @:0 B@:0\n"  # Marlin's answer to M105


def test_the_greeting_is_m110_and_a_probe_that_runs() -> None:
    host = RepRapDialect()
    host.start(0.0)
    # A real line that Marlin takes once it holds line 0 (the M110), and answers with the
    # temperatures: no error, whatever the controller held before.
    assert host.data_to_send(0.0) == HELLO + b"N1 M105*38\n"
    host.receive_data(b"ok\n" + TEMPERATURES, 0.002)
    assert ControllerReady(ProbeKind.COMMAND) in events(host)
    host.send("G28", 0)
    assert host.data_to_send(0.002) == b"N2 G28*17\n"


def test_a_controller_whose_m105_answer_says_nothing_is_probed_with_checksums() -> None:
    host = RepRapDialect()
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO + b"N1 M105*38\n"
    # Its temperatures on a line of their own: the probe's answer is a plain ok.
    host.receive_data(b"ok\nT:21.0 /0.0\nok\n", 0.002)
    notices = [e for e in events(host) if isinstance(e, Notice)]
    assert len(notices) == 1 and "plain ok" in notices[0].text
    assert host.data_to_send(0.002) == frame(1, "M110 N1") + ping(2)
    host.receive_data(b"ok\n" + ping_reply(2), 0.004)
    assert ControllerReady(ProbeKind.CHECKSUM) in events(host)


def test_an_answer_before_the_m110s_ok_does_not_end_the_greeting() -> None:
    # Replies come in order: the M110's ok before the probe's answer. An "ok T:" first is
    # an earlier one said twice; taken, it would number lines the controller never reset.
    host = RepRapDialect()
    host.start(0.0)
    host.data_to_send(0.0)
    host.receive_data(TEMPERATURES, 0.001)
    assert host.phase is RepRapPhase.GREETING and not events(host)
    host.receive_data(b"ok\n" + TEMPERATURES, 0.003)
    assert ControllerReady(ProbeKind.COMMAND) in events(host)


def test_octoprints_virtual_printer_gets_at_most_64_bytes_in_flight() -> None:
    # Its 64-byte buffer, full, stalls it 10 s on each error it reports: once its M115
    # says who it is, no more than that goes ahead of its answers.
    host = RepRapDialect(FlowControl(FlowMode.BUFFERED, rx_buffer=4096, max_lines=96))
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO + frame(1, "M105")
    host.receive_data(b"ok\n" + TEMPERATURES, 0.001)
    host.send("M115", "who", confirm=True)
    assert host.data_to_send(0.001) == frame(2, "M115")
    host.receive_data(b"FIRMWARE_NAME:Virtual Marlin 1.0 PROTOCOL_VERSION:1.0\nok\n", 0.002)
    assert any(isinstance(e, Notice) and "64 bytes" in e.text for e in events(host))
    for i in range(10):
        host.send(f"G1 X{i}.123 Y{i}.456 E{i}.789", i)  # 31-32 bytes framed
    assert host.data_to_send(0.003) == frame(3, "G1 X0.123 Y0.456 E0.789") + frame(
        4, "G1 X1.123 Y1.456 E1.789"
    )
    host.receive_data(b"ok\n", 0.004)
    assert host.data_to_send(0.004) == frame(5, "G1 X2.123 Y2.456 E2.789")


def command_probing() -> RepRapDialect:
    host = RepRapDialect(FlowControl(FlowMode.UNBUFFERED), probe=ProbeKind.COMMAND)
    host.start(0.0)
    assert host.data_to_send(0.0) == HELLO + frame(1, "M105")
    host.receive_data(b"ok\n" + TEMPERATURES, 0.001)
    assert ControllerReady(ProbeKind.COMMAND) in events(host)
    return host


def test_only_an_ok_with_temperatures_answers_a_command_probe() -> None:
    host = command_probing()
    host.send("G1 X1", 0)
    host.request_sync()
    assert host.data_to_send(0.01) == frame(2, "G1 X1")
    host.receive_data(b"ok\n", 0.011)
    assert host.data_to_send(0.011) == frame(3, "M105")
    host.receive_data(b"ok\n", 0.012)  # a duplicated ok: not the probe's answer
    assert not host.is_done
    host.receive_data(TEMPERATURES, 0.013)
    # One answer could be an earlier M105's said twice: a second probe, then done.
    assert not host.is_done and host.data_to_send(0.013) == frame(4, "M105")
    host.receive_data(TEMPERATURES, 0.015)
    assert host.is_done


def test_a_command_probe_answer_is_found_behind_lost_oks() -> None:
    host = command_probing()
    host.send("G1 X1", 0)
    assert host.data_to_send(0.01) == frame(2, "G1 X1")
    # Line 2's ok is lost: after a timeout the host probes; the probe's answer settles it.
    deadline = host.next_deadline()
    assert deadline is not None
    host.handle_timeout(deadline)
    assert host.data_to_send(deadline) == frame(3, "M105")
    host.receive_data(TEMPERATURES, deadline + 0.002)
    assert acked(host) == [2]
    host.send("G1 X2", 1)
    assert host.data_to_send(deadline + 0.002) == frame(4, "G1 X2")


def test_a_line_dropped_without_a_resend_request_is_probed_for_within_a_round_trip() -> None:
    # OctoPrint's virtual printer drops a line with only this error: no resend, no ok.
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G1 X1", 0)
    host.send("G1 X2", 1)
    host.data_to_send(1.0)
    host.receive_data(b"ok\n", 1.002)
    assert host.data_to_send(1.002) == frame(2, "G1 X2")
    host.receive_data(b"Error: No Line Number with checksum, Last Line: 1\n", 1.004)
    deadline = host.next_deadline()
    assert deadline is not None and deadline <= 1.004 + host.retransmission_timeout
    host.handle_timeout(deadline)
    assert host.data_to_send(deadline) == ping(3)
    host.receive_data(
        b"Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\n", 1.1
    )
    assert host.data_to_send(1.1) == frame(2, "G1 X2")
    host.receive_data(b"ok\n", 1.102)
    assert acked(host) == [1, 2]


def test_a_heat_up_does_not_stretch_the_retransmission_timeout() -> None:
    # An unbuffered command's ok comes once the machine finished it: 20 s of heating is
    # not a round trip. Counted as one, it held the timeout at 5 s for hundreds of lines,
    # and the next dropped line (OctoPrint's virtual printer drops one) waited that long.
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    host.send("G1 X1", 0)
    host.data_to_send(1.0)
    host.receive_data(b"ok\n", 1.002)
    host.send("M109 S200", 1)
    assert host.data_to_send(1.002) == frame(2, "M109 S200")
    host.receive_data(b"ok\n", 21.0)
    host.send("G1 X2", 2)
    host.send("G1 X3", 3)
    assert host.data_to_send(21.0) == frame(3, "G1 X2")
    host.receive_data(b"ok\n", 21.002)
    assert host.retransmission_timeout == MIN_RTO
    assert host.data_to_send(21.002) == frame(4, "G1 X3")
    host.receive_data(b"Error: No Line Number with checksum, Last Line: 3\n", 21.004)
    deadline = host.next_deadline()
    assert deadline is not None and deadline <= 21.004 + MIN_RTO
    host.handle_timeout(deadline)
    assert host.data_to_send(deadline) == ping(5)
    host.receive_data(
        b"Error:Line Number is not Last Line Number+1, Last Line: 3\nResend: 4\n", deadline
    )
    assert host.data_to_send(deadline) == frame(4, "G1 X3")
    host.receive_data(b"ok\n", deadline + 0.002)
    assert acked(host) == [1, 2, 3, 4]


def test_lines_sent_behind_a_heat_up_do_not_stretch_the_retransmission_timeout() -> None:
    # Buffered: the lines sent behind an M109 wait in the controller until it is done,
    # so their oks come as late as its own.
    host = greeted(FlowControl(FlowMode.BUFFERED))
    host.send("G1 X1", 0)
    host.data_to_send(1.0)
    host.receive_data(b"ok\n", 1.002)
    host.send("M109 S200", 1)
    for i in range(2, 6):
        host.send(f"G1 X{i}", i)
    host.data_to_send(1.002)
    host.receive_data(b"ok\n" * 5, 21.0)
    assert acked(host) == [1, 2, 3, 4, 5, 6]
    assert host.retransmission_timeout == MIN_RTO


def test_a_probe_after_a_stall_never_repeats_the_greetings_probe() -> None:
    host = greeted(FlowControl(FlowMode.UNBUFFERED))
    now = 1.0
    for i in range(5):
        host.send(f"G1 X{i}", i)
        host.data_to_send(now)
        now += 0.002
        host.receive_data(b"ok\n", now)
    host.request_sync()
    assert host.data_to_send(now) == ping(6)
    sent = []
    for _ in range(3):  # the answers are lost
        deadline = host.next_deadline()
        assert deadline is not None
        host.handle_timeout(deadline)
        sent.append(host.data_to_send(deadline))
    assert ping(1) not in sent  # the greeting's probe, N1 M105 S0*9999
    assert sent == [ping(6)] * 3


def advance(host: RepRapDialect, until: float) -> bytes:
    """Every timeout due up to ``until``, handled; what the host sent for them."""
    sent = b""
    while (deadline := host.next_deadline()) is not None and deadline <= until:
        host.handle_timeout(deadline)
        sent += host.data_to_send(deadline)
    return sent


def test_a_heat_wait_whose_reports_say_it_heats_draws_no_probe() -> None:
    # Marlin's M190 answers once the bed is there, and reports the temperatures every
    # second meanwhile: the host reads them, and asks nothing.
    host = command_probing()
    host.send("M190 S60", 0)
    host.request_sync()
    assert host.data_to_send(0.01) == frame(2, "M190 S60")
    now, bed = 0.01, 21.0
    while bed < 60.0:
        now += 1.0
        bed = min(60.0, bed + 0.5)
        host.receive_data(f" T:21.00 /0.00 B:{bed:.2f} /60.00 @:0 B@:0 W:?\n".encode(), now)
        assert advance(host, now) == b""
    host.receive_data(b"ok\n", now + 8.0)  # its residency over
    assert host.data_to_send(now + 8.0) == frame(3, "M105")  # the sync's probes, and only
    host.receive_data(TEMPERATURES, now + 8.01)
    assert host.data_to_send(now + 8.01) == frame(4, "M105")
    host.receive_data(TEMPERATURES, now + 8.02)
    assert host.is_done and host.stats.pings == 3  # the greeting's, the sync's two


def test_a_heat_wait_long_at_its_target_without_an_ok_is_probed() -> None:
    host = command_probing()
    host.send("M109 S200", 0)
    assert host.data_to_send(0.01) == frame(2, "M109 S200")
    now, sent = 0.01, b""
    while not sent:  # its ok was lost: the reports say the hotend is there, no residency
        now += 1.0
        host.receive_data(b" T:200.00 /200.00 B:21.00 /0.00 @:0 B@:0\n", now)
        sent = advance(host, now)
    # It was over at once (its heater there, no W: said): asked a report's gap later, not
    # after the 30 s a heat wait is given when nothing is heard of it.
    assert sent == frame(3, "M105") and REPORT_GAP < now < 2 * REPORT_GAP
    host.receive_data(TEMPERATURES, now + 0.01)
    assert acked(host) == [2]


def test_a_probe_unanswered_is_followed_by_the_next_line_not_a_copy() -> None:
    # Marlin 2.1 drops a copy of the line it took last without a word: after a probe
    # whose answer was lost, a new one, numbered next, which it takes and answers.
    host = command_probing()
    host.send("G1 X1", 0)
    host.request_sync()
    assert host.data_to_send(0.01) == frame(2, "G1 X1")
    host.receive_data(b"ok\n", 0.012)
    assert host.data_to_send(0.012) == frame(3, "M105")
    now, sent = 0.012, b""
    while not sent:  # its answer is lost
        now = host.next_deadline() or now
        host.handle_timeout(now)
        sent = host.data_to_send(now)
    assert sent == frame(4, "M105")
    host.receive_data(TEMPERATURES, now + 0.01)
    assert host.data_to_send(now + 0.01) == frame(5, "M105")  # the sync's second
    host.receive_data(TEMPERATURES, now + 0.02)
    assert host.is_done


def test_a_probe_given_up_that_answers_late_confirms_no_line_of_the_callers() -> None:
    host = command_probing()
    host.send("G4 S1", 0)
    host.request_sync()
    assert host.data_to_send(0.01) == frame(2, "G4 S1")
    host.receive_data(b"ok\n", 1.02)
    assert host.data_to_send(1.02) == frame(3, "M105")
    now, sent = 1.02, b""
    while not sent:  # the controller is slower than anything says
        now = host.next_deadline() or now
        host.handle_timeout(now)
        sent = host.data_to_send(now)
    assert sent == frame(4, "M105")
    host.receive_data(TEMPERATURES, now + 0.01)  # probe 3's answer, taken as probe 4's
    assert host.data_to_send(now + 0.01) == frame(5, "M105")  # the sync's second
    host.receive_data(TEMPERATURES, now + 0.02)  # probe 4's own, taken as probe 5's
    assert host.is_done
    host.send("G1 X1", 1)
    assert host.data_to_send(now + 0.02) == frame(6, "G1 X1")
    host.receive_data(TEMPERATURES, now + 0.021)  # probe 5's own: not line 6's ok
    assert acked(host) == [2]
    host.receive_data(b"ok\n", now + 0.022)
    assert acked(host) == [6]
