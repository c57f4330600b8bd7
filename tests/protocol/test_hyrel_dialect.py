"""The host's side of Hyrel's link against the simulated Hyrel controller, on simulated time."""

from __future__ import annotations

import re
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from repetrel_host.errors import ControllerError
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.protocol.dialects.hyrel import (
    ANSWER_AT_ONCE,
    KEEPALIVE,
    STATUS_AFTER,
    SYNC_AFTER,
    SYNC_EVERY,
    SYNC_EVERY_MIN,
    SYNC_INTERVAL,
    HyrelDialect,
)
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    DialectFailed,
    FailureKind,
    GreetingRetry,
    LineAcknowledged,
    LineRefused,
)
from repetrel_host.protocol.flow import FlowControl
from repetrel_host.session.loopback import LoopbackResult, run_loopback
from repetrel_host.session.pump import Outcome
from tests.support.helpers import CONE, job_commands

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
    # Among the lines, the host's M115s: one among every 16 of the first (the controller's
    # 8 KB go before an answer says how fast lines run), then one among every 256 (they
    # run in half a second), and the one after the end.
    assert result.executed == commands
    first = 8192 // len("N1 G1 X0 Y0\n") // SYNC_EVERY_MIN
    syncs = result.controller.executed.count("M115")
    assert 5000 // SYNC_EVERY + 1 < syncs <= 5000 // SYNC_EVERY + first
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
    assert result.failure is not None and result.failure.kind is FailureKind.NO_ANSWER
    assert result.failure.reason == "no answer to Hyrel's ping (0x07), sent 3 times in 9 s"
    assert result.executed == []


def test_each_unanswered_ping_is_told_as_it_goes_again() -> None:
    dialect = HyrelDialect(HYREL_WINDOW)
    dialect.start(0.0)
    assert dialect.data_to_send(0.0) == b"\x07"
    told = []
    while dialect.failure is None:
        now = dialect.next_deadline()
        assert now is not None
        dialect.handle_timeout(now)
        assert dialect.data_to_send(now) == (b"" if dialect.failure else b"\x07")
        while (event := dialect.next_event()) is not None:
            told.append(event)
    assert told[:-1] == [GreetingRetry(2, 3, 3.0), GreetingRetry(3, 3, 6.0)]
    assert told[-1] == dialect.failure and dialect.failure.kind is FailureKind.NO_ANSWER


def test_a_line_the_controller_refuses_stops_the_job_naming_it() -> None:
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
    # The job must stop there; the link goes on (the pump aborts, then the safe stop).
    assert dialect.next_event() == LineRefused(
        "the controller says: >ER: checksum mismatch (line 2): not run", "second"
    )
    assert dialect.failure is None and dialect.is_ready


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
    # The job's M115 ran, and the host's after the last line.
    assert result.executed == commands and summary is not None
    assert result.controller.executed == [*commands, "M115"]
    assert summary.seconds >= 20  # the dwell ran before the job was done


def test_an_ack_lost_on_the_way_does_not_hold_the_end_forever() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "one")
    dialect.send("G1 X2", "two")
    dialect.request_sync()
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 G1 X2\nN3 M115\n"
    dialect.receive_data(b"\x06", 0.1)  # the two other ACKs were lost
    assert dialect.next_event() == LineAcknowledged(1, "G1 X1", "one", "")
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra_5 PROTOCOL_VERSION:1.0\n", 0.2)
    # Line 2 ran, so it was received: its ACK was lost (its answer's is the host's own).
    assert dialect.is_done and dialect.next_event() == LineAcknowledged(2, "G1 X2", "two", "")
    assert dialect.next_event() is None and dialect.stats.lost_acks == 2
    assert dialect.next_deadline() == KEEPALIVE  # nothing waits for an ACK


def test_lines_whose_acks_are_lost_get_a_sync_once_they_waited_long() -> None:
    dialect = greeted()
    for i in range(3):
        dialect.send(f"G1 X{i}", i)
    assert dialect.data_to_send(0.0) == b"N1 G1 X0\nN2 G1 X1\nN3 G1 X2\n"
    dialect.receive_data(b"\x06", 0.1)  # the job goes on; two ACKs were lost
    assert dialect.next_deadline() == pytest.approx(0.1 + SYNC_AFTER)
    dialect.handle_timeout(0.1 + SYNC_AFTER)
    assert dialect.data_to_send(0.6) == b"N4 M115\n"  # what ran? (past a full window)
    assert dialect.next_deadline() == pytest.approx(0.1 + STATUS_AFTER)
    dialect.handle_timeout(0.1 + STATUS_AFTER)
    assert dialect.data_to_send(5.1) == b"\x05"  # is it there at all?
    dialect.receive_data(b">ST: T:21.0 /0.0\nFIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 5.2)
    assert [e.tag for e in iter(dialect.next_event, None) if isinstance(e, LineAcknowledged)] == [
        0, 1, 2
    ]  # fmt: skip
    assert dialect.stats.stalls_recovered == 1 and dialect.stats.lost_acks == 3


def test_lines_after_a_quiet_spell_get_their_full_time_before_a_status_request() -> None:
    dialect = greeted()
    dialect.handle_timeout(KEEPALIVE)
    assert dialect.data_to_send(KEEPALIVE) == b"\x0e"
    dialect.send("G28")
    assert dialect.data_to_send(19.9) == b"N1 G28\n"
    assert dialect.next_deadline() == pytest.approx(19.9 + SYNC_AFTER)
    dialect.handle_timeout(19.9 + SYNC_AFTER)
    assert dialect.next_deadline() == pytest.approx(19.9 + STATUS_AFTER)


def greeted() -> HyrelDialect:
    dialect = HyrelDialect(HYREL_WINDOW)
    dialect.start(0.0)
    dialect.data_to_send(0.0)
    dialect.receive_data(b">Hy: Hydra\n", 0.0)
    assert isinstance(dialect.next_event(), ControllerReady)
    return dialect


def test_a_commands_reply_is_complete_once_the_controller_ran_it() -> None:
    dialect = greeted()
    dialect.send("M104 S200", "command", confirm=True)
    # Nothing would say it ran but a notice that may not come: a sync follows it.
    assert dialect.data_to_send(0.0) == b"N1 M104 S200\nN2 M115\n"
    dialect.receive_data(b"\x06", 0.1)  # received: not yet run
    assert dialect.next_event() is None and not dialect.is_done
    dialect.receive_data(b">MC:M104: S200:\n", 0.2)  # it ran: its notice, then the reply
    message = dialect.next_event()
    assert isinstance(message, ControllerMessage) and message.text == ">MC:M104: S200:"
    assert dialect.next_event() == LineAcknowledged(1, "M104 S200", "command", "")
    assert not dialect.is_done  # for that, an answer: what it wrote as it ran all came
    dialect.receive_data(b"\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.3)
    assert dialect.next_event() is None and dialect.is_done  # the sync's answer


def test_a_callers_m115_is_its_own_sync_and_its_answer_is_its_reply() -> None:
    dialect = greeted()
    dialect.send("M115", "who", confirm=True)
    assert dialect.data_to_send(0.0) == b"N1 M115\n"  # its answer will say it ran
    dialect.receive_data(b"\x06", 0.1)
    assert dialect.data_to_send(0.1) == b""
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra_5.1 PROTOCOL_VERSION:1.0\n", 0.2)
    answer = dialect.next_event()
    assert isinstance(answer, ControllerMessage) and answer.text.startswith("FIRMWARE_NAME:")
    assert dialect.next_event() == LineAcknowledged(1, "M115", "who", "")


def test_a_notice_confirms_the_oldest_line_of_its_code_and_every_line_before() -> None:
    dialect = greeted()
    for command in ("G1 X1", "M106 S255", "G1 X2", "M104 S200", "G1 X3", "M104 S0"):
        dialect.send(command, command)
    dialect.send("G1 X4", "last", confirm=True)
    assert dialect.data_to_send(0.0).endswith(b"N7 G1 X4\nN8 M115\n")
    dialect.receive_data(b"\x06" * 8 + b">MC:M104: S200:\n", 0.1)
    events = [dialect.next_event() for _ in range(7)]
    assert [e.tag for e in events if isinstance(e, LineAcknowledged)] == [
        "G1 X1", "M106 S255", "G1 X2", "M104 S200", "G1 X3", "M104 S0"
    ]  # fmt: skip
    assert not dialect.is_done  # up to the first M104 ran, not the line after the second
    dialect.receive_data(b">MC:M104: S0:\n", 0.2)
    assert not dialect.is_done
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.3)
    events = list(iter(dialect.next_event, None))
    assert events[-1] == LineAcknowledged(7, "G1 X4", "last", "") and dialect.is_done


def two_moves_each_with_a_sync() -> HyrelDialect:
    """A greeted dialect that sent G1 X1 and G1 X2, each followed by a sync of its own."""
    dialect = greeted()
    dialect.send("G1 X1", confirm=True)
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 M115\n"
    dialect.send("G1 X2", confirm=True)
    assert dialect.data_to_send(0.1) == b"N3 G1 X2\nN4 M115\n"
    return dialect


def test_an_answer_garbled_or_cut_in_two_is_still_one_answer() -> None:
    dialect = two_moves_each_with_a_sync()
    # One byte of the first answer became a newline, one of the second an "X".
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hy\nra PROTOCOL_VERSION:1.0\n", 0.2)
    events = list(iter(dialect.next_event, None))
    assert [type(e) for e in events] == [LineAcknowledged, ControllerMessage]
    assert not dialect.is_done  # the second half of the first answer is not the second
    assert dialect.data_to_send(0.2) == b"\x05"  # so that something comes between answers
    dialect.receive_data(STATUS_REPORT + b"FIRMWARE_NAXE:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.3)
    assert dialect.is_done


def test_answers_a_garbled_newline_ran_together_count_once_and_the_last_m115_goes_again() -> None:
    dialect = two_moves_each_with_a_sync()
    # The first answer's newline garbled into an "r": it runs into the second, or into
    # itself said again: nothing came between them. Counted once; the last M115 may wait
    # for an answer that came: it goes again, right after itself, and one answer is both's.
    dialect.receive_data(b"\x06\x06\x06\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0r", 0.2)
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.3)
    assert not dialect.is_done
    assert dialect.data_to_send(0.3) == b"\x05N5 M115\n"
    dialect.receive_data(
        STATUS_REPORT + b"\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.4
    )
    assert dialect.is_done and dialect.stats.lost_acks == 0
    events = list(iter(dialect.next_event, None))
    assert [type(e) for e in events if not isinstance(e, ControllerMessage)] == [
        LineAcknowledged
    ] * 2
    # The repeat ran right behind it, at once: its own answer came with the first, or
    # comes now. Not come within ANSWER_AT_ONCE, it came before: nothing waits any longer.
    dialect.handle_timeout(0.4 + ANSWER_AT_ONCE)
    dialect.send("G4 P1000", "dwell", confirm=True)
    assert dialect.data_to_send(1.5).endswith(b"N6 G4 P1000\nN7 M115\n")
    dialect.receive_data(b"\x06\x06" + STATUS_REPORT, 1.51)
    assert not dialect.is_done
    dialect.receive_data(IDENTITY, 2.5)  # the dwell's, taken for its sync's
    assert dialect.is_done and dialect.data_to_send(2.5) == b""


def test_an_ack_inside_two_answers_run_together_does_not_tell_them_apart() -> None:
    dialect = two_moves_each_with_a_sync()
    # The byte between them may be the first's newline, garbled into an ACK: the second
    # is not counted. The last M115 goes again, and one answer is both's.
    dialect.receive_data(b"\x06\x06\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\x06", 0.2)
    dialect.receive_data(IDENTITY, 0.3)
    assert not dialect.is_done
    assert dialect.data_to_send(0.3) == b"\x05N5 M115\n"
    dialect.receive_data(STATUS_REPORT + b"\x06" + IDENTITY, 0.4)
    assert dialect.is_done


def test_answers_run_together_with_acks_between_them_both_count() -> None:
    dialect = two_moves_each_with_a_sync()
    # The first's newline garbled; the second came long after, lines ACKed meanwhile:
    # one garbled byte is one ACK at most, two were written between the answers.
    dialect.receive_data(b"\x06\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0r", 0.2)
    dialect.receive_data(b"\x06\x06FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.3)
    assert dialect.is_done and dialect.stats.lost_acks == 0


def test_an_ack_byte_in_place_of_an_answers_first_letter_does_not_tell_it_apart() -> None:
    dialect = greeted()
    dialect.send("G1 X1", confirm=True)
    dialect.data_to_send(0.0)
    dialect.send("G4 P5000", "dwell", confirm=True)
    assert dialect.data_to_send(0.1) == b"N3 G4 P5000\nN4 M115\n"
    dialect.receive_data(b"\x06" * 4, 0.15)
    # Said twice, the second's "F" garbled into an ACK byte: no byte came between them.
    dialect.receive_data(IDENTITY + b"\x06" + IDENTITY[1:], 0.2)
    assert not dialect.is_done  # the dwell has not run
    dialect.receive_data(STATUS_REPORT, 0.21)
    dialect.receive_data(IDENTITY, 5.1)
    assert dialect.is_done


def test_cancel_aborts_and_what_the_aborted_lines_still_earn_is_not_taken_for_the_safe_stop() -> (
    None
):
    dialect = greeted()
    dialect.send("M109 S200", "heat")
    dialect.send("G1 X1", "move")
    dialect.request_sync()
    assert dialect.data_to_send(0.0).endswith(b"N3 M115\n")  # waits behind the heat-up
    dialect.receive_data(b"\x06\x06", 0.1)
    assert len(list(iter(dialect.next_event, None))) == 2
    assert dialect.abort()
    dialect.send("M104 S0", "off", urgent=True)
    dialect.request_sync()
    # No sync yet: the aborted M115's answer may still come (if it ran before the abort).
    assert dialect.data_to_send(0.2) == b"\x08\x09N4 M104 S0\n"
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n\x06", 0.2)
    assert list(iter(dialect.next_event, None)) == [] and not dialect.is_done  # and its ACK
    assert dialect.data_to_send(0.2) == b"N5 M115\n"  # it came: the sync may go
    dialect.receive_data(b"\x06\x06", 0.3)  # the safe stop's line, the sync
    assert dialect.next_event() == LineAcknowledged(4, "M104 S0", "off", "")
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 0.4)  # its ACK first
    assert dialect.is_done


def test_pause_resume_m108_and_m112_are_control_bytes() -> None:
    dialect = greeted()
    assert dialect.hold() and dialect.data_to_send(0.0) == b"\x02"
    assert dialect.hold(at_layer_end=True) and dialect.data_to_send(0.0) == b"\x03"
    dialect.end_wait()
    assert dialect.data_to_send(0.0) == b"\x01"
    dialect.send_urgent("M108")
    assert dialect.data_to_send(0.0) == b"\x01"
    dialect.send("G1 X1")
    dialect.send_urgent("M112")  # ahead of what is queued, after an abort
    assert dialect.data_to_send(0.0) == b"\x08\x09N1 M112\nN2 G1 X1\n"
    assert dialect.pause_command == "M0"


def test_an_error_naming_a_line_names_its_source_and_a_reboot_fails_the_stream() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "first")
    dialect.send("T7", "second")
    dialect.data_to_send(0.0)
    dialect.receive_data(b"\x06\x06>ER: N2: no head in that slot\n", 0.1)
    events = list(iter(dialect.next_event, None))
    assert isinstance(events[-1], ControllerMessage) and events[-1].tag == "second"
    dialect.receive_data(b">Hy: Hydra_5.1 booted\n", 10.0)  # unasked: it restarted
    failed = dialect.next_event()
    assert isinstance(failed, DialectFailed) and failed.kind is FailureKind.RESET
    assert failed.reason == "the controller reset (it says: >Hy: Hydra_5.1 booted)"


# A job of moves with M-codes among them (whose notices confirm what ran), and a dwell.
NOISY_JOB = [
    command
    for i in range(1500)
    for command in (f"G1 X{i % 200} Y{i % 7} E{i * 0.01:.2f}", *(("M106 S128",) * (i % 50 == 0)))
] + ["G4 P500", "M104 S0"]


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_lost_acks_and_garbled_replies_still_run_every_line_exactly_once(seed: int) -> None:
    # So many ACKs lost that the window would fill with lines whose ACK never comes: the
    # answers of the syncs among the lines release them.
    faults = Faults(drop_ok=0.1, garble=0.02, seed=seed)
    result = stream(NOISY_JOB, move_time=0.001, latency=0.001, bandwidth=11_520, faults=faults)
    assert result.failure is None and result.run.outcome is Outcome.COMPLETED
    assert result.executed == NOISY_JOB
    controller = result.controller
    assert controller.link.bytes_dropped == 0  # the window kept the buffer from overflowing
    assert controller.counts.dropped_oks > 20 and controller.counts.garbled_replies > 0
    assert result.acknowledged == list(range(len(NOISY_JOB)))
    assert result.host.stats.lost_acks > 50  # released by the answers of the syncs


class CorruptsOneLine(HyrelControllerSimulator):
    """Changes a digit of the job's line 200 on its way, as a noisy wire would."""

    def _maybe_corrupt(self, piece: bytes) -> bytes:
        return piece.replace(b" G1 X199*", b" G1 X198*")


def test_a_line_refused_for_its_checksum_is_named_and_the_controller_aborts() -> None:
    commands = [f"G1 X{i}" for i in range(1000)]
    settings = ControllerSettings(rx_buffer=8192, banner=False, move_time=0.01, latency=0.001)
    result = run_loopback(
        commands,
        dialect=HyrelDialect(HYREL_WINDOW, checksum=True),
        controller=CorruptsOneLine(settings),
    )
    assert result.failure is None  # the link goes on: the job stopped
    error = result.run.error
    assert isinstance(error, ControllerError)
    assert re.search(r"checksum mismatch \(line \d+\): not run \(at job:200\)", str(error))
    assert "the last line the controller acknowledged is job:" in str(error)
    # In order without it, and not far past it: the abort came within a round trip (and
    # dropped what the controller held, lines before it in its command slots too).
    executed = result.executed
    assert executed == [c for c in commands if c != "G1 X199"][: len(executed)]
    assert 150 < len(executed) <= 199 + 20


def test_an_abort_while_acks_were_held_back_waits_for_what_it_left_behind() -> None:
    dialect = greeted()
    dialect.send("G1 X1")
    dialect.data_to_send(0.0)
    dialect.handle_timeout(SYNC_AFTER)  # a full buffer holds the ACK back: a sync goes
    assert dialect.data_to_send(SYNC_AFTER) == b"N2 M115\n"
    assert dialect.abort()  # it was dropped with the line, or ran: its answer may come
    dialect.send("M104 S0", "off", urgent=True)
    dialect.request_sync()
    assert dialect.data_to_send(1.0) == b"\x08\x09N3 M104 S0\n"  # no sync yet
    dialect.receive_data(b"\x06\x06\x06", 1.1)  # the two dropped lines', the safe stop's
    assert dialect.data_to_send(1.1) == b"N4 M115\n"  # every answer left behind came first
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", 1.2)
    assert dialect.is_done


def test_a_garbled_notice_confirms_no_line_that_has_not_run() -> None:
    dialect = greeted()
    job = ["M107", *(f"G1 X{i}" for i in range(50)), "M106 S255", *(f"G1 Y{i}" for i in range(50))]
    for command in job:
        dialect.send(command, command)
    dialect.request_sync()
    dialect.data_to_send(0.0)
    dialect.receive_data(b"\x06" * 10, 0.1)  # ten received so far
    assert len(list(iter(dialect.next_event, None))) == 10
    # The M107's notice, its 7 garbled into a 6: a notice names the oldest M-code not known
    # to have run, or nothing.
    dialect.receive_data(b">MC:M106:\n", 0.2)
    assert [type(e) for e in iter(dialect.next_event, None)] == [ControllerMessage]
    assert dialect.stats.lost_acks == 0 and not dialect.is_done
    # Nor does a notice alone say a job is done: only an answer does.
    dialect.receive_data(b">MC:M107:\n", 0.3)
    assert not dialect.is_done


def test_an_answer_cut_by_a_garbled_colon_is_no_reset() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "line")
    dialect.request_sync()
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 M115\n"
    dialect.receive_data(b"\x06\x06FIRMWARE_NAME\n>Hy: Hydra_5 PROTOCOL_VERSION:1.0\n", 0.1)
    events = list(iter(dialect.next_event, None))
    assert not any(isinstance(e, DialectFailed) for e in events) and dialect.is_done


def test_what_ran_of_a_job_is_its_line_not_a_command_confirmed_after_it() -> None:
    # A session's M105 (poll_while_printing) among a job's lines, confirmed by the same
    # answer: the last job line known to have run is still the job's (the resume hint).
    from repetrel_host.fakes.hyrel_simulator import M115_REPLY, PING_REPLY
    from repetrel_host.protocol.hyrel import Control
    from repetrel_host.session.job import JobLine

    dialect = HyrelDialect(HYREL_WINDOW)
    dialect.start(0.0)
    dialect.data_to_send(0.0)
    dialect.receive_data(PING_REPLY, 0.0)
    line = JobLine(1, 1, "G1 X1", 6, "job.gcode")
    dialect.send("G1 X1", line)
    dialect.send("M105", "the session's poll", confirm=True)
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 M105\nN3 M115\n"
    dialect.receive_data(bytes([Control.ACK]) * 3 + b">ST: T0:21.0/0\n" + M115_REPLY, 0.1)
    assert dialect.last_ran is line


# --- what ran: the notices of the M-codes the controller reports, and the syncs ---------


def sent_lines(dialect: HyrelDialect, commands: list[str], now: float) -> bytes:
    """``commands`` queued (tagged with their indexes) and what goes on the wire."""
    for command in commands:
        dialect.send(command, command)
    return dialect.data_to_send(now)


def test_m_codes_the_controller_never_notices_hold_back_no_notice_after_them() -> None:
    # PrusaSlicer's M73 (progress) first: the controller says nothing of it, nor of M82.
    dialect = greeted()
    job = ["M73 P0 R12", "M104 S200", "M82", "G1 X1", "M106 S255", "G1 X2"]
    assert sent_lines(dialect, job, 0.0) == (
        b"N1 M73 P0 R12\nN2 M104 S200\nN3 M82\nN4 G1 X1\nN5 M106 S255\nN6 G1 X2\n"
    )
    dialect.receive_data(b"\x06" * 6, 0.1)
    assert dialect.last_ran is None  # received, not run
    dialect.receive_data(b">MC:M104: S200:\n", 0.2)
    assert dialect.last_ran == "M104 S200"
    dialect.receive_data(b">MC:M106: S255:\n", 0.3)
    assert dialect.last_ran == "M106 S255"


def test_a_lost_notice_holds_back_none_after_it() -> None:
    dialect = greeted()
    job = ["M104 S200", "G1 X1", "M106 S255", "G1 X2", "M107", "G1 X3"]
    sent_lines(dialect, job, 0.0)
    dialect.receive_data(b"\x06" * 6, 0.1)
    # The M104's notice was lost (or garbled): the controller runs lines in order, so the
    # M106's says the M104 ran too.
    dialect.receive_data(b">MC:M106: S255:\n", 0.2)
    assert dialect.last_ran == "M106 S255"
    dialect.receive_data(b">MC:M107:\n", 0.3)
    assert dialect.last_ran == "M107"


def test_a_notice_is_taken_only_for_a_line_it_may_be_about() -> None:
    dialect = greeted()
    job = ["M106 S128", "G1 X1", "M104 S200", "G1 X2", "M106 S128", "G1 X3", "M104 S0", "G1 X4"]
    for index, command in enumerate(job):
        dialect.send(command, index)
    assert dialect.data_to_send(0.0) == b"".join(
        f"N{number} {command}\n".encode() for number, command in enumerate(job, start=1)
    )
    # No ACK yet: the controller has none of these lines, no notice is about one of them.
    dialect.receive_data(b">MC:M106: S128:\n", 0.1)
    assert dialect.last_ran is None
    dialect.receive_data(b"\x06" * 4, 0.2)  # the first four received
    for notice in (
        b">MC:M104: S210:\n",  # values no line has
        b">MC:M109: S200:\n",  # a code the host did not send
        b">MC:M104: S2\xb10:\n",  # a byte garbled: what it says cannot be told
        b">MC:M104:\n",  # cut short by a byte garbled into a newline: no line's with an S
    ):
        dialect.receive_data(notice, 0.3)
        assert dialect.last_ran is None, notice
    # The second M106 S128's, the first's lost? It is taken for the first, no further.
    dialect.receive_data(b">MC:M106: S128:\n", 0.4)
    assert dialect.last_ran == 0
    # The M104 S0 is not received yet: no notice is about it.
    dialect.receive_data(b">MC:M104: S0:\n", 0.5)
    assert dialect.last_ran == 0
    # Received, it ran: so did the lines before it whose notices were lost.
    dialect.receive_data(b"\x06" * 4 + b">MC:M104: S0:\n", 0.6)
    assert dialect.last_ran == 6
    # A notice of a line known to have run (late, repeated) is taken for nothing.
    dialect.receive_data(b">MC:M106: S128:\n", 0.7)
    assert dialect.last_ran == 6


def answer(dialect: HyrelDialect, now: float) -> None:
    dialect.receive_data(b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n", now)


def syncs_among(data: bytes) -> list[int]:
    """The numbers of the M115 lines in ``data``."""
    return [int(line.split()[0][1:]) for line in data.splitlines() if line.endswith(b" M115")]


def test_syncs_go_among_as_many_lines_as_run_in_a_sync_interval() -> None:
    dialect = greeted()
    moves = [f"G1 X{i}" for i in range(100)]
    # Before an answer says how fast lines run: one among every SYNC_EVERY_MIN of them.
    data = sent_lines(dialect, moves[:20], 0.0)
    assert b"N16 G1 X15\nN17 M115\nN18 G1 X16\n" in data and syncs_among(data) == [17]
    dialect.receive_data(b"\x06" * 21, 0.01)
    # 16 lines (and the sync) ran in 0.1 s: 170 a second, but the count at most doubles
    # with each answer (the first lines only filled the planner, at once).
    answer(dialect, 0.1)
    assert dialect.last_ran == "G1 X15"
    data = sent_lines(dialect, moves[20:60], 0.1)
    assert syncs_among(data) == [21 + 28 + 1]  # 32 lines after the last sync
    dialect.receive_data(b"\x06" * 41, 0.11)
    # Those 32 lines and the sync ran in the next SYNC_INTERVAL: one among every 33 lines.
    answer(dialect, 0.1 + SYNC_INTERVAL)
    assert dialect.last_ran == "G1 X47"
    assert syncs_among(sent_lines(dialect, moves[60:100], 2.0)) == [62 + 21 + 1]


def watch_what_ran(commands: list[str], settings: ControllerSettings) -> tuple[int, int]:
    """Stream ``commands`` (tagged 1, 2, ...) to the simulated controller; return how far
    :attr:`HyrelDialect.last_ran` ever was ahead of what the controller ran (never past
    it: 0 at most) and behind it, at every step. The job is done only once the controller
    ran every line, each once."""
    ran = 0
    run: list[str] = []

    def executed(command: str) -> None:
        nonlocal ran
        if command != "M115":
            ran += 1
            run.append(command)

    dialect = HyrelDialect(HYREL_WINDOW)
    controller = HyrelControllerSimulator(settings, on_execute=executed)
    lines = iter(enumerate(commands, start=1))
    now, wire, queued = 0.0, bytearray(), False
    ahead, behind = -len(commands), 0
    dialect.start(now)
    while not (queued and dialect.is_done):
        assert dialect.failure is None
        while not queued and dialect.wants_lines:
            line = next(lines, None)
            if line is None:
                dialect.request_sync()
                queued = True
            else:
                dialect.send(line[1], line[0])
        dialect.handle_timeout(now)
        sent = dialect.data_to_send(now)
        wire += sent
        controller.receive_from(wire, now)
        controller.advance(now)
        received = controller.take_output(now)
        dialect.receive_data(received, now)
        while dialect.next_event() is not None:
            pass
        last = dialect.last_ran
        assert last is None or isinstance(last, int)
        ahead, behind = max(ahead, (last or 0) - ran), max(behind, ran - (last or 0))
        if not (sent or received):
            upcoming = [
                t for t in (controller.next_wakeup(), dialect.next_deadline()) if t is not None
            ]
            now = max(min(upcoming), now + 1e-9)
    assert run == commands  # done once the last line ran, every line once, in order
    return ahead, behind


MOVE_TIME = 0.02  # 50 moves a second: a slow job


NOISE = [
    *(Faults(drop_ok=0.05, garble=0.05, seed=seed) for seed in (1, 2, 3)),
    Faults(drop_ok=0.05, garble=0.05, identity_twice=0.3, seed=4),
]


@pytest.mark.parametrize("faults", [Faults(), *NOISE])
def test_what_ran_follows_a_slow_job_and_is_never_ahead_of_it(faults: Faults) -> None:
    # A real PrusaSlicer job, with its M73 first (the controller notices neither it nor
    # M82, M204...), over a 115,200 baud link.
    commands = ["M73 P0 R12", *job_commands(CONE)[:3000]]
    settings = ControllerSettings(
        rx_buffer=8192,
        banner=False,
        move_time=MOVE_TIME,
        latency=0.001,
        bandwidth=11_520,
        faults=faults,
    )
    ahead, behind = watch_what_ran(commands, settings)
    assert ahead <= 0
    # Behind by what runs between two syncs: a SYNC_INTERVAL's worth, and a little more
    # where the count is learnt (answers lost or late).
    assert behind <= 1.25 * SYNC_INTERVAL / MOVE_TIME


# Notices of all kinds among moves, some without values: a garbled byte must not make one
# pass for a later line's.
CODES = ["M107", "M106", "M106 S255", "M104 S200", "M73 P1", "M82", "M104 S0"]
NOTICED_JOB = [
    command
    for i in range(3000)
    for command in (f"G1 X{i % 100} Y{i % 7} E{i * 0.01:.2f}", *(CODES[i % 7],) * (i % 5 == 0))
]


@pytest.mark.parametrize("seed", range(16))
def test_garbled_notices_and_lost_acks_never_put_what_ran_ahead(seed: int) -> None:
    faults = Faults(drop_ok=0.1, garble=0.2, seed=seed)
    settings = ControllerSettings(
        rx_buffer=8192,
        banner=False,
        move_time=0.005,
        latency=0.001,
        bandwidth=11_520,
        faults=faults,
    )
    ahead, _ = watch_what_ran(NOTICED_JOB, settings)
    assert ahead <= 0


IDENTITY = b"FIRMWARE_NAME:>Hy: Hydra PROTOCOL_VERSION:1.0\n"
STATUS_REPORT = b">ST: T:20.0 /0.0 B:20.0 /0.0\n"


def test_an_identity_said_twice_at_once_answers_one_m115() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "before", confirm=True)
    assert dialect.data_to_send(0.0) == b"N1 G1 X1\nN2 M115\n"
    dialect.send("G4 P5000", "dwell")
    dialect.send("G1 X2", "after", confirm=True)
    assert dialect.data_to_send(0.1) == b"N3 G4 P5000\nN4 G1 X2\nN5 M115\n"
    dialect.receive_data(b"\x06" * 5, 0.11)
    # The first M115 ran; the controller says so twice. The second M115 waits behind the
    # dwell: taken for its answer, the repeat would call the dwell and G1 X2 run.
    dialect.receive_data(IDENTITY * 2, 0.2)
    events = list(iter(dialect.next_event, None))
    told = [e.tag for e in events if isinstance(e, LineAcknowledged)]
    assert told == ["dwell", "before"]  # the dwell received (its ACK), G1 X1 run
    assert dialect.last_ran is None and not dialect.is_done
    # Something between this answer and the next; and the last M115, which may wait for
    # an answer not taken, goes again right after itself.
    assert dialect.data_to_send(0.2) == b"\x05N6 M115\n"
    dialect.receive_data(STATUS_REPORT, 0.21)
    dialect.receive_data(IDENTITY, 5.2)  # its own answer, once the dwell ended
    assert dialect.last_ran == "dwell" and dialect.is_done


def test_an_identity_quoted_in_a_message_is_no_answer() -> None:
    dialect = greeted()
    dialect.send("G4 P5000", "dwell")
    dialect.send("G1 X2", "after", confirm=True)
    assert dialect.data_to_send(0.0) == b"N1 G4 P5000\nN2 G1 X2\nN3 M115\n"
    dialect.receive_data(b"\x06" * 3, 0.01)
    dialect.receive_data(b">IN: " + IDENTITY + b">GB: identity FIRMWARE_NAME:>Hy: Hydra\n", 5.0)
    events = list(iter(dialect.next_event, None))
    assert [type(e) for e in events] == [LineAcknowledged] + [ControllerMessage] * 2
    assert dialect.last_ran is None and not dialect.is_done  # the dwell received, not run
    dialect.receive_data(IDENTITY, 5.1)
    assert dialect.last_ran == "dwell" and dialect.is_done


def test_two_answers_taken_for_one_leave_no_lag_the_last_m115_goes_again() -> None:
    """Two M115s ran with nothing said between them, their answers read at once: taken
    for one answer said twice (what cannot be told is not counted). The second M115 is
    asked again, right after itself: one answer is both's, and the next ones count."""
    dialect = greeted()
    dialect.send("G1 X1", "first", confirm=True)
    dialect.data_to_send(0.0)
    dialect.send("G1 X2", "second", confirm=True)
    assert dialect.data_to_send(0.01) == b"N3 G1 X2\nN4 M115\n"
    dialect.receive_data(b"\x06" * 4, 0.02)
    dialect.receive_data(IDENTITY * 2, 0.1)
    events = list(iter(dialect.next_event, None))
    assert [e.tag for e in events if isinstance(e, LineAcknowledged)] == ["first"]
    assert not dialect.is_done
    assert dialect.data_to_send(0.1) == b"\x05N5 M115\n"  # the last M115, again
    assert dialect.data_to_send(0.2) == b""  # once
    dialect.receive_data(STATUS_REPORT + b"\x06", 0.2)
    dialect.receive_data(IDENTITY, 0.3)
    events = list(iter(dialect.next_event, None))
    assert [e.tag for e in events if isinstance(e, LineAcknowledged)] == ["second"]
    assert dialect.is_done
    # The repeat, right behind it, not answered at once: its answer came before. Nothing
    # waits for an answer that came: the next line's sync is answered as usual.
    dialect.handle_timeout(0.3 + ANSWER_AT_ONCE)
    dialect.send("G1 X3", "third", confirm=True)
    assert dialect.data_to_send(2.0) == b"N6 G1 X3\nN7 M115\n"
    dialect.receive_data(b"\x06\x06", 2.01)  # its ACK, between the answers
    dialect.receive_data(IDENTITY, 2.1)
    assert dialect.is_done
    events = list(iter(dialect.next_event, None))
    assert [e.tag for e in events if isinstance(e, LineAcknowledged)] == ["third"]


def test_a_notice_after_an_m115_whose_answer_was_taken_for_a_repeat_drops_it() -> None:
    dialect = greeted()
    dialect.send("G1 X1", "first", confirm=True)
    dialect.data_to_send(0.0)
    dialect.send("G1 X2", "second", confirm=True)
    dialect.data_to_send(0.01)
    dialect.send("M106 S255", "fan")
    dialect.send("G1 X3", "third", confirm=True)
    assert dialect.data_to_send(0.02) == b"N5 M106 S255\nN6 G1 X3\nN7 M115\n"
    dialect.receive_data(b"\x06" * 7, 0.03)
    dialect.receive_data(IDENTITY * 2, 0.1)  # the second taken for a repeat
    # The fan's notice: the M115 before it ran, its answer came before the notice.
    dialect.receive_data(b">MC:M106: S255:\n", 0.2)
    dialect.receive_data(IDENTITY, 0.3)  # the last M115's
    assert dialect.is_done and dialect.data_to_send(0.3) == b""
    events = list(iter(dialect.next_event, None))
    told = [e.tag for e in events if isinstance(e, LineAcknowledged)]
    assert told == ["fan", "first", "second", "third"]  # the fan's at its ACK


def test_answers_run_together_by_a_garbled_newline_are_one_without_an_ack_between() -> None:
    dialect = greeted()
    dialect.send("G1 X1", confirm=True)
    dialect.data_to_send(0.0)
    dialect.send("G4 P5000", "dwell")
    dialect.send("G1 X2", confirm=True)
    dialect.data_to_send(0.1)
    dialect.receive_data(b"\x06" * 5, 0.11)
    # An answer said twice, the first's newline garbled: one line, nothing between them.
    dialect.receive_data(IDENTITY[:-1] + b"r" + IDENTITY, 0.2)
    assert dialect.last_ran is None and not dialect.is_done


# A dwell with moves before and after it: the M115s among them answered twice, the
# identity quoted unasked after the dwell, on a clean or a noisy link.
DWELL_JOB = [
    *(f"G1 X{i} Y1" for i in range(40)),
    "G4 P2000",
    *(f"G1 X{i} Y2" for i in range(48)),
    "M104 S0",
    *(f"G1 X{i} Y3" for i in range(30)),
]
IDENTITY_FAULTS = [
    Faults(identity_twice=1.0),
    Faults(unasked_identity=1.0),
    *(
        Faults(identity_twice=0.3, unasked_identity=1.0, drop_ok=0.05, garble=0.02, seed=seed)
        for seed in range(1, 9)
    ),
]


@pytest.mark.parametrize("faults", IDENTITY_FAULTS)
def test_an_identity_said_twice_or_unasked_never_calls_a_line_run_before_it_ran(
    faults: Faults,
) -> None:
    settings = ControllerSettings(
        rx_buffer=8192, banner=False, move_time=0.02, latency=0.001, bandwidth=11_520,
        faults=faults,
    )  # fmt: skip
    # Never ahead of the controller (the resume point, were the link cut in the dwell, is
    # not past the first line it did not run), done once its last line ran, each once.
    ahead, _ = watch_what_ran(DWELL_JOB, settings)
    assert ahead <= 0


HYREL_COMMANDS = [
    "G1 X1 Y2 E0.1", "G1 X20 Y5", "G4 P300", "G4 P0", "M104 S0", "M106 S255", "M107",
    "M82", "M73 P5",
]  # fmt: skip


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    commands=st.lists(st.sampled_from(HYREL_COMMANDS), min_size=1, max_size=400),
    twice=st.sampled_from([0.0, 0.3, 1.0]),
    unasked=st.sampled_from([0.0, 1.0]),
    drop=st.sampled_from([0.0, 0.05]),
    garble=st.sampled_from([0.0, 0.02]),
    seed=st.integers(0, 2**16),
)
def test_any_job_under_the_links_faults_runs_once_and_is_never_called_run_early(
    commands: list[str], twice: float, unasked: float, drop: float, garble: float, seed: int
) -> None:
    faults = Faults(
        identity_twice=twice, unasked_identity=unasked, drop_ok=drop, garble=garble, seed=seed
    )
    settings = ControllerSettings(
        rx_buffer=8192, banner=False, move_time=0.005, latency=0.001, bandwidth=11_520,
        faults=faults,
    )  # fmt: skip
    ahead, _ = watch_what_ran(commands, settings)
    assert ahead <= 0
