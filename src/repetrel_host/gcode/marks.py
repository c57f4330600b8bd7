"""What slicers mark in a job's comments: layers, Z, progress and time estimates.

Read once per job, in C-speed regular expressions over the file's bytes, so that the
progress display can say which layer and Z the last acknowledged line belongs to and how
long the slicer thinks is left, and ``--from-layer`` can find where a layer starts.

Markers read (layers are numbered from 1, in the file's order, as slicers' previews show
them; the first kind of layer marker in the file is the one counted):

- PrusaSlicer, SuperSlicer, OrcaSlicer: ``;LAYER_CHANGE`` then ``;Z:0.35``;
  ``M73 P12 R34`` (percent done, minutes left); ``; estimated printing time (normal mode) =
  1h 2m 3s``.
- Cura: ``;LAYER:0`` (0-based in the file), ``;TIME:4567`` (seconds in all) and
  ``;TIME_ELAPSED:123.4`` at each layer's end.
- Simplify3D: ``; layer 1, Z = 0.200``.
- Hyrel: ``M790`` (new layer), a host code in the job.

Z is the ``;Z:`` (or Simplify3D's) value when the file gives one, else the last ``G0``/``G1``
``Z`` word (absolute; slicers move Z absolutely).
"""

from __future__ import annotations

import re
from bisect import bisect_right
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, TypeVar

T = TypeVar("T")

_MARKS = re.compile(
    rb"^[ \t]*(?:"
    rb"(?P<prusa>;LAYER_CHANGE)"
    rb"|;LAYER:(?P<cura>-?\d+)"
    rb"|; ?layer (?P<s3d>\d+), Z = (?P<s3d_z>-?[\d.]+)"
    rb"|(?P<hyrel>M790)\b"
    rb"|;Z:(?P<z>-?[\d.]+)"
    rb"|M73\b(?P<m73>[^;\r\n]*)"
    rb"|;TIME_ELAPSED:(?P<elapsed>[\d.]+)"
    rb"|;TIME:(?P<total>\d+)"
    rb"|; estimated printing time \(normal mode\) = (?P<estimate>[^\r\n]+)"
    rb"|G[01](?![\d.])[^;\r\n]*?Z(?P<move_z>-?\d*\.?\d+)"
    rb")",
    re.MULTILINE | re.IGNORECASE,
)
_M73_WORD = re.compile(r"([PR])\s*(\d+(?:\.\d*)?)", re.IGNORECASE)
# The named group a layer marker matched, by the kind of marker it is.
_LAYER_KINDS = {"prusa": "prusa", "cura": "cura", "s3d": "s3d", "s3d_z": "s3d", "hyrel": "hyrel"}
_CHUNK = 1 << 20
_DURATION = re.compile(r"(\d+)\s*([dhms])")
_SECONDS = {"d": 86400, "h": 3600, "m": 60, "s": 1}


@dataclass(frozen=True, slots=True)
class Layer:
    """A layer: its number (from 1), the source line of its marker, its Z if known."""

    number: int
    line: int
    z: float | None


@dataclass(frozen=True, slots=True)
class Position:
    """Where a source line is in the print, as far as the slicer said."""

    layer: Layer | None
    z: float | None
    percent: float | None  # M73 P
    seconds_left: float | None  # the slicer's estimate


@dataclass
class SlicerMarks:
    """The marks of one file, by source line (see the module's docstring)."""

    layers: list[Layer] = field(default_factory=list)
    z_changes: list[tuple[int, float]] = field(default_factory=list)
    progress: list[tuple[int, float | None, float | None]] = field(default_factory=list)
    elapsed: list[tuple[int, float]] = field(default_factory=list)
    total_seconds: float | None = None

    def layer(self, number: int) -> Layer | None:
        """Layer ``number`` (from 1), or None when the file has fewer."""
        return self.layers[number - 1] if 1 <= number <= len(self.layers) else None

    def at(self, line: int, fraction: float = 0.0) -> Position:
        """Where source ``line`` is; ``fraction`` (of the file's bytes done) scales a whole
        print estimate when the file gives nothing finer."""
        layer = _last_at(self.layers, line, lambda item: item.line)
        z_change = _last_at(self.z_changes, line, lambda item: item[0])
        percent = left = None
        mark = _last_at(self.progress, line, lambda item: item[0])
        if mark is not None:
            _, percent, minutes = mark
            left = minutes * 60 if minutes is not None else None
        if left is None and self.total_seconds is not None:
            elapsed = _last_at(self.elapsed, line, lambda item: item[0])
            if self.elapsed:
                done = elapsed[1] if elapsed is not None else 0.0
            else:
                done = self.total_seconds * min(max(fraction, 0.0), 1.0)
            left = max(self.total_seconds - done, 0.0)
        return Position(layer, z_change[1] if z_change else None, percent, left)


def _last_at(items: list[T], line: int, key: Callable[[T], int]) -> T | None:
    index = bisect_right(items, line, key=key)
    return items[index - 1] if index else None


def scan_marks(path: Path, until_line: int | None = None) -> SlicerMarks:
    """The slicer's marks in ``path`` (none for an unreadable file); ``until_line``: read
    no further than the piece holding that line (what a resume needs of a big file)."""
    try:
        with path.open("rb") as handle:
            return _scan(_chunks(handle), until_line)
    except OSError:
        return SlicerMarks()


def _chunks(handle: BinaryIO) -> Iterator[bytes]:
    """The file in pieces of whole lines (about 1 MB each, so memory stays small)."""
    rest = b""
    while chunk := handle.read(_CHUNK):
        data = rest + chunk
        # After the last LF; in a file of lone CRs, after the last CR but a final one
        # (it may be the first half of a CRLF).
        cut = data.rfind(b"\n") + 1 or data.rfind(b"\r", 0, len(data) - 1) + 1
        data, rest = data[:cut], data[cut:]
        if data:
            yield data
    if rest:
        yield rest


def _line_ends(data: bytes) -> int:
    """Line ends as :class:`~repetrel_host.job.Job` counts them (LF, CRLF, a lone CR)."""
    return data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n")


def _scan(chunks: Iterable[bytes], until_line: int | None = None) -> SlicerMarks:
    marks = SlicerMarks()
    layer_kind: str | None = None
    move_z: list[tuple[int, float]] = []
    comment_z: list[tuple[int, float]] = []  # ;Z: comments: when there are any, they say Z
    first_line = 1
    past = False  # read past until_line
    for data in chunks:
        if b"\n" not in data:  # lone CRs end its lines: let ^ see them (same length)
            data = data.replace(b"\r", b"\n")
        line, counted = first_line, 0
        for match in _MARKS.finditer(data):
            start = match.start()
            line += _line_ends(data[counted:start])
            counted = start
            kind = match.lastgroup
            if kind in _LAYER_KINDS:
                kind = _LAYER_KINDS[kind]
                layer_kind = layer_kind or kind
                if kind == layer_kind:
                    marks.layers.append(Layer(len(marks.layers) + 1, line, None))
                if kind == "s3d":
                    comment_z.append((line, float(match["s3d_z"])))
            elif kind == "z":
                comment_z.append((line, float(match["z"])))
            elif kind == "move_z" and not comment_z:  # once there are ;Z:, they say Z
                move_z.append((line, float(match["move_z"])))
            elif kind == "m73":
                words = {w.upper(): float(v) for w, v in _M73_WORD.findall(match["m73"].decode())}
                if words:
                    marks.progress.append((line, words.get("P"), words.get("R")))
            elif kind == "elapsed":
                marks.elapsed.append((line, float(match["elapsed"])))
            elif kind == "total":
                marks.total_seconds = float(match["total"])
            elif kind == "estimate" and marks.total_seconds is None:
                marks.total_seconds = _duration(match["estimate"].decode(errors="replace"))
        first_line += _line_ends(data)
        if until_line is not None and first_line > until_line:
            if past:  # a piece more than the line's: the Z set after its layer's marker
                break
            past = True
    marks.z_changes = comment_z or move_z
    marks.layers = [_with_z(layer, marks.z_changes) for layer in marks.layers]
    return marks


def _with_z(layer: Layer, z_changes: list[tuple[int, float]]) -> Layer:
    """A layer's Z: the first Z set at or after its marker (before: the one in force)."""
    index = bisect_right(z_changes, layer.line - 1, key=lambda item: item[0])
    if index < len(z_changes):
        return Layer(layer.number, layer.line, z_changes[index][1])
    return Layer(layer.number, layer.line, z_changes[-1][1] if z_changes else None)


def _number(text: bytes) -> float:
    return float(text.decode())


def _duration(text: str) -> float | None:
    """``1d 2h 3m 4s`` (PrusaSlicer's estimate) in seconds."""
    parts = _DURATION.findall(text)
    return float(sum(int(n) * _SECONDS[unit] for n, unit in parts)) if parts else None
