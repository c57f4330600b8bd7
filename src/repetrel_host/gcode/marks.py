"""What slicers mark in a job's comments: layers, Z, progress and time estimates.

Read once per job, by :mod:`repetrel_host.gcode.analysis`'s one pass over the file, so
that the progress display can say which layer and Z the last acknowledged line belongs to
and how long the slicer thinks is left, and ``--from-layer`` can find where a layer starts.

Markers read (layers are numbered from 1, in the file's order, as slicers' previews show
them; the first kind of the slicer's layer markers in the file is the one counted, and
Hyrel's M790 only in a file without any: see the analysis module for why):

- PrusaSlicer, SuperSlicer, OrcaSlicer: ``;LAYER_CHANGE`` then ``;Z:0.35``;
  ``M73 P12 R34`` (percent done, minutes left); ``; estimated printing time (normal mode) =
  1h 2m 3s``.
- Cura: ``;LAYER:0`` (0-based in the file), ``;TIME:4567`` (seconds in all) and
  ``;TIME_ELAPSED:123.4`` at each layer's end.
- Simplify3D: ``; layer 1, Z = 0.200``.
- Hyrel: ``M790`` (new layer), a host code in the job.

Z is the ``;Z:`` (or Simplify3D's) value when the file gives one, else where the last move
with a ``Z`` word went.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

T = TypeVar("T")


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
