"""A job: the commands of a G-code file, read lazily, with their source positions.

Some codes are the host's, not the controller's (as in Repetrel):

- ``M0`` / ``M1``: pause. On the wire it becomes the machine's ``pause_sync`` command
  (``M400``: its ok means every move before it has finished), or ``M0`` where the
  controller waits itself (Hyrel's link); once that is confirmed the host shows the
  text after the semicolon and waits to resume.
  ``M0 ; SAY Hello`` also performs the actions ``M792`` knows.
- ``M792 ; SAY text ; PIC file ; VID file ; SEND text ; BEEP ; SHELL program``: actions
  on the host, in stream order. Not forwarded.
- ``M719``: forwarded (it tells the controller what to report), and the host starts
  logging the controller's reports to a file. ``M718``: the host stops logging; not
  forwarded.
- ``M790`` (new layer) and ``M791`` (snap image): the host's camera takes a snapshot (at
  every ``M790`` when the configuration says so). Not forwarded. They hold nothing up:
  they are markers, due as the line before them is acknowledged, while the job streams on.
- ``M110``: not forwarded; the host owns line numbers. A bare ``N14`` line sends nothing.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import BinaryIO

from repetrel_host.errors import JobError
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol.framing import clean_line

ACTION_VERBS = ("SAY", "PIC", "VID", "SEND", "BEEP", "SHELL")


@dataclass(slots=True)
class JobLine:
    """One command to send. ``index`` counts the job's commands from 1 (0 outside the job);
    ``end_offset`` is the byte offset just past the line, for progress by bytes.

    Not to be changed once made; not frozen, though: it is made for every line, and a
    frozen dataclass costs four times as much to make."""

    index: int
    source_line: int  # 0 for lines the host adds (header, safe stop)
    command: str
    end_offset: int
    source: str  # the job's file name, or "header: head T1 (MK1-250)", "safe stop"

    @property
    def position(self) -> str:
        """Where the line comes from: ``job.gcode:1234`` or ``header: head T1 (MK1-250)``."""
        return f"{self.source}:{self.source_line}" if self.source_line else self.source


class ActionKind(StrEnum):
    PAUSE = "pause"  # M0, M1: wait for the operator
    ACTIONS = "actions"  # M792: SAY, BEEP, SHELL...
    LOG_START = "log_start"  # M719: keep the controller's reports
    LOG_STOP = "log_stop"  # M718
    LAYER = "layer"  # M790: a new layer (a snapshot when the camera takes one per layer)
    SNAPSHOT = "snapshot"  # M791: a camera snapshot


@dataclass(frozen=True, slots=True)
class HostAction:
    """Something the host does itself once every line before it is acknowledged."""

    kind: ActionKind
    message: str
    actions: tuple[tuple[str, str], ...]  # (verb, argument), e.g. ("SAY", "Hello")
    source_line: int
    source: str

    @property
    def position(self) -> str:
        return f"{self.source}:{self.source_line}"

    @property
    def is_marker(self) -> bool:
        """Done beside the stream (a snapshot), not once it stopped and everything before it
        was confirmed: it waits for nothing, and nothing waits for it."""
        return self.kind in _MARKERS


_MARKERS = frozenset({ActionKind.LAYER, ActionKind.SNAPSHOT})

JobItem = JobLine | HostAction


def parse_actions(text: str) -> tuple[str, tuple[tuple[str, str], ...]]:
    """Split M0/M792 text at semicolons into a message and (verb, argument) actions."""
    message: list[str] = []
    actions: list[tuple[str, str]] = []
    for part in (p.strip() for p in text.split(";")):
        if not part:
            continue
        verb, _, argument = part.partition(" ")
        if verb.upper() in ACTION_VERBS:
            actions.append((verb.upper(), argument.strip()))
        else:
            message.append(part)
    return "; ".join(message), tuple(actions)


class Job:
    """A G-code file to stream. Opening checks it is a readable file; reading is lazy."""

    def __init__(self, path: Path, pause_sync: str = "M400") -> None:
        self.path = path
        self.name = path.name
        self.pause_sync = pause_sync
        if not path.exists():
            raise JobError(f"{path}: no such file")
        if path.is_dir():
            raise JobError(f"{path}: is a directory, not a G-code file")
        if not os.access(path, os.R_OK):
            raise JobError(f"{path}: permission denied (the file is not readable)")
        self.size = path.stat().st_size

    def commands(self) -> Iterator[tuple[int, str, bytes, int]]:
        """(line number, command, raw line, end offset) of every line with a command."""
        try:
            handle = self.path.open("rb")
        except OSError as exc:
            raise JobError(f"{self.path}: cannot be read ({exc.strerror})") from None
        with handle:
            for number, (raw, offset) in enumerate(_raw_lines(handle), start=1):
                where = f"{self.name}:{number}"
                command = clean_line(raw, where)
                if len(command) > MAX_COMMAND_LENGTH:
                    cut = len(raw) >= MAX_KEPT_LINE  # only its start was kept
                    size = f"over {MAX_KEPT_LINE}" if cut else str(len(command))
                    raise JobError(
                        f"{where}: the command is {size} characters long; "
                        f"controllers take at most {MAX_COMMAND_LENGTH}"
                    )
                if command:
                    yield number, command, raw, offset

    def items(
        self,
        check: Callable[[int, str], None] | None = None,
        pause_sync: str | None = None,
        start: int = 1,
    ) -> Iterator[JobItem]:
        """Lines to send and host actions, in order; :class:`JobError` at a line that cannot go.

        ``check(line number, command)`` sees each command as read (it may raise JobError);
        ``pause_sync`` replaces :attr:`pause_sync` (``M0`` where the controller waits itself);
        ``start``: the first source line (a recovered job: the lines before it are neither
        sent, nor checked, nor their host actions done; ``index`` counts from 1 there).
        """
        index = 0
        name = self.name
        pause_sync = pause_sync or self.pause_sync
        for number, command, raw, offset in self.commands():
            if number < start:
                continue
            if check is not None:
                check(number, command)
            word = command_word(command)
            if word not in _HOST_WORDS:
                index += 1
                yield JobLine(index, number, command, offset, name)
                continue
            for item in self._host_code(word, command, raw, number, pause_sync):
                if isinstance(item, str):  # a command the host still sends
                    index += 1
                    yield JobLine(index, number, item, offset, name)
                else:
                    yield item

    def lines(self) -> Iterator[JobLine]:
        """Only the lines that go on the wire."""
        return (item for item in self.items() if isinstance(item, JobLine))

    def _host_code(
        self, word: str, command: str, raw: bytes, number: int, pause_sync: str
    ) -> list[str | HostAction]:
        """What a host-side code becomes: commands still sent, and actions."""
        name = self.name
        if word == "M110":
            return []  # forwarding it would desynchronise the host's line numbers
        if word == "M718":
            return [HostAction(ActionKind.LOG_STOP, "", (), number, name)]
        if word == "M719":
            return [command, HostAction(ActionKind.LOG_START, command, (), number, name)]
        if word in _CAMERA_WORDS:
            return [HostAction(_CAMERA_WORDS[word], "", (), number, name)]
        # M0, M1 and M792 carry their text after the command and after semicolons.
        text = raw.decode("utf-8", errors="replace")
        text = text.strip()[len(text.strip().split(None, 1)[0]) :]
        message, actions = parse_actions(text)
        if word == "M792":
            return [HostAction(ActionKind.ACTIONS, message, actions, number, name)]
        return [pause_sync, HostAction(ActionKind.PAUSE, message, actions, number, name)]


_CAMERA_WORDS = {"M790": ActionKind.LAYER, "M791": ActionKind.SNAPSHOT}
_HOST_WORDS = frozenset({"M0", "M1", "M110", "M718", "M719", "M792", *_CAMERA_WORDS})
_ENDING = re.compile(rb"\r\n|\r|\n")
# Marlin's line buffer holds 96 bytes and Repetrel cuts lines at 100 characters: a
# longer command would arrive cut, fail its checksum and be asked for forever.
MAX_COMMAND_LENGTH = 96
# Of a longer line only this much is kept as it is read (see _raw_lines).
MAX_KEPT_LINE = 1 << 16
# Read a megabyte at a time: in a thread, reading 64 KB at a time (a GIL release and retake
# each time, a few milliseconds apart) starved the event loop of the GIL for most of a second.
_READ_SIZE = 1 << 20
UTF8_BOM = b"\xef\xbb\xbf"


def _raw_lines(handle: BinaryIO) -> Iterator[tuple[bytes, int]]:
    """Lines without their ending (LF, CRLF or a lone CR), with the offset past each; a
    UTF-8 byte order mark at the file's start is skipped (Windows editors write one).

    Linear in the file's size, whatever its lines (a line of megabytes without an end
    costs what its bytes do), and bounded in memory: of a line longer than
    :data:`MAX_KEPT_LINE` only its first bytes are kept. That is safe: what would be sent
    is its command before any comment, and one that long is refused anyway (it is over
    :data:`MAX_COMMAND_LENGTH`)."""
    offset = 0
    parts: list[bytes] = []  # the line so far
    kept = 0  # its bytes in parts
    held_cr = False  # the last chunk ended with a CR: maybe the first half of a CRLF
    first = True
    while True:
        try:
            chunk = handle.read(_READ_SIZE)
        except OSError as exc:  # a stick pulled out, a network share gone
            raise JobError(f"{handle.name}: cannot be read on ({exc.strerror})") from None
        if first and chunk.startswith(UTF8_BOM):  # an editor's mark, not part of a command
            chunk, offset = chunk[len(UTF8_BOM) :], len(UTF8_BOM)
        first = False
        if held_cr:
            crlf = chunk.startswith(b"\n")
            line, length = b"".join(parts), offset + 1 + crlf
            offset, parts, kept, held_cr = length, [], 0, False
            yield line, offset
            chunk = chunk[crlf:]
        if not chunk:
            if parts or kept:
                yield b"".join(parts), offset
            return
        if chunk.endswith(b"\r"):
            chunk, held_cr = chunk[:-1], True
        start = 0
        for ending in _ENDING.finditer(chunk):
            piece = chunk[start : ending.start()]
            offset += ending.end() - start
            if parts:
                yield b"".join((*parts, piece[: MAX_KEPT_LINE - kept])), offset
                parts, kept = [], 0
            else:
                yield piece[:MAX_KEPT_LINE], offset
            start = ending.end()
        rest = chunk[start:]
        offset += len(rest)
        if rest and kept < MAX_KEPT_LINE:
            parts.append(rest[: MAX_KEPT_LINE - kept])
            kept += len(parts[-1])
