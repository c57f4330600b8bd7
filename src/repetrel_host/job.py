"""A job: the commands of a G-code file, read lazily, with their source positions."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from repetrel_host.errors import JobError
from repetrel_host.protocol.framing import clean_line, is_reset_command


@dataclass(frozen=True, slots=True)
class JobLine:
    """One command to send: ``index`` counts sent commands from 1; ``end_offset`` is the
    byte offset in the file just past this line, for progress by bytes."""

    index: int
    source_line: int
    command: str
    end_offset: int


class Job:
    """A G-code file to stream. Opening checks it is a readable file; reading is lazy."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.name = path.name
        if not path.exists():
            raise JobError(f"{path}: no such file")
        if path.is_dir():
            raise JobError(f"{path}: is a directory, not a G-code file")
        if not os.access(path, os.R_OK):
            raise JobError(f"{path}: permission denied (the file is not readable)")
        self.size = path.stat().st_size
        self.host_consumed = 0  # lines the host keeps to itself (M110)

    def lines(self) -> Iterator[JobLine]:
        """Yield the commands to send; raise :class:`JobError` at a line that cannot be sent."""
        index = 0
        offset = 0
        try:
            handle = self.path.open("rb")
        except OSError as exc:
            raise JobError(f"{self.path}: cannot be read ({exc.strerror})") from None
        with handle:
            for number, raw in enumerate(handle, start=1):
                offset += len(raw)
                command = clean_line(raw.rstrip(b"\r\n"), f"{self.name}:{number}")
                if not command:
                    continue
                if is_reset_command(command):
                    # The host owns line numbering; forwarding M110 would desynchronise it.
                    self.host_consumed += 1
                    continue
                index += 1
                yield JobLine(index, number, command, offset)
