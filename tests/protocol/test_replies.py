"""Reply classification (docs/protocol.md and docs/hyrel-link.md)."""

import pytest

from repetrel_host.protocol.replies import (
    Busy,
    Error,
    HyrelReport,
    Ok,
    OtherReply,
    Reply,
    ResendRequest,
    Start,
    Wait,
    classify,
)


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        ("ok", Ok()),
        ("ok T:200.0 /200.0 B:60.0 /60.0", Ok("T:200.0 /200.0 B:60.0 /60.0")),
        ("ok N12 P15 B3", Ok("N12 P15 B3", line_number=12, planner_free=15, slots_free=3)),
        ("Resend: 42", ResendRequest(42)),
        ("Resend:42", ResendRequest(42)),
        ("rs 42", ResendRequest(42)),
        ("rs N42", ResendRequest(42)),
        (
            "Error:checksum mismatch, Last Line: 41",
            Error("checksum mismatch, Last Line: 41", line_error=True),
        ),
        (
            "Error:Line Number is not Last Line Number+1, Last Line: 41",
            Error("Line Number is not Last Line Number+1, Last Line: 41", line_error=True),
        ),
        (
            "Error:No Checksum with line number, Last Line: 41",
            Error("No Checksum with line number, Last Line: 41", line_error=True),
        ),
        (
            "Error:MINTEMP triggered, system stopped!",
            Error("MINTEMP triggered, system stopped!", False),
        ),
        ("!! thermal runaway", Error("thermal runaway", line_error=False)),
        ("echo:busy: processing", Busy("echo:busy: processing")),
        ("wait", Wait()),
        ("start", Start()),
        (
            ">IN:  50: **  Begin M773 - print job metrics Report",
            HyrelReport("IN", " 50: **  Begin M773 - print job metrics Report"),
        ),
        (">ER: head 11 not responding", HyrelReport("ER", "head 11 not responding")),
        ("// action:pause", OtherReply("// action:pause")),
        ('echo:Unknown command: "G999"', OtherReply('echo:Unknown command: "G999"')),
        ("okay then", OtherReply("okay then")),
    ],
)
def test_classify(line: str, reply: Reply) -> None:
    assert classify(line) == reply
