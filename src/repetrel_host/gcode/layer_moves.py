"""The moves of one layer, for the page's layer view: each move's source line, where it
starts and ends in X and Y, and whether it extrudes.

Only that layer's bytes are read (found by the analysis's layer offsets), with the 64 KB
before it for the position and modes it starts in, and the file's first 64 KB for the modes
a slicer sets in its start G-code: a layer of a 1 GB file costs what the layer costs.
Arcs (G2, G3) are drawn as the straight line to where they end: a preview, not a path.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

CONTEXT = 1 << 16  # bytes read before the layer, and of the file's start, for its state
_WORD = re.compile(rb"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_MOVE = re.compile(rb"^\s*(?:N\d+\s*)?[Gg]0?[0-3](?![0-9.])")
_MODE = re.compile(rb"^\s*(?:N\d+\s*)?(G90|G91|M82|M83)\b", re.MULTILINE)


@dataclass
class _State:
    x: float | None = None
    y: float | None = None
    relative_xy: bool = False
    relative_e: bool = False
    e: float = 0.0


def _words(text: bytes) -> dict[bytes, float]:
    return {letter.upper(): float(value) for letter, value in _WORD.findall(text)}


def _modes(text: bytes, state: _State) -> None:
    """The last of G90/G91 and M82/M83 in ``text`` sets ``state``'s modes."""
    for found in _MODE.finditer(text):
        word = found.group(1)
        if word in (b"G90", b"G91"):
            state.relative_xy = state.relative_e = word == b"G91"
        else:
            state.relative_e = word == b"M83"


def _position(before: bytes, state: _State) -> None:
    """The last X and Y a move of ``before`` named (absolute files: where the layer starts)."""
    for line in reversed(before.splitlines()):
        if state.x is not None and state.y is not None:
            return
        move = _MOVE.match(line)
        if move:
            words = _words(line.split(b";", 1)[0][move.end() :])
            if state.x is None and b"X" in words:
                state.x = words[b"X"]
            if state.y is None and b"Y" in words:
                state.y = words[b"Y"]


def layer_moves(
    path: Path, start: int, end: int | None, first_line: int
) -> list[tuple[int, float, float, float, float, bool]]:
    """The moves between byte ``start`` (the layer's first line, source line ``first_line``)
    and ``end`` (None: the file's end): ``(line, x0, y0, x1, y1, extrudes)`` each."""
    state = _State()
    with path.open("rb") as handle:
        _modes(handle.read(min(CONTEXT, start)), state)
        context_start = max(0, start - CONTEXT)
        handle.seek(context_start)
        before = handle.read(start - context_start)
        _modes(before, state)
        if not state.relative_xy:
            _position(before, state)
        handle.seek(start)
        body = handle.read() if end is None else handle.read(max(0, end - start))
    moves: list[tuple[int, float, float, float, float, bool]] = []
    for number, line in enumerate(body.split(b"\n"), start=first_line):
        code = line.split(b";", 1)[0]
        if not code.strip():
            continue
        move = _MOVE.match(code)
        if move is None:
            _modes(code, state)
            if code.lstrip().upper().startswith(b"G92"):
                state.e = _words(code.lstrip()[3:]).get(b"E", state.e)
            continue
        words = _words(code[move.end() :])
        x0, y0 = state.x, state.y
        x, y = words.get(b"X"), words.get(b"Y")
        if state.relative_xy:
            x = (x0 or 0.0) + x if x is not None else x0
            y = (y0 or 0.0) + y if y is not None else y0
        else:
            x = x if x is not None else x0
            y = y if y is not None else y0
        extrudes = False
        if b"E" in words:
            e = words[b"E"]
            extrudes = e > 0 if state.relative_e else e > state.e
            state.e = state.e + e if state.relative_e else e
        state.x, state.y = x, y
        if x is None or y is None or (x == x0 and y == y0):
            continue  # Z alone, E alone, or not yet placed
        if x0 is None or y0 is None:
            x0, y0 = x, y  # where the layer starts is not known: its first move is a dot
        moves.append((number, x0, y0, x, y, extrudes))
    return moves
