"""The wire's log as OctoPrint's terminal shows it ("Send: ...", "Recv: ..."): read from
the session's tail of the wire a tick at a time, its newest lines only."""

from __future__ import annotations

from collections import deque
from itertools import islice

LOG_LINES = 300  # OctoPrint's terminal: the log lines a history (and a tick) carries
_PREFIXES = (b"\nRecv: ", b"\nSend: ")  # OctoPrint's terminal, by "sent"
_PREFIX = len("Send: ")


def terminal_lines(pieces: deque[tuple[bool, bytes]], partial: list[bytes]) -> list[str]:
    """The wire's ``pieces`` (sent or not, data) as OctoPrint's terminal shows them ("Send:
    ...", "Recv: ..."), their last :data:`LOG_LINES` lines; ``partial`` holds the lines not
    complete yet (received, sent), from the last call and for the next. Only the newest
    pieces are read, a piece at a time with C's string operations: a line at a time in
    Python would cost more than the rest of a tick."""
    # The newest pieces that hold the lines shown (a piece holds a line, or hundreds).
    before: list[bytes | None] = [partial[False], partial[True]]
    kept = found = 0
    for _, data in reversed(pieces):
        kept += 1
        found += data.count(b"\n")
        if found > LOG_LINES:
            break
    if kept < len(pieces):
        # Where older pieces are left out, a line begun in them is too (None: unknown).
        unknown = {False, True}
        for sent, data in islice(reversed(pieces), kept, None):
            if sent in unknown:
                unknown.discard(sent)
                before[sent] = b"" if data[-1] == 10 else None
                if not unknown:
                    break
        pieces = deque(islice(pieces, len(pieces) - kept, None))
    chunks: list[bytes] = []
    add = chunks.append
    for sent, data in pieces:
        begun = before[sent]
        if begun:
            data = begun + data
            before[sent] = b""
        elif begun is None:
            cut = data.find(b"\n")
            if cut < 0:
                continue
            data, before[sent] = data[cut + 1 :], b""
            if not data:
                continue
        if data[-1] != 10:  # a line not complete yet (mostly a piece ends with one)
            data, newline, before[sent] = data.rpartition(b"\n")
            if not newline:
                continue
        # "\nSend: " before each line (and after the last: an empty line, left out)
        prefix = _PREFIXES[sent]
        add(prefix + data.replace(b"\n", prefix))
    partial[:] = [before[False] or b"", before[True] or b""]
    text = b"".join(chunks).replace(b"\r", b"").decode("utf-8", "replace")
    lines = text.split("\n")[-LOG_LINES * 2 :]
    return [line for line in lines if len(line) > _PREFIX][-LOG_LINES:]
