"""Print time from the moves (issue 37): ours against PrusaSlicer's own figure and OctoPrint's
method, on the PrusaSlicer files in tests/data with their time comments removed.

    python bench/estimate.py            # the table
    python bench/estimate.py --lines 100000   # and the cost on a long file (the sphere, repeated)

For each file: PrusaSlicer's "estimated printing time (normal mode)" (the reference); ours
with the limits from its configuration block; ours with the same limits given as
``M201``-``M205`` lines at the top instead (the block's ``machine_max_*`` lines removed);
ours with no limits anywhere (Marlin's defaults); and OctoPrint's analysis (distance over
feed rate, no acceleration), each with its error against PrusaSlicer's. The CPU seconds are
ours with the configuration block's limits.
"""

from __future__ import annotations

import argparse
import math
import re
import resource
import tempfile
import time
from pathlib import Path

from repetrel_host.gcode.estimate import estimate_file

DATA = Path(__file__).resolve().parent.parent / "tests" / "data"
FILES = ("cone-prusaslicer.gcode", "sphere-prusaslicer.gcode")
_TIME = re.compile(r"; estimated printing time \(normal mode\) = (.+)")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_LIMIT = re.compile(r";\s*machine_max_([a-z]+)_([a-z]+)\s*=\s*([-\d.]+)")


def seconds_of(text: str) -> float:
    """PrusaSlicer's "1d 2h 3m 4s"."""
    units = {"d": 86400, "h": 3600, "m": 60, "s": 1}
    return float(sum(int(n) * units[u] for n, u in re.findall(r"(\d+)([dhms])", text)))


def without_times(lines: list[str]) -> list[str]:
    """The file without what states its time: M73 progress lines and the estimate comments."""
    return [ln for ln in lines if not ln.startswith("M73") and "estimated printing time" not in ln]


def limits_as_lines(lines: list[str]) -> list[str]:
    """The configuration block's limits as M201/M203/M204/M205 at the top, the block's own
    ``machine_max_*`` lines removed."""
    values: dict[tuple[str, str], str] = {}
    for line in lines:
        match = _LIMIT.match(line)
        if match:
            values[(match.group(1), match.group(2))] = match.group(3)
    axes = "xyze"

    def words(kind: str) -> str:
        return " ".join(f"{a.upper()}{values[(kind, a)]}" for a in axes if (kind, a) in values)

    header = [
        f"M201 {words('acceleration')}",
        f"M203 {words('feedrate')}",
        f"M204 P{values[('acceleration', 'extruding')]} R{values[('acceleration', 'retracting')]}"
        f" T{values[('acceleration', 'extruding')]}",
        f"M205 {words('jerk')}",
    ]
    return header + [ln for ln in lines if not _LIMIT.match(ln)]


def without_limits(lines: list[str]) -> list[str]:
    return [ln for ln in lines if not _LIMIT.match(ln)]


def octoprint_method(path: Path) -> float:
    """OctoPrint 1.11's analysis: each move's longest of its XYZ and E lengths over its feed
    rate, plus dwells; no acceleration."""
    x = y = z = e = 0.0
    feed = 1500.0
    absolute = absolute_e = True
    total = 0.0
    for raw in path.read_text(encoding="utf-8").splitlines():
        command = raw.split(";", 1)[0].strip().upper()
        if not command:
            continue
        head, *rest = command.split()
        words = {
            w[0]: float(w[1:])
            for w in rest
            if len(w) > 1 and w[1:].lstrip("-.").replace(".", "", 1).isdigit()
        }
        if head in ("G0", "G1"):
            feed = words.get("F", feed)
            nx = words.get("X", 0.0 if not absolute else x) + (x if not absolute else 0.0)
            ny = words.get("Y", 0.0 if not absolute else y) + (y if not absolute else 0.0)
            nz = words.get("Z", 0.0 if not absolute else z) + (z if not absolute else 0.0)
            ne = words.get("E", 0.0 if not absolute_e else e) + (e if not absolute_e else 0.0)
            length = max(math.dist((x, y, z), (nx, ny, nz)), abs(ne - e))
            total += length / (feed / 60.0) if feed > 0 else 0.0
            x, y, z, e = nx, ny, nz, ne
        elif head == "G4":
            total += words.get("S", 0.0) + words.get("P", 0.0) / 1000.0
        elif head == "G92":
            x, y, z, e = (words.get(a, v) for a, v in zip("XYZE", (x, y, z, e), strict=True))
        elif head in ("G90", "G91"):
            absolute = absolute_e = head == "G90"
        elif head in ("M82", "M83"):
            absolute_e = head == "M82"
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--lines", type=int, help="also time a file about this long")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name in FILES:
            lines = (DATA / name).read_text(encoding="utf-8").splitlines()
            reference = next(seconds_of(m.group(1)) for ln in lines if (m := _TIME.match(ln)))
            variants = {
                "config": without_times(lines),
                "m-lines": limits_as_lines(without_times(lines)),
                "none": without_limits(without_times(lines)),
            }
            figures = {}
            for variant, text in variants.items():
                path = Path(folder) / f"{variant}-{name}"
                path.write_text("\n".join(text) + "\n", encoding="utf-8")
                started = time.process_time()
                figures[variant] = estimate_file(path).moving
                if variant == "config":
                    cpu = time.process_time() - started
                    octoprint = octoprint_method(path)
            rows.append((name, reference, figures, octoprint, cpu, len(lines)))
        print(
            "| file | PrusaSlicer s | ours (settings) | ours (M201-M205) | ours (no limits) "
            "| OctoPrint's method | CPU s (lines) |"
        )
        print("|---|---|---|---|---|---|---|")
        for name, reference, figures, octoprint, cpu, count in rows:

            def cell(value: float, reference: float = reference) -> str:
                return f"{value:,.1f} ({(value - reference) / reference:+.2%})"

            print(
                f"| {name} | {reference:,.0f} | {cell(figures['config'])} | "
                f"{cell(figures['m-lines'])} | {cell(figures['none'])} | {cell(octoprint)} | "
                f"{cpu:.2f} ({count:,}) |"
            )
        if args.lines:
            sphere = (DATA / FILES[1]).read_text(encoding="utf-8")
            copies = max(1, math.ceil(args.lines / sphere.count("\n")))
            big = Path(folder) / "big.gcode"
            with big.open("w", encoding="utf-8") as file:
                for _ in range(copies):
                    file.write(sphere)
            started = time.process_time()
            result = estimate_file(big)
            cpu = time.process_time() - started
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(
                f"\n{copies * sphere.count(chr(10)):,} lines ({big.stat().st_size / 1e6:.0f} MB): "
                f"{cpu:.2f} s CPU, estimate {result.seconds:,.0f} s, peak RSS {rss:.0f} MB"
            )


if __name__ == "__main__":
    main()
