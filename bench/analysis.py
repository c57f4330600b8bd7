"""One pass over a job's file against the two it replaced (issue 22).

    python bench/analysis.py                # the cone, and a 200 MB file (the sphere repeated)
    python bench/analysis.py --size 50      # a 50 MB one

Before: the server read a job's file twice as it started, ``layer_offsets`` (a Python loop
over its lines for the byte offsets of layer marks) and ``scan_marks`` (regular expressions
over 1 MB pieces for layers, Z and estimates); both are copied below as they were. After:
:func:`repetrel_host.gcode.analysis.analyse`, which gives both and OctoPrint's analysis
(filament, boxes) in one pass. Each is run in turn (before, after, before, ...) three times;
the medians of wall and CPU time are printed. The big file is built in the temporary folder
and removed after.
"""

from __future__ import annotations

import argparse
import re
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from repetrel_host.gcode.analysis import analyse, chunks

DATA = Path(__file__).resolve().parent.parent / "tests" / "data"

# --- before: the two passes, as they were (src/repetrel_host at aefd9de) ----------------

_LAYER_MARKS = (b";LAYER_CHANGE", b";LAYER:", b"M790")
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
_LAYER_KINDS = {"prusa": "prusa", "cura": "cura", "s3d": "s3d", "s3d_z": "s3d", "hyrel": "hyrel"}


def layer_offsets(path: Path) -> list[int]:
    offsets: list[int] = []
    offset = 0
    with path.open("rb") as handle:
        for line in handle:
            if line.lstrip().startswith(_LAYER_MARKS):
                offsets.append(offset)
            offset += len(line)
    return offsets


def _line_ends(data: bytes) -> int:
    return data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n")


def scan_marks(path: Path) -> int:
    """The old pass, less the final Z per layer (a bisect per layer: nothing to measure)."""
    layers: list[int] = []
    progress: list[tuple[int, float | None, float | None]] = []
    move_z: list[tuple[int, float]] = []
    comment_z: list[tuple[int, float]] = []
    elapsed: list[tuple[int, float]] = []
    layer_kind: str | None = None
    first_line = 1
    with path.open("rb") as handle:
        for data in chunks(handle):
            if b"\n" not in data:
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
                        layers.append(line)
                    if kind == "s3d":
                        comment_z.append((line, float(match["s3d_z"])))
                elif kind == "z":
                    comment_z.append((line, float(match["z"])))
                elif kind == "move_z" and not comment_z:
                    move_z.append((line, float(match["move_z"])))
                elif kind == "m73":
                    words = {
                        w.upper(): float(v) for w, v in _M73_WORD.findall(match["m73"].decode())
                    }
                    if words:
                        progress.append((line, words.get("P"), words.get("R")))
                elif kind == "elapsed":
                    elapsed.append((line, float(match["elapsed"])))
            first_line += _line_ends(data)
    return len(layers)


def before(path: Path) -> int:
    return len(layer_offsets(path)) + scan_marks(path)


def after(path: Path) -> int:
    return 2 * len(analyse(path).layer_offsets)


def after_marks(path: Path) -> int:
    return 2 * len(analyse(path, moves=False).layer_offsets)


# --- the measurement ---------------------------------------------------------------------


def timed(work: Callable[[Path], int], path: Path) -> tuple[float, float, int]:
    wall, cpu = time.perf_counter(), time.process_time()
    found = work(path)
    return time.perf_counter() - wall, time.process_time() - cpu, found


def compare(path: Path, runs: int) -> None:
    figures: dict[str, list[tuple[float, float]]] = {"before": [], "after": [], "marks": []}
    counts = set()
    for _ in range(runs):
        for name, work in (("before", before), ("after", after), ("marks", after_marks)):
            wall, cpu, found = timed(work, path)
            figures[name].append((wall, cpu))
            counts.add(found)
    size = path.stat().st_size / 1e6
    walls = {name: statistics.median(w for w, _ in runs_) for name, runs_ in figures.items()}
    cpus = {name: statistics.median(c for _, c in runs_) for name, runs_ in figures.items()}
    print(f"{path.name} ({size:.1f} MB), median of {runs}:")
    for name in figures:
        print(
            f"  {name:6}  wall {walls[name]:7.2f} s  cpu {cpus[name]:7.2f} s"
            f"  ({size / walls[name]:5.1f} MB/s)"
        )
    for name in ("after", "marks"):
        print(f"  {name}/before: wall {walls[name] / walls['before']:.2f}x", end="")
        print(f", cpu {cpus[name] / cpus['before']:.2f}x")
    if len(counts) != 1:
        print(f"  the layer counts differ: {sorted(counts)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=200, help="the big file, in MB")
    parser.add_argument("--runs", type=int, default=3)
    options = parser.parse_args()
    compare(DATA / "cone-prusaslicer.gcode", options.runs)
    sphere = (DATA / "sphere-prusaslicer.gcode").read_bytes()
    with tempfile.TemporaryDirectory() as folder:
        big = Path(folder) / f"sphere-{options.size}mb.gcode"
        with big.open("wb") as out:
            for _ in range(max(1, options.size * 1_000_000 // len(sphere))):
                out.write(sphere)
        compare(big, options.runs)


if __name__ == "__main__":
    main()
