"""Hyrel's own link, both sides of the wire: framing, ACK credit, control bytes, notices."""

from __future__ import annotations

import pytest

from repetrel_host.protocol import replies
from repetrel_host.protocol.hyrel import (
    Control,
    ControllerReceiver,
    HostReceiver,
    HyrelNotice,
    ReceivedControl,
    ReceivedLine,
    additive_checksum,
    frame,
    mark_urgent,
    parse_notice,
    read_line,
)
from repetrel_host.protocol.reports import ReportReader


def test_lines_are_framed_with_an_optional_number_and_additive_checksum() -> None:
    assert frame("G1 X5") == b"G1 X5\n"
    assert frame("G1 X5", number=14) == b"N14 G1 X5\n"
    body = b"N14 G1 X5"
    assert additive_checksum(body) == sum(body) == 504
    assert frame("G1 X5", number=14, checksum=True) == b"N14 G1 X5*504\n"
    assert mark_urgent(frame("M107")) == b"\x09M107\n"


def test_the_controller_reads_lines_numbers_checksums_and_urgent_marks() -> None:
    assert read_line(b"N14 G1 X5*504") == ReceivedLine("G1 X5", 14, False, True)
    assert read_line(b"N14 G1 X5*505") == ReceivedLine("G1 X5", 14, False, False)
    assert read_line(b"\x09M107") == ReceivedLine("M107", None, True, True)
    assert read_line(b"N14 ; set line numbers") == ReceivedLine("", 14, False, True)
    assert read_line(b"; a comment") is None and read_line(b"") is None


def test_control_bytes_act_at_once_between_and_inside_lines() -> None:
    receiver = ControllerReceiver()
    got = receiver.feed(b"G1 X1\n\x07G1 X")
    assert got == [ReceivedLine("G1 X1", None, False), ReceivedControl(Control.PING)]
    # An abort in the middle of a line acts at once; the line goes on where it was.
    got = receiver.feed(b"2\x08\n\x09M104 S0\n")
    assert got == [
        ReceivedControl(Control.ABORT),
        ReceivedLine("G1 X2", None, False),
        ReceivedLine("M104 S0", None, True),
    ]


def test_the_host_counts_acks_wherever_they_come_and_keeps_the_text() -> None:
    receiver = HostReceiver()
    assert receiver.feed(b"\x06\x06>IN:  50: **  Begin M") == []
    assert receiver.feed(b"773\x06 - print job metrics Report\n>MC:M109: T11: S200:\n\x01") == [
        ">IN:  50: **  Begin M773 - print job metrics Report",
        ">MC:M109: T11: S200:",
    ]
    assert receiver.take_acks() == 3 and receiver.take_acks() == 0
    assert receiver.end_wait_echoes == 1
    report = replies.classify(">MC:M109: T11: S200:")
    assert report == replies.HyrelReport("MC", "M109: T11: S200:")


@pytest.mark.parametrize(
    ("text", "notice"),
    [
        ("M109: T11: S200:", HyrelNotice("M109", {"T": "11", "S": "200"})),
        ("M30:", HyrelNotice("M30", {})),
        ("m06: T12: Z-0.25:", HyrelNotice("M6", {"T": "12", "Z": "-0.25"})),
        ("G28 done", None),
        ("", None),
    ],
)
def test_m_code_notices_are_read(text: str, notice: HyrelNotice | None) -> None:
    assert parse_notice(text) == notice


def test_the_m773_report_is_picked_out_of_the_controllers_lines() -> None:
    reader = ReportReader()
    lines = [
        ">IN:  50: ******",  # not the report's: no Begin follows
        ">MC:M30:",
        ">IN:  50: ******",
        ">IN:  50: **  Begin M773 - print job metrics Report",
        ">IN:  50: ******",
        ">IN:  50: Totals:                   12.5       0.317",
        ">IN:  50: approx filament (PI*d)    0.132 m",
        ">IN:  50: unprimes issued:          3",
        ">IN:  50: **  End M773 Report",
        ">IN:  50: ******",
        ">IN:  50: next",
    ]
    shown = [line for text in lines for line in reader.feed(text)]
    assert shown == [">IN:  50: ******", ">MC:M30:", ">IN:  50: next"]
    report = reader.report
    assert report is not None and report.complete and report.lines[0] == "******"
    assert report.lines[1] == "**  Begin M773 - print job metrics Report"
    assert report.lines[-2:] == ("**  End M773 Report", "******")
    assert report.fields == {
        "Totals": ["12.5", "0.317"],
        "approx filament (PI*d)": ["0.132 m"],
        "unprimes issued": ["3"],
    }
    cut = ReportReader()
    for text in lines[2:6]:
        cut.feed(text)
    assert cut.report is not None and not cut.report.complete


def test_the_host_tells_where_acks_came_among_the_lines() -> None:
    receiver = HostReceiver()
    assert receiver.feed(b"\x06FIRMWARE_NAME: a\nFIRMWARE_NAME: a\nFIRM") == [
        "FIRMWARE_NAME: a",
        "FIRMWARE_NAME: a",
    ]
    # An ACK before the first; nothing between the first and the second: written together.
    assert receiver.acked_ahead == [True, False] and receiver.acks_before == [1, 1]
    assert receiver.take_acks() == 1
    # An ACK inside a line (not between it and the line before), one after it, one in the
    # next before its text, one after the last line: in the order they came.
    assert receiver.feed(b"WARE\x06_NAME: b\n\x06\n\x06>MC:M107:\n\x06") == [
        "FIRMWARE_NAME: b",
        ">MC:M107:",
    ]
    assert receiver.acked_ahead == [False, True] and receiver.acks_before == [1, 3]
    assert receiver.take_acks() == 4
