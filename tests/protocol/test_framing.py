"""Framing, byte-exact against the examples in reprap-gcode-protocol.txt."""

import pytest

from repetrel_host.errors import JobError
from repetrel_host.protocol.framing import (
    checksum,
    clean_line,
    frame,
    reset_command,
)


@pytest.mark.parametrize(
    ("number", "command", "wire"),
    [
        # The reference's own examples ("Checking"), plus the opening reset line.
        (3, "T0", b"N3 T0*57\n"),
        (4, "G92 E0", b"N4 G92 E0*67\n"),
        (5, "G28", b"N5 G28*22\n"),
        (0, "M110 N0", b"N0 M110 N0*125\n"),
    ],
)
def test_frame_matches_reference_examples(number: int, command: str, wire: bytes) -> None:
    assert frame(number, command) == wire


def test_checksum_is_xor_of_bytes_before_star() -> None:
    assert checksum(b"") == 0
    assert checksum(b"N3 T0") == 57
    assert checksum(b"AA") == 0


def test_reset_command_repeats_the_number() -> None:
    assert reset_command(0) == "M110 N0"


@pytest.mark.parametrize(
    ("raw", "command"),
    [
        ("G1 X5 Y5 ; a comment", "G1 X5 Y5"),
        ("   G28\t", "G28"),
        ("G1\tX1\tY2", "G1 X1 Y2"),
        ("; only a comment", ""),
        ("", ""),
        ("   ", ""),
        (b"M104 S200 ; \xb0C is fine inside a comment", "M104 S200"),
        # An already framed line: number and checksum are stripped, we renumber.
        ("N12 G1 X5*87", "G1 X5"),
        ("N12 G1 X5", "G1 X5"),
        # Hyrel's bare N line ("set line numbers for error logging") sends nothing.
        ("N14", ""),
    ],
)
def test_clean_line(raw: str | bytes, command: str) -> None:
    assert clean_line(raw) == command


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b"G1 X\xb05", "not ASCII"),
        ("G1 X5 \u00b0", "not ASCII"),
        ("G1 X5*3 Y4", "checksum"),
        ("G1 X5\x00", "control characters"),
    ],
)
def test_clean_line_refuses_what_cannot_be_framed(raw: str | bytes, reason: str) -> None:
    with pytest.raises(JobError, match=reason) as error:
        clean_line(raw, "job.gcode:7")
    assert str(error.value).startswith("job.gcode:7: ")
