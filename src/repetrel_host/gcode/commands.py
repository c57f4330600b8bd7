"""What kind of command a G-code line is, as far as flow control cares."""

from __future__ import annotations

import re

_WORD = re.compile(r"([A-Za-z])\s*(\d+)(\.\d+)?")
_HEAD = re.compile(r"^\s*[A-Za-z]\s*\d+(?:\.\d+)?")
_VALUE = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")

# Commands a controller acknowledges only after its motion queue drained and
# the command finished (docs/protocol.md, "Numbered lines").
# Their long waits are not communication failures.
UNBUFFERED = frozenset(
    {
        "G4",  # dwell
        "G28",  # home
        "G29",  # bed probing
        "G30",  # single probe
        "G32",  # probe and level
        "M0",  # stop / wait for user
        "M1",  # sleep / wait for user
        "M109",  # set hotend temperature and wait
        "M116",  # wait for temperatures
        "M190",  # set bed temperature and wait
        "M191",  # set chamber temperature and wait
        "M226",  # wait for pin state
        "M303",  # PID autotune
        "M400",  # wait for moves to finish
        "M600",  # filament change
    }
)


def command_word(command: str) -> str:
    """The normalised first word: ``g01 x5`` and ``G1X5`` give ``G1``, ``T0`` gives ``T0``."""
    # Slicer output is nearly all ``G1 X...``: a word already in its normal form is
    # returned as it is (this runs twice for every streamed line).
    head = command.split(" ", 1)[0]
    digits = head[1:]
    if (
        digits.isdigit()
        and digits.isascii()
        and "A" <= head[0] <= "Z"
        and (digits[0] != "0" or len(digits) == 1)
    ):
        return head
    match = _WORD.match(command)
    if match is None:
        return command.split(" ", 1)[0].upper()
    letter, number, fraction = match.groups()
    return letter.upper() + str(int(number)) + (fraction or "")


def command_rest(command: str) -> str:
    """What follows the command's own word, upper-cased: `` X5 E.2`` of ``g1 x5 e.2``."""
    return _HEAD.sub("", command, count=1).upper()


def command_words(command: str) -> dict[str, float]:
    """The words after the command's own: ``G1 X5 E.2`` (or ``G1X5E.2``) gives X 5 and E 0.2."""
    return {letter: float(value) for letter, value in _VALUE.findall(command_rest(command))}


def is_unbuffered(command: str) -> bool:
    """True when the controller acknowledges ``command`` only after it has finished."""
    return command_word(command) in UNBUFFERED
