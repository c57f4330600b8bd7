"""The device side: Marlin's line checks and reply strings."""

from repetrel_host.protocol.controller import Accepted, ControllerProtocol, Ignored, Rejected


def test_accepts_numbered_lines_in_sequence() -> None:
    controller = ControllerProtocol()
    assert controller.handle_line(b"N0 M110 N0*125") == Accepted("M110 N0", 0)
    assert controller.handle_line(b"N1 G28*18") == Accepted("G28", 1)
    assert controller.last_line == 1


def test_checksum_mismatch_asks_for_the_next_expected_line() -> None:
    controller = ControllerProtocol()
    controller.handle_line(b"N0 M110 N0*125")
    outcome = controller.handle_line(b"N1 G28*99")
    assert outcome == Rejected(
        "checksum mismatch",
        b"Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n",
    )
    assert controller.last_line == 0


def test_out_of_sequence_line_is_refused_without_executing() -> None:
    controller = ControllerProtocol()
    controller.handle_line(b"N0 M110 N0*125")
    outcome = controller.handle_line(b"N4 G92 E0*67")
    assert isinstance(outcome, Rejected)
    assert outcome.reply == (
        b"Error:Line Number is not Last Line Number+1, Last Line: 0\nResend: 1\nok\n"
    )


def test_numbered_line_without_checksum_is_refused() -> None:
    controller = ControllerProtocol()
    outcome = controller.handle_line(b"N1 G28")
    assert isinstance(outcome, Rejected)
    assert outcome.reason == "No Checksum with line number"


def test_checksum_without_line_number_is_refused() -> None:
    outcome = ControllerProtocol().handle_line(b"G28*22")
    assert isinstance(outcome, Rejected)


def test_m110_takes_the_second_number_like_marlin() -> None:
    controller = ControllerProtocol()
    controller.handle_line(b"N0 M110 N0*125")
    controller.handle_line(b"N1 G28*18")
    # A renumbering line may carry any first N: the N after M110 counts.
    line = b"N7 M110 N0"
    from repetrel_host.protocol.framing import checksum

    assert isinstance(controller.handle_line(line + b"*%d" % checksum(line)), Accepted)
    assert controller.last_line == 0


def test_unnumbered_lines_and_comments() -> None:
    controller = ControllerProtocol()
    assert controller.handle_line(b"M105") == Accepted("M105", None)
    assert controller.handle_line(b"; hello") == Ignored()
    assert controller.handle_line(b"") == Ignored()
