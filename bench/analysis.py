"""One pass over a job's file against the two it replaced (issue 22), and its memory (issue 23).

    python bench/analysis.py                # the cone, and a 200 MB file (the sphere repeated)
    python bench/analysis.py --size 50      # a 50 MB one
    python bench/analysis.py --memory       # the whole pass on 20 MB and 1 GB: time, peak RSS
    python bench/analysis.py --memory --memory-sizes 20 200   # other sizes (MB)
    python bench/analysis.py --quick        # small inputs (--memory: 2 and 40 MB; a test runs it)

Before: the server read a job's file twice as it started, ``layer_offsets`` (a Python loop
over its lines for the byte offsets of layer marks) and ``scan_marks`` (regular expressions
over 1 MB pieces for layers, Z and estimates); both are copied below as they were. After:
:func:`repetrel_host.gcode.analysis.analyse`, which gives both and OctoPrint's analysis
(filament, boxes) in one pass. Each is run in turn (before, after, before, ...) three times;
the medians of wall and CPU time are printed. The big file is built in the temporary folder
and removed after.

``--memory``: for each size, a file of that size (the sphere repeated, built in the temporary
folder, removed after; its free space is checked first) is analysed whole (``analyse(path)``,
moves read) in a fresh Python process, so that the peak RSS is that run's alone. The process
notes its peak RSS (``ru_maxrss``) after its imports and again after the pass; the growth is
what the pass held at its most. A pass that streams grows by its pieces and its result (a few
hundred bytes a layer), not by the file.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import statistics
import subprocess
import sys
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


def build(folder: Path, size_mb: float) -> Path:
    """A file of about ``size_mb`` MB in ``folder``: the sphere repeated."""
    sphere = (DATA / "sphere-prusaslicer.gcode").read_bytes()
    times = max(1, round(size_mb * 1_000_000 / len(sphere)))
    path = folder / f"sphere-x{times}.gcode"
    with path.open("wb") as out:
        for _ in range(times):
            out.write(sphere)
    return path


# --- memory: the whole pass in a fresh process -------------------------------------------

# Run by ``sys.executable -c``: the imports, the peak RSS so far, the pass, the peak again,
# and the RSS at the end, the result still held (its lists grow with the layers).
_CHILD = """
import json, os, resource, sys, time
from pathlib import Path
from repetrel_host.gcode.analysis import analyse

def peak():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB

def now():
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return None

before = peak()
wall, cpu = time.perf_counter(), time.process_time()
found = analyse(Path(sys.argv[1]))
wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
print(json.dumps({"wall": wall, "cpu": cpu, "before": before, "after": peak(), "end": now(),
                  "layers": len(found.layer_offsets)}))
"""

MB = 2**20  # RSS in MB as bench/run.py gives it; file sizes in 10^6 bytes


def measure(path: Path) -> dict[str, float]:
    """``analyse(path)`` in a fresh process: its figures (see ``_CHILD``)."""
    result = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path)], capture_output=True, text=True, check=False
    )
    if result.returncode != 0:
        raise SystemExit(f"the pass over {path.name} failed:\n{result.stderr}")
    return json.loads(result.stdout)


def memory(sizes: list[float]) -> bool:
    """The memory table for these file sizes (MB); False when a file could not be built."""
    sphere = (DATA / "sphere-prusaslicer.gcode").stat().st_size
    rows, complete = [], True
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        for size in sizes:
            needed = max(1, round(size * 1_000_000 / sphere)) * sphere
            free = shutil.disk_usage(folder).free
            if free < needed + 100_000_000:  # and some room left for everyone else
                print(
                    f"not enough free space in {folder.parent} for the {size:g} MB file: "
                    f"{needed / 1e6:,.0f} MB needed (and 100 MB to spare), "
                    f"{free / 1e6:,.0f} MB free; set TMPDIR to a roomier folder or pass smaller "
                    "--memory-sizes",
                    file=sys.stderr,
                )
                complete = False
                continue
            path = build(folder, size)
            try:
                figures = measure(path)
            finally:
                path.unlink()
            rows.append((path.name, needed, figures))
    print(
        "| file | size MB | layers | wall s | CPU s | MB/s (CPU) | peak RSS before MB "
        "| peak RSS after MB | growth MB | RSS at the end MB |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for file, size, f in rows:
        end = "-" if f["end"] is None else f"{f['end'] / MB:.1f}"
        print(
            f"| {file} | {size / 1e6:,.1f} | {f['layers']:,} | {f['wall']:.2f} | {f['cpu']:.2f} "
            f"| {size / 1e6 / f['cpu']:.1f} | {f['before'] / MB:.1f} | {f['after'] / MB:.1f} "
            f"| {(f['after'] - f['before']) / MB:.1f} | {end} |"
        )
    return complete


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=200, help="the big file, in MB")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument(
        "--memory", action="store_true", help="the whole pass's time and peak RSS, by file size"
    )
    parser.add_argument(
        "--memory-sizes",
        type=float,
        nargs="+",
        default=[20, 1000],
        metavar="MB",
        help="the files' sizes for --memory (default: 20 1000)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="small inputs: 5 MB, one run; --memory: 2 and 40 MB"
    )
    options = parser.parse_args()
    if options.memory:
        sizes = [2, 40] if options.quick else options.memory_sizes
        raise SystemExit(0 if memory(sizes) else 1)
    runs, size = (1, 5) if options.quick else (options.runs, options.size)
    compare(DATA / "cone-prusaslicer.gcode", runs)
    with tempfile.TemporaryDirectory() as folder:
        compare(build(Path(folder), size), runs)


if __name__ == "__main__":
    main()
