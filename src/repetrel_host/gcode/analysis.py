"""One pass over a G-code file: what the slicer marked and what the moves do.

It gives, read once and streaming (pieces of about 1 MB: a 1 GB job is never held whole):

- the slicer's marks (:class:`~repetrel_host.gcode.marks.SlicerMarks`: layers, Z, M73,
  time estimates, by source line), which ``hyrel-send`` and the server follow a job by;
- where each of those layers begins, in bytes (the server's progress counts layers by the
  bytes acknowledged);
- a :class:`FileSummary` of the file, OctoPrint's ``gcodeAnalysis`` (``octoprint/util/
  gcodeInterpreter.py`` and ``octoprint/filemanager/analysis.py``): filament per tool, the
  box of the extruding moves and of every move; with the layer count, the slicer's name and
  its estimated print time;
- on request (``planned``), the print time the moves take as the firmware's planner runs
  them (:func:`~repetrel_host.gcode.estimate.estimate_file`, a second read of the file),
  kept beside the slicer's figure, never in its place, with the planned time at a few dozen
  of its lines (what a job recovered from a line has left).

Layers: the slicer's own marks when the file has any (PrusaSlicer's ``;LAYER_CHANGE``,
Cura's ``;LAYER:``, Simplify3D's ``; layer N``: only the first of these kinds met is counted,
since some files carry two for each layer), else Hyrel's ``M790``. A PrusaSlicer file for a
Hyrel printer often has both, an ``M790`` in its layer-change G-code beside the slicer's
mark; counting both would make every layer two. The slicer's marks are what its preview
numbers and what ``--from-layer`` means; an ``M790`` may also stand where no layer begins
(a snapshot wanted mid-layer).

Filament follows OctoPrint's interpreter: E is absolute (M82) or relative (M83, or G91 for
every axis); G92 sets the register; each tool (T0..T19: Hyrel's head addresses) keeps its
own. A tool's length is the most its net extrusion ever reached, so a retraction counts
nothing, and the filament it pulls back counts once when pushed out again. The slicer's own
``; filament used [mm]`` (and ``[cm3]``) lines win where the file has them; a volume is
otherwise the length times the section of ``; filament_diameter`` (else 1.75 mm; OctoPrint
takes 0 and so says 0 cm³). Boxes are OctoPrint's too: an extruding move's start and end
(arcs with the extremes they pass) for ``printingArea``, every move's for ``travelArea``,
with Z measured from the bed (Z 0) as OctoPrint's default ``bedZ``.

Move lines are split into words (the fast path: slicers write ``G1 X1.2 Y3.4 E.05``); words
glued together (``G1X1Y2``) or spaced from their number (``X 1``) take a slower, exact one.
"""

from __future__ import annotations

import math
import re
from bisect import bisect_right
from collections.abc import Iterable, Iterator
from dataclasses import asdict, astuple, dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

from repetrel_host.gcode.estimate import PlanSettings
from repetrel_host.gcode.marks import Layer, SlicerMarks
from repetrel_host.gcode.thumbnails import Thumbnail
from repetrel_host.gcode.timeline import PlannedTime, Timeline

_CHUNK = 1 << 20
DEFAULT_DIAMETER = 1.75  # mm, where the file names none
MAX_TOOL = 19  # T0..T19 are Hyrel's head addresses; a higher T is a device, not a head
PLANNED_POINTS = 48  # lines whose planned time a summary keeps: a small JSON file still

_NUMBER = rb"[-+]?(?:\d+\.?\d*|\.\d+)"  # what float() reads, but inf and nan
_COMMENT = re.compile(
    rb";(?:"
    rb"(?P<prusa>LAYER_CHANGE)"
    rb"|LAYER:(?P<cura>-?\d+)"
    rb"| ?layer (?P<s3d>\d+), Z = (?P<s3d_z>" + _NUMBER + rb")"
    rb"|Z:(?P<z>" + _NUMBER + rb")"
    rb"|TIME_ELAPSED:(?P<elapsed>" + _NUMBER + rb")"
    rb"|TIME:(?P<total>\d+)"
    rb"| estimated printing time \(normal mode\) = (?P<estimate>.+)"
    rb"|[ \t]*filament used \[mm\] = (?P<used_mm>.+)"
    rb"|[ \t]*filament used \[cm3\] = (?P<used_cm3>.+)"
    rb"|[ \t]*Filament used: (?P<used_m>.+)"  # Cura's, in metres
    rb"|[ \t]*filament_?diameter[ \t]*[=:,][ \t]*(?P<diameter>.+)"
    rb"|[ \t]*(?:G-Code )?generated (?:by|with) (?P<slicer>.+)"
    rb"|[ \t]*thumbnail(?:_(?P<thumb_format>PNG|JPG|QOI))? begin[ \t]+(?P<thumb_width>\d+)"
    rb"x(?P<thumb_height>\d+)(?P<thumb_begin>)"
    rb"|[ \t]*(?P<thumb_end>thumbnail(?:_(?:PNG|JPG|QOI))? end)"
    rb")",
    re.IGNORECASE,
)
_NUMBERS = re.compile(_NUMBER)
_WORD = re.compile(rb"([A-Z])[ \t]*(" + _NUMBER + rb")")
_AXES = re.compile(rb"[XYZ]")
_GLUED = re.compile(rb"[GMT]\d+(?:\.\d+)?[A-Z]")
_M73_WORD = re.compile(r"([PR])\s*(\d+(?:\.\d*)?)", re.IGNORECASE)
_DURATION = re.compile(r"(\d{1,9})\s*([dhms])")
_SECONDS = {"d": 86400, "h": 3600, "m": 60, "s": 1}
_MOVES = frozenset((b"G0", b"G1", b"G00", b"G01", b"G2", b"G3", b"G02", b"G03"))
_ARCS = frozenset((b"G2", b"G3", b"G02", b"G03"))
_FAST = (b"G1 ", b"G0 ")  # the moves read in the fast path
_INF = math.inf
_X, _Y, _Z, _E, _I, _J, _R = b"XYZEIJR"  # the words' letters, as bytes' items


@dataclass(frozen=True, slots=True)
class Box:
    """A box in the printer's coordinates (mm)."""

    min_x: float
    min_y: float
    min_z: float
    max_x: float
    max_y: float
    max_z: float

    def area(self) -> dict[str, float]:
        """OctoPrint's ``printingArea``/``travelArea``."""
        return {
            "minX": self.min_x,
            "minY": self.min_y,
            "minZ": self.min_z,
            "maxX": self.max_x,
            "maxY": self.max_y,
            "maxZ": self.max_z,
        }

    def dimensions(self) -> dict[str, float]:
        """OctoPrint's ``dimensions``/``travelDimensions``."""
        return {
            "width": round(self.max_x - self.min_x, 6),
            "depth": round(self.max_y - self.min_y, 6),
            "height": round(self.max_z - self.min_z, 6),
        }


@dataclass(frozen=True, slots=True)
class Filament:
    """One tool's filament: length (mm) and volume (cm³)."""

    length: float
    volume: float


@dataclass(frozen=True)
class FileSummary:
    """What a file list shows of a file (OctoPrint's ``gcodeAnalysis``, and more)."""

    slicer_seconds: float | None = None  # the slicer's estimate, from its comments
    # The print time from the moves (the planner's; None: no moves, or not asked for) and
    # where its limits came from ("the file's slicer settings", "Marlin's defaults"...).
    planned_seconds: float | None = None
    planned_limits_from: str | None = None
    # The planned seconds at the end of some lines, in order (:data:`PLANNED_POINTS` at
    # most; none in a summary kept before they were).
    planned_points: tuple[tuple[int, float], ...] = ()
    # Of the planned seconds, the heat waits' (from room temperature) and the tool changes'.
    planned_heating: float = 0.0
    planned_tool_changes: float = 0.0
    filament: dict[str, Filament] = field(default_factory=dict)  # by tool: "tool0"...
    printing_area: Box | None = None  # of the extruding moves
    travel_area: Box | None = None  # of every move
    layers: int = 0
    slicer: str | None = None  # "PrusaSlicer 2.5.0"
    thumbnails: tuple[Thumbnail, ...] = ()  # the slicer's preview images, where they lie

    def gcode_analysis(self, pace: float = 1.0) -> dict[str, Any]:
        """OctoPrint's ``gcodeAnalysis``. ``estimatedPrintTime`` is the time from the moves
        (what OctoPrint's own analysis gives there) at ``pace`` (a printer's: its moving part
        scaled, see :class:`PlannedTime`), left out when the file has none; the
        slicer's figure is beside it as ``slicerEstimatedPrintTime`` (a key OctoPrint's
        clients ignore), when the file states one. A file with no extruding move has
        OctoPrint's empty result (zeros)."""
        empty = Box(0, 0, 0, 0, 0, 0)
        printing, travel = self.printing_area or empty, self.travel_area or empty
        found: dict[str, Any] = {}
        planned = self.planned
        if planned is not None:
            found["estimatedPrintTime"] = planned.total(pace)
        if self.slicer_seconds is not None:
            found["slicerEstimatedPrintTime"] = self.slicer_seconds
        found["filament"] = {
            tool: {"length": used.length, "volume": used.volume}
            for tool, used in self.filament.items()
        }
        found["dimensions"] = printing.dimensions()
        found["printingArea"] = printing.area()
        found["travelDimensions"] = travel.dimensions()
        found["travelArea"] = travel.area()
        if self.printing_area is None:
            found["_empty"] = True
        return found

    def as_json(self, pace: float = 1.0) -> dict[str, Any]:
        """OctoPrint's ``gcodeAnalysis`` (at ``pace``) with both estimates always present
        (None when unknown), the plan split and the pace, where the limits of ours came
        from, the layer count, the slicer's name and the thumbnails' formats and sizes."""
        thumbnails = [
            {"format": t.format, "width": t.width, "height": t.height} for t in self.thumbnails
        ]
        planned = self.planned
        split = astuple(planned) if planned is not None else (None, None, None)
        names = ("estimatedMoving", "estimatedHeating", "estimatedToolChanges")
        return {
            **self.gcode_analysis(pace),
            "estimatedPrintTime": planned.total(pace) if planned else None,
            **dict(zip(names, split, strict=True)),
            "estimatedPace": round(pace, 4),
            "estimatedPrintTimeLimitsFrom": self.planned_limits_from,
            "slicerEstimatedPrintTime": self.slicer_seconds,
            "layers": self.layers,
            "slicer": self.slicer,
            "thumbnails": thumbnails,
        }

    @property
    def planned(self) -> PlannedTime | None:
        """The planned time, split (None: not planned)."""
        if self.planned_seconds is None:
            return None
        return PlannedTime.of(self.planned_seconds, self.planned_heating, self.planned_tool_changes)

    def planned_after(self, line: int, pace: float = 1.0) -> float | None:
        """The planned seconds after ``line`` (what a job that starts at the next line
        takes), between the points kept in proportion, its moves at ``pace`` and the heat
        waits still ahead as planned (a file heats first); None when the file was not
        planned or its summary keeps no points."""
        points = self.planned_points
        if self.planned_seconds is None or not points:
            return None
        index = bisect_right([at for at, _ in points], line)
        if index >= len(points):
            return 0.0
        after_line, after = points[index]
        before_line, before = points[index - 1] if index > 0 else (0, 0.0)
        share = (line - before_line) / (after_line - before_line) if after_line > before_line else 1
        rest = max(0.0, self.planned_seconds - (before + share * (after - before)))
        heat_left = max(0.0, self.planned_heating - (self.planned_seconds - rest))
        return (rest - heat_left) * pace + heat_left

    def largest_thumbnail(self) -> Thumbnail | None:
        """The embedded image with the most pixels (the one a page shows), if any."""
        return max(self.thumbnails, key=lambda t: t.width * t.height, default=None)

    def as_dict(self) -> dict[str, Any]:
        """All of it, as JSON that :meth:`from_dict` reads back (a cache's)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FileSummary:
        """What :meth:`as_dict` gave (:class:`KeyError`, :class:`TypeError` or
        :class:`ValueError` when it is not)."""

        def box(found: dict[str, float] | None) -> Box | None:
            return Box(**{name: float(value) for name, value in found.items()}) if found else None

        def seconds(found: float | None) -> float | None:
            return float(found) if found is not None else None

        limits_from = data["planned_limits_from"]
        return cls(
            slicer_seconds=seconds(data["slicer_seconds"]),
            planned_seconds=seconds(data["planned_seconds"]),
            planned_limits_from=str(limits_from) if limits_from is not None else None,
            planned_points=tuple(
                (int(line), float(at)) for line, at in data.get("planned_points", ())
            ),
            planned_heating=float(data.get("planned_heating", 0.0)),
            planned_tool_changes=float(data.get("planned_tool_changes", 0.0)),
            filament={
                tool: Filament(float(used["length"]), float(used["volume"]))
                for tool, used in data["filament"].items()
            },
            printing_area=box(data["printing_area"]),
            travel_area=box(data["travel_area"]),
            layers=int(data["layers"]),
            slicer=str(data["slicer"]) if data["slicer"] is not None else None,
            thumbnails=tuple(
                Thumbnail(
                    str(t["format"]), *(int(t[k]) for k in ("width", "height", "start", "end"))
                )
                for t in data["thumbnails"]
            ),
        )


@dataclass
class Analysis:
    """The whole of one pass: the marks, each layer's byte offset, the summary."""

    marks: SlicerMarks
    layer_offsets: list[int]  # where each of marks.layers begins, in bytes
    summary: FileSummary | None  # None when the moves were not read


def analyse(
    path: Path,
    until_line: int | None = None,
    moves: bool = True,
    *,
    planned: bool = False,
    settings: PlanSettings | None = None,
) -> Analysis:
    """``path`` read once (:class:`OSError` when it cannot be). ``until_line``: read no
    further than the piece holding that line (what a recovery needs of a big file; a summary
    is then of that part only). ``moves=False``: the marks and offsets alone, no summary
    (about three times faster: moves are read only for their Z, where no comment says Z).

    ``planned`` (with a summary of the whole file): the summary also carries the print time
    the moves take, read again by :func:`~repetrel_host.gcode.estimate.estimate_file`
    (several times the pass's own cost) with the file's limits, else Marlin's defaults (a
    file is not a machine's: a job's own plan has its machine's), or as ``settings`` say
    (the printer's: then the summary's time is the one its jobs plan, from room
    temperature); None for a file without moves."""
    with path.open("rb") as handle:
        found = scan(chunks(handle), until_line, moves)
    if planned and found.summary is not None and until_line is None:
        timeline = Timeline()
        try:
            estimate = (settings or PlanSettings()).estimate(path, on_time=timeline.add)
        except ArithmeticError:  # numbers past a float's range: the rest of it stands
            return found
        if estimate.moves and math.isfinite(estimate.seconds):  # JSON has no infinity
            timeline.finish()
            found.summary = replace(
                found.summary,
                planned_seconds=estimate.seconds,
                planned_limits_from=estimate.limits_from,
                planned_points=timeline.few(PLANNED_POINTS),
                planned_heating=estimate.heating,
                planned_tool_changes=estimate.tool_change_seconds,
            )
    return found


def chunks(handle: BinaryIO) -> Iterator[bytes]:
    """The file in pieces of whole lines (about 1 MB each, so memory stays small)."""
    rest: list[bytes] = []  # a line without its end yet, in pieces: joined once
    while chunk := handle.read(_CHUNK):
        # After the last LF; in a file of lone CRs, after the last CR but a final one
        # (it may be the first half of a CRLF).
        if b"\n" not in chunk and b"\r" not in chunk[:-1]:
            rest.append(chunk)  # a line of megabytes: not copied again for each chunk
            continue
        data = b"".join((*rest, chunk))
        cut = data.rfind(b"\n") + 1 or data.rfind(b"\r", 0, len(data) - 1) + 1
        data, rest = data[:cut], [data[cut:]]
        if data:
            yield data
    if any(rest):
        yield b"".join(rest)


def scan(pieces: Iterable[bytes], until_line: int | None = None, moves: bool = True) -> Analysis:
    """The pass over pieces of whole lines (see :func:`chunks` and :func:`analyse`)."""
    state = _Pass(moves)
    offset = 0
    past = False  # read past until_line
    for data in pieces:
        state.feed(data, offset)
        offset += len(data)
        if until_line is not None and state.line >= until_line:
            if past:  # a piece more than the line's: the Z set after its layer's marker
                break
            past = True
    return state.result()


def _line_start(data: bytes, raw: bytes, start: int) -> int:
    """Where the whole line ``raw`` begins in ``data``, at or after ``start``."""
    end = len(data)
    while (at := data.find(raw, start)) >= 0:
        after = at + len(raw)
        if (at == 0 or data[at - 1] in b"\r\n") and (after == end or data[after] in b"\r\n"):
            return at
        start = at + 1
    return start  # not reached: raw is one of data's lines


def _words(line: bytes) -> dict[int, float]:
    """A line's words by letter, however they are spaced (the slow path)."""
    return {letter[0]: float(number) for letter, number in _WORD.findall(line)}


def _numbers(text: bytes) -> list[float]:
    """The numbers in ``text`` (one too big for a float: 0)."""
    return [_finite(number) or 0.0 for number in _NUMBERS.findall(text)]


def _finite(text: bytes | str) -> float | None:
    """A number as a float; None when it is too big for one (JSON has no infinity)."""
    value = float(text)
    return value if math.isfinite(value) else None


def duration(text: str) -> float | None:
    """``1d 2h 3m 4s`` (PrusaSlicer's estimate) in seconds."""
    parts = _DURATION.findall(text)
    return float(sum(int(n) * _SECONDS[unit] for n, unit in parts)) if parts else None


def _arc_box(
    start: tuple[float, float], end: tuple[float, float], centre: tuple[float, float], r: float
) -> tuple[float, float, float, float]:
    """The extremes (min x, max x, min y, max y) a counter-clockwise arc passes: the
    circle's east, north, west and south points where the arc sweeps over them (an arc back
    to its start is a whole circle). OctoPrint's ``_addArcMinMax`` misses those of an arc
    that sweeps over east (0°), such as a clockwise half circle through south."""
    begin = math.degrees(math.atan2(start[1] - centre[1], start[0] - centre[0]))
    finish = math.degrees(math.atan2(end[1] - centre[1], end[0] - centre[0]))
    sweep = (finish - begin) % 360 or 360

    def crosses(angle: float) -> bool:
        return (angle - begin) % 360 <= sweep

    cx, cy = centre
    return (
        cx - r if crosses(180) else _INF,
        cx + r if crosses(0) else -_INF,
        cy - r if crosses(270) else _INF,
        cy + r if crosses(90) else -_INF,
    )


class _Pass:
    """The state of one pass; :meth:`feed` takes each piece in order."""

    def __init__(self, moves: bool) -> None:
        self.moves = moves  # False: the marks only (moves read for their Z, if need be)
        self.line = 0  # lines read
        # Marks.
        self.slicer_kind: str | None = None
        self.slicer_layers: list[tuple[int, int]] = []  # (line, offset)
        self.hyrel_layers: list[tuple[int, int]] = []
        self.comment_z: list[tuple[int, float]] = []  # ;Z: comments: when any, they say Z
        self.move_z: list[tuple[int, float]] = []
        self.marks = SlicerMarks()
        self.estimate: float | None = None
        self.slicer: str | None = None
        self.used_mm: list[float] = []
        self.used_cm3: list[float] = []
        self.diameters: list[float] = []
        self.thumbnails: list[Thumbnail] = []
        self.thumbnail_open: tuple[str, int, int, int] | None = None  # format, size, start
        # Moves.
        self.pos = [0.0, 0.0, 0.0]
        self.relative = False  # G91
        self.relative_e = False  # M83
        self.tool = 0
        self.e = [0.0]  # each tool's E register
        self.net = [0.0]  # each tool's net extrusion
        self.peak = [0.0]  # the most the net ever was
        # min x, max x, min y, max y, min z, max z; Z from the bed (OctoPrint's bedZ 0).
        self.printed = [_INF, -_INF, _INF, -_INF, 0.0, -_INF]
        self.travelled = [_INF, -_INF, _INF, -_INF, 0.0, -_INF]

    def feed(self, data: bytes, offset: int) -> None:
        """One piece of whole lines, which begins ``offset`` bytes into the file."""
        if b"\n" not in data:  # lone CRs end its lines (same length: offsets hold)
            data = data.replace(b"\r", b"\n")
        searched = 0  # where the next M790's line is looked for in data
        number = self.line
        x, y, z = self.pos
        tool = self.tool
        e_now, net, peak = self.e[tool], self.net[tool], self.peak[tool]
        relative, relative_e = self.relative, self.relative or self.relative_e
        p_min_x, p_max_x, p_min_y, p_max_y, p_min_z, p_max_z = self.printed
        t_min_x, t_max_x, t_min_y, t_max_y, t_min_z, t_max_z = self.travelled
        printing = False  # the last move extruded: where this one starts is in its box
        joined = False  # where this move starts is in the travel box
        move_z = self.move_z
        z_from_moves = not self.comment_z
        marks_only = not self.moves
        # LF, CRLF and lone CR end lines, as the job counts them.
        for number, raw in enumerate(data.splitlines(), self.line + 1):
            arc = clockwise = False
            if raw.startswith(_FAST):  # G1 X1.2 Y3.4 E.05: most of a file
                if marks_only and not (z_from_moves and b"Z" in raw):
                    continue
                cut = raw.find(b";")
                nx = ny = nz = ne = None
                try:
                    for word in (raw[:cut] if cut >= 0 else raw).split()[1:]:
                        letter = word[0]
                        if letter == _X:
                            nx = float(word[1:])
                        elif letter == _Y:
                            ny = float(word[1:])
                        elif letter == _E:
                            ne = float(word[1:])
                        elif letter == _Z:
                            nz = float(word[1:])
                except ValueError:  # X 1, or no number: the exact reading
                    found = _words(raw[2:cut] if cut >= 0 else raw[2:])
                    nx, ny, nz, ne = found.get(_X), found.get(_Y), found.get(_Z), found.get(_E)
                ai = aj = ar = None
            else:
                line = raw.strip()
                if not line:
                    continue
                head = line[0]
                if head == 59:  # ;
                    self._comment(raw, number, data, offset)
                    z_from_moves = not self.comment_z
                    continue
                if head > 96:  # lower case
                    line = line.upper()
                    head = line[0]
                if head != 71 and head != 77 and head != 84:  # G, M, T
                    continue
                cut = line.find(b";")
                if cut >= 0:
                    line = line[:cut]
                if _GLUED.match(line):  # G1X1Y2: spaced, then read
                    line = re.sub(rb"(?<=[\d.])(?=[A-Z])", b" ", line)
                words = line.split()
                if not words:
                    continue
                code = words[0]
                if code in _MOVES:
                    found = _words(line[len(code) :])
                    nx, ny, nz, ne = found.get(_X), found.get(_Y), found.get(_Z), found.get(_E)
                    ai, aj, ar = found.get(_I), found.get(_J), found.get(_R)
                    arc = code in _ARCS
                    clockwise = code in (b"G2", b"G02")
                elif code == b"G92":
                    found = _words(line[3:])
                    if not found:
                        x = y = z = e_now = 0.0
                    x, y, z = found.get(_X, x), found.get(_Y, y), found.get(_Z, z)
                    e_now = found.get(_E, e_now)
                    printing = joined = False
                    continue
                elif code == b"G28":  # the axes it names (G28 X, G28 X0), else all
                    axes = set(_AXES.findall(line[3:])) or {b"X", b"Y", b"Z"}
                    x = 0.0 if b"X" in axes else x
                    y = 0.0 if b"Y" in axes else y
                    z = 0.0 if b"Z" in axes else z
                    printing = joined = False
                    continue
                elif code == b"G90" or code == b"G91":
                    relative = code == b"G91"
                    relative_e = relative or self.relative_e
                    continue
                elif code == b"M82" or code == b"M83":
                    self.relative_e = code == b"M83"
                    relative_e = relative or self.relative_e
                    continue
                elif code == b"M73":
                    self._progress(line[3:], number)
                    continue
                elif code == b"M790":
                    searched = _line_start(data, raw, searched)
                    self.hyrel_layers.append((number, offset + searched))
                    searched += len(raw)
                    continue
                elif head == 84 and code[1:].isdigit() and len(code) < 5:  # a tool change
                    chosen = int(code[1:])
                    if chosen != tool and chosen <= MAX_TOOL:
                        self.e[tool], self.net[tool], self.peak[tool] = e_now, net, peak
                        for kept in (self.e, self.net, self.peak):
                            kept.extend([0.0] * (chosen + 1 - len(kept)))
                        tool = chosen
                        e_now, net, peak = self.e[tool], self.net[tool], self.peak[tool]
                    continue
                else:
                    continue
            # A move: where it goes, what it extrudes, the boxes it reaches.
            old_x, old_y, old_z = x, y, z
            if relative:
                x += nx or 0.0
                y += ny or 0.0
                z += nz or 0.0
            else:
                if nx is not None:
                    x = nx
                if ny is not None:
                    y = ny
                if nz is not None:
                    z = nz
            delta = 0.0
            if ne is not None:
                delta = ne if relative_e else ne - e_now
                e_now += delta
                net += delta
                if net > peak:
                    peak = net
            if nz is not None and z_from_moves and math.isfinite(z):
                move_z.append((number, z))
            if nx is None and ny is None and nz is None and not arc:
                continue  # no move (E alone, F alone)
            # Where the move starts is the last one's end, in each box already unless the
            # position was set since (and at first). Only the coordinates it names change.
            if not joined:
                joined = True
                t_min_x, t_max_x = min(t_min_x, old_x), max(t_max_x, old_x)
                t_min_y, t_max_y = min(t_min_y, old_y), max(t_max_y, old_y)
                t_min_z, t_max_z = min(t_min_z, old_z), max(t_max_z, old_z)
            if nx is not None:
                if x < t_min_x:
                    t_min_x = x
                elif x > t_max_x:
                    t_max_x = x
            if ny is not None:
                if y < t_min_y:
                    t_min_y = y
                elif y > t_max_y:
                    t_max_y = y
            if nz is not None:
                if z < t_min_z:
                    t_min_z = z
                elif z > t_max_z:
                    t_max_z = z
            if delta > 0:
                if not printing:
                    printing = True
                    p_min_x, p_max_x = min(p_min_x, old_x), max(p_max_x, old_x)
                    p_min_y, p_max_y = min(p_min_y, old_y), max(p_max_y, old_y)
                    p_min_z, p_max_z = min(p_min_z, old_z), max(p_max_z, old_z)
                if nx is not None:
                    if x < p_min_x:
                        p_min_x = x
                    if x > p_max_x:
                        p_max_x = x
                if ny is not None:
                    if y < p_min_y:
                        p_min_y = y
                    if y > p_max_y:
                        p_max_y = y
                if nz is not None:
                    if z < p_min_z:
                        p_min_z = z
                    if z > p_max_z:
                        p_max_z = z
            else:
                printing = False
            if arc:
                r = ar if ar is not None else math.hypot(ai or 0.0, aj or 0.0)
                centre = (old_x + (ai or 0.0), old_y + (aj or 0.0))
                start, end = ((x, y), (old_x, old_y)) if clockwise else ((old_x, old_y), (x, y))
                low_x, high_x, low_y, high_y = _arc_box(start, end, centre, r)
                t_min_x, t_max_x = min(t_min_x, low_x), max(t_max_x, high_x)
                t_min_y, t_max_y = min(t_min_y, low_y), max(t_max_y, high_y)
                if delta > 0:
                    p_min_x, p_max_x = min(p_min_x, low_x), max(p_max_x, high_x)
                    p_min_y, p_max_y = min(p_min_y, low_y), max(p_max_y, high_y)
        self.line = number
        self.pos = [x, y, z]
        self.relative = relative
        self.tool = tool
        self.e[tool], self.net[tool], self.peak[tool] = e_now, net, peak
        self.printed = [p_min_x, p_max_x, p_min_y, p_max_y, p_min_z, p_max_z]
        self.travelled = [t_min_x, t_max_x, t_min_y, t_max_y, t_min_z, t_max_z]

    def _progress(self, words: bytes, number: int) -> None:
        """M73's percent done and minutes left."""
        found = {w.upper(): _finite(v) for w, v in _M73_WORD.findall(words.decode())}
        if found:
            self.marks.progress.append((number, found.get("P"), found.get("R")))

    def _comment(self, raw: bytes, number: int, data: bytes, offset: int) -> None:
        match = _COMMENT.match(raw.lstrip())
        if match is None:
            return
        kind = match.lastgroup
        marks = self.marks
        if kind in ("prusa", "cura", "s3d_z"):
            kind = "s3d" if kind == "s3d_z" else kind
            self.slicer_kind = self.slicer_kind or kind
            if kind == self.slicer_kind:
                # Not with the M790s' search start: comments are rarely marks, so look from
                # the last slicer mark's line (kept in the list) or the piece's start.
                start = self.slicer_layers[-1][1] - offset + 1 if self.slicer_layers else 0
                at = _line_start(data, raw, max(start, 0))
                self.slicer_layers.append((number, offset + at))
            z = _finite(match["s3d_z"]) if kind == "s3d" else None
            if z is not None:
                self.comment_z.append((number, z))
        elif kind == "z" and (z := _finite(match["z"])) is not None:
            self.comment_z.append((number, z))
        elif kind == "elapsed" and (elapsed := _finite(match["elapsed"])) is not None:
            marks.elapsed.append((number, elapsed))
        elif kind == "total":
            self.estimate = _finite(match["total"])
        elif kind == "estimate" and self.estimate is None:
            self.estimate = duration(match["estimate"].decode(errors="replace"))
        elif kind == "used_mm":
            self.used_mm = _numbers(match["used_mm"])
        elif kind == "used_cm3":
            self.used_cm3 = _numbers(match["used_cm3"])
        elif kind == "used_m" and not self.used_mm:
            self.used_mm = [metres * 1000 for metres in _numbers(match["used_m"])]
        elif kind == "diameter":
            self.diameters = _numbers(match["diameter"])
        elif kind == "slicer" and self.slicer is None:
            self.slicer = _slicer_name(match["slicer"].decode(errors="replace"))
        elif kind == "thumb_begin":
            # Its base64 lines start after this line (a line end the reader skips).
            start = offset + _line_start(data, raw, 0) + len(raw)
            found = (match["thumb_format"] or b"PNG").decode().upper()
            width, height = int(match["thumb_width"]), int(match["thumb_height"])
            self.thumbnail_open = (found, width, height, start)
        elif kind == "thumb_end" and self.thumbnail_open is not None:
            found, width, height, start = self.thumbnail_open
            end = offset + _line_start(data, raw, max(start - offset, 0))
            self.thumbnails.append(Thumbnail(found, width, height, start, end))
            self.thumbnail_open = None

    def result(self) -> Analysis:
        marks = self.marks
        marks.total_seconds = self.estimate
        marks.z_changes = self.comment_z or self.move_z
        found = self.slicer_layers or self.hyrel_layers
        marks.layers = [
            _with_z(Layer(n, line, None), marks.z_changes) for n, (line, _) in enumerate(found, 1)
        ]
        if not self.moves:
            return Analysis(marks, [at for _, at in found], None)
        summary = FileSummary(
            slicer_seconds=self.estimate,
            filament=self._filament(),
            printing_area=_box(self.printed),
            travel_area=_box(self.travelled),
            layers=len(found),
            slicer=self.slicer,
            thumbnails=tuple(self.thumbnails),
        )
        return Analysis(marks, [at for _, at in found], summary)

    def _filament(self) -> dict[str, Filament]:
        """By tool: the slicer's figures where it wrote them, else the moves' (tools that
        extruded nothing are left out)."""
        lengths = self.used_mm or self.peak
        used: dict[str, Filament] = {}
        for tool, length in enumerate(lengths):
            if not 0 < length < _INF:
                continue
            if tool < len(self.used_cm3) and self.used_mm:
                volume = self.used_cm3[tool]
            else:
                diameters = self.diameters or [DEFAULT_DIAMETER]
                diameter = diameters[min(tool, len(diameters) - 1)]
                volume = length * math.pi * (diameter / 2) ** 2 / 1000
            if math.isfinite(volume):
                used[f"tool{tool}"] = Filament(round(length, 5), round(volume, 5))
        return used


def _box(limits: list[float]) -> Box | None:
    min_x, max_x, min_y, max_y, min_z, max_z = limits
    if min_x > max_x:  # nothing recorded
        return None
    box = Box(min_x, min_y, min_z, max_x, max_y, max(max_z, min_z))
    if not all(math.isfinite(size) for size in box.dimensions().values()):
        return None  # a move to X1e999: not a box JSON can say
    return box


def _slicer_name(text: str) -> str | None:
    """``PrusaSlicer 2.5.0 on 2026-11-22 at ...`` as ``PrusaSlicer 2.5.0``."""
    words = [w for w in text.replace("(R)", "").split() if w.lower() != "version"]
    if not words:
        return None
    name = words[0].removesuffix("_SteamEngine")
    if len(words) > 1 and words[1][:1].isdigit():
        return f"{name} {words[1]}"
    return name


def _with_z(layer: Layer, z_changes: list[tuple[int, float]]) -> Layer:
    """A layer's Z: the first Z set at or after its marker (before: the one in force)."""
    index = bisect_right(z_changes, layer.line - 1, key=lambda item: item[0])
    if index < len(z_changes):
        return Layer(layer.number, layer.line, z_changes[index][1])
    return Layer(layer.number, layer.line, z_changes[-1][1] if z_changes else None)


def scan_marks(path: Path, until_line: int | None = None) -> SlicerMarks:
    """The slicer's marks in ``path`` (none for an unreadable file); ``until_line``: read
    no further than the piece holding that line (what a recovery needs of a big file)."""
    try:
        return analyse(path, until_line, moves=False).marks
    except OSError:
        return SlicerMarks()


def slicer_estimate(path: Path, span: int = 1 << 16) -> float | None:
    """The slicer's estimate of the whole print in seconds, from the file's first and last
    ``span`` bytes, where slicers write it (Cura's ``;TIME:`` and PrusaSlicer's first
    ``M73 R`` at the top, PrusaSlicer's "estimated printing time" at the end); None where
    the file gives none. Cheap for any size of file."""
    try:
        with path.open("rb") as handle:
            head = handle.read(span)
            size = handle.seek(0, 2)
            handle.seek(max(size - span, len(head)))
            tail = handle.read()
    except OSError:
        return None
    if size > len(head) + len(tail):  # a gap between them: whole lines on both sides
        head = head[: head.rfind(b"\n") + 1]
        tail = tail[tail.find(b"\n") + 1 :]
    marks = scan(iter([head, tail]), None, False).marks
    if marks.total_seconds is not None:
        return marks.total_seconds
    first = next((left for _, _, left in marks.progress if left is not None), None)
    return first * 60 if first is not None else None  # M73 R: minutes left at the start
