"""How many M115 answers a piece of a Hyrel controller's text holds, and where they begin.

Rules read off the text (the count remembers only whether the line before was an answer
cut in two; the dialect in :mod:`~repetrel_host.protocol.dialects.hyrel` keeps the rest):
an answer's name, one byte of it garbled or not; an answer and a message that a garbled
newline ran together; whether a ``>MC:`` notice gives a command's values; the line number
an error report names.
"""

from __future__ import annotations

import re

from repetrel_host.protocol import replies
from repetrel_host.protocol.hyrel import HyrelNotice

ANSWER_NAME = "FIRMWARE_NAME:"
# The parts of an answer: a line holding one is a piece of an answer (cut in two by a
# garbled newline, or quoted), never a message between two answers.
ANSWER_PARTS = ("FIRMWARE", "PROTOCOL_VERSION", "HYREL_PROTOCOL", "MACHINE_TYPE")
_LINE_NUMBER = re.compile(r"\bline\s+(\d+)|\bN(\d+)\b", re.IGNORECASE)
_TAG = re.compile(r">..:")  # a message's
_FIELD = re.compile(r"([A-Za-z])\s*(-?\d+(?:\.\d*)?)")
_NOTICE_VALUES = "TS"  # the values a notice gives of its line (">MC:M<n>: T<t>: S<s>:")


def notice_agrees(notice: HyrelNotice, command: str) -> bool:
    """The notice gives the command's values: every value it gives is the command's, and it
    gives the command's T and S (``T11: S200:`` and ``M104 T11 S200.0``). A notice cut
    short by a garbled byte (``>MC:M104:``), or another code's garbled, is no line's with
    values."""
    values = {letter.upper(): float(value) for letter, value in _FIELD.findall(command[1:])}
    given = {letter: float(value) for letter, value in notice.fields.items()}
    return all(values.get(letter) == value for letter, value in given.items()) and all(
        given.get(letter) == values[letter] for letter in _NOTICE_VALUES if letter in values
    )


def answer_starts(text: str, answers: int) -> list[int]:
    """Where each of the ``answers`` answers in ``text`` begins, as far as can be told (by
    their names, or their version fields); else 0 for each."""
    for mark in (ANSWER_NAME, "PROTOCOL_VERSION:"):
        starts = [match.start() for match in re.finditer(re.escape(mark), text)]
        if len(starts) == answers:
            return starts
    return [0] * answers


def answer_name_at(text: str) -> int:
    """Where an answer's name begins in ``text``, one byte of it garbled or not; -1 if
    nowhere (one garbled byte leaves its first seven bytes whole, or its last seven)."""
    at = text.find(ANSWER_NAME[:7])
    if at < 0:
        at = text.find(ANSWER_NAME[7:])
        at = at - 7 if at >= 7 else -1
    return at


def reads_hy(tag: str) -> bool:
    """Whether a tag reads ``HY`` but for one garbled byte: the second half of an answer
    cut in two begins with ``>Hy:``."""
    return tag[0] == "H" or tag[1] == "Y"


def answer_run_in(text: str) -> int:
    """Where an answer begins that a garbled newline ran into the message before it
    (``>ST: T:20.0 ...?FIRMWARE_NAME:...``), or 0: a message of its own text first, then
    one byte (the newline) that no quote puts before a name (a space, a colon)."""
    at = text.find(ANSWER_NAME, 5)
    if at < 0 or not text.startswith(">") or text[at - 1] in " :":
        return 0
    said = _TAG.sub("", text[: at - 1], count=1)
    return at if len(said.strip()) > 1 else 0


def message_run_on(text: str) -> int:
    """Where a message begins that a garbled newline ran onto the end of an answer
    (``FIRMWARE_NAME:... HYREL_PROTOCOL:1?>ST: T:20.0 ...``), or 0."""
    for match in _TAG.finditer(text, 1):
        if match.group().upper() != ">HY:":
            return match.start()
    return 0


def line_named(text: str) -> int | None:
    """The line number an error report names ("line 12", "N12"), if any."""
    match = _LINE_NUMBER.search(text)
    if match is None:
        return None
    return int(match.group(1) or match.group(2))


class AnswerCounter:
    """Counts the M115 answers in each line the controller writes, in order: the second
    half of an answer that a garbled newline cut in two counts with its first."""

    def __init__(self) -> None:
        self._fragment = False  # the last line was an answer cut in two

    def count(self, text: str, hyrel: replies.HyrelReport | None) -> int:
        """M115 answers in a line, even with a byte garbled: each has its name or its
        version field (both halves of one that a garbled newline cut in two count once;
        one whose newline was garbled runs into the next line, another answer maybe).
        A message is none, even quoting one (only the second half of one cut in two may
        read ``>Hy: ...``)."""
        if hyrel is not None and not reads_hy(hyrel.tag):
            self._fragment = False
            return 0
        named = text.count(ANSWER_NAME)
        versioned = text.count("PROTOCOL_VERSION:")
        answers = max(named, versioned - self._fragment)
        self._fragment = named > versioned
        return answers
