"""The benchmarks run (on small inputs; their figures live in bench/README.md)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.pg import needs_postgres

SOAK = Path(__file__).parent.parent / "bench" / "soak.py"


@pytest.mark.timeout(120)
def test_soak_bench_runs_and_reports_exactly_once() -> None:
    result = subprocess.run(
        [sys.executable, str(SOAK), "--lines", "3000", "--flow", "buffered"],
        capture_output=True,
        text=True,
        timeout=110,
    )
    assert result.returncode == 0, result.stderr
    assert "exactly once" in result.stdout
    assert "stall/ok" in result.stdout


RUN = Path(__file__).parent.parent / "bench" / "run.py"


def quick_table(script: Path, timeout: float) -> tuple[str, list[str], list[list[str]]]:
    """Run a benchmark with --quick: its output, its table's header and rows."""
    result = subprocess.run(
        [sys.executable, str(script), "--quick"], capture_output=True, text=True, timeout=timeout
    )
    assert result.returncode == 0, result.stderr
    rows = [line.split("|")[1:-1] for line in result.stdout.splitlines() if line.startswith("| ")]
    header, *table = [[cell.strip() for cell in row] for row in rows]
    return result.stdout, header, table


@pytest.mark.timeout(240)
@pytest.mark.slow
def test_speed_bench_prints_every_figure_against_printcore() -> None:
    output, header, table = quick_table(RUN, 230)
    assert header[:4] == ["host", "link", "lines", "lines/s"]
    hosts = {(row[0], row[1]) for row in table}
    for link in ("uart", "usb"):
        for host in ("ours-buffered", "ours-unbuffered", "ours-hyrel", "printcore", "ideal"):
            assert (host, link) in hosts
    assert ("ours-buffered", "uart+advanced_ok") in hosts
    for host in ("ours-buffered", "ours-unbuffered", "printcore"):  # moves that take time
        assert (host, "uart+planner") in hosts
    for row in table:
        figures = dict(zip(header, row, strict=True))
        assert figures["exactly once"] == "yes"
        if figures["host"].startswith("ours"):  # a healthy link draws no error
            assert figures["errors /10k lines"] == "0.0"
        assert float(figures["lines/s"].replace(",", "")) > 0
        assert float(figures["CPU µs/line"]) > 0 and float(figures["peak RSS MB"]) > 0
        if figures["link"].startswith("uart"):
            assert figures["dropped B"] == "0"
    assert "first job line on the wire" in output


SERVER = Path(__file__).parent.parent / "bench" / "server.py"


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_server_bench_streams_to_four_printers_and_reports_each() -> None:
    _, header, table = quick_table(SERVER, 170)
    assert header[:5] == ["link", "printers", "printer", "lines", "lines/s"]
    assert [(row[0], row[1], row[2]) for row in table] == [
        (link, count, printer)
        for link in ("uart", "usb")
        for count, printer in [("1", "p0"), *[("4", f"p{i}") for i in range(4)]]
    ]
    assert all(float(row[4].replace(",", "")) > 0 for row in table)
    assert float(table[0][6]) > 0 and float(table[0][7]) > 0  # the server's, a fake's CPU


ANALYSIS = Path(__file__).parent.parent / "bench" / "analysis.py"


@pytest.mark.timeout(90)
@pytest.mark.slow
def test_analysis_bench_memory_grows_with_the_layers_not_the_file() -> None:
    """The whole pass over 2 and 40 MB files, each in its own process: the bigger file's peak
    RSS grows by a few MB, as the smaller's does (a pass that read the file whole would grow
    by 40 MB and more)."""
    result = subprocess.run(
        [sys.executable, str(ANALYSIS), "--memory", "--quick"],
        capture_output=True,
        text=True,
        timeout=80,
    )
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    header, *table = [[cell.strip() for cell in line.split("|")[1:-1]] for line in lines]
    rows = [dict(zip(header, row, strict=True)) for row in table]
    assert [round(float(row["size MB"].replace(",", ""))) for row in rows] == [2, 40]
    small, big = rows
    assert int(big["layers"].replace(",", "")) == 20 * int(small["layers"])
    growth = [float(row["growth MB"]) for row in rows]
    # The smaller's growth moves between 2 and 3 MB from run to run (the allocator's own).
    assert growth[1] <= 3 * max(growth[0], 3.0), growth
    assert growth[1] < float(big["size MB"].replace(",", "")) / 4, growth


FARM = Path(__file__).parent.parent / "bench" / "farm.py"


@pytest.mark.timeout(300)
@needs_postgres
@pytest.mark.slow
def test_farm_bench_reports_latency_throughput_and_claims() -> None:
    done = subprocess.run(
        [sys.executable, str(FARM), "--quick"], capture_output=True, text=True, timeout=280
    )
    assert done.returncode == 0, done.stdout + done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["submit_to_first_line_median_ms"] > 0
    assert figures["jobs_per_second_six_printers"] > 0
    assert figures["simulated_printers"] == 40 and figures["claims_per_second"] > 0
    assert "99th percentile" in done.stdout


VS_OCTOPRINT = Path(__file__).parent.parent / "bench" / "vs_octoprint.py"
# OctoPrint is not among the test extra's packages: its own virtualenv, when there is one.
OCTOPRINT_PYTHON = Path(os.environ.get("OCTOPRINT_PYTHON", "/tmp/octo-venv/bin/python"))


@pytest.mark.timeout(300)
@pytest.mark.skipif(not OCTOPRINT_PYTHON.exists(), reason="no OctoPrint virtualenv")
@pytest.mark.slow
def test_the_octoprint_bench_runs_every_host_exactly_once(tmp_path: Path) -> None:
    options = ["--runs", "1", "--lines", "300", "--keep", str(tmp_path)]
    result = subprocess.run(
        [sys.executable, str(VS_OCTOPRINT), "--octoprint-python", str(OCTOPRINT_PYTHON), *options],
        capture_output=True,
        text=True,
        timeout=280,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    for host in ("octoprint", "unbuffered", "buffered"):
        assert f"round 1 {host}: " in result.stdout
    assert result.stdout.count("exactly once") == 3


LOOP_DELAY = Path(__file__).parent.parent / "bench" / "loop_delay.py"


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_loop_delay_bench_reports_each_step_and_every_line_once() -> None:
    result = subprocess.run(
        [sys.executable, str(LOOP_DELAY), "--size-mb", "5"],
        capture_output=True,
        text=True,
        timeout=110,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    steps = [line.split(":")[0].strip() for line in result.stdout.splitlines()[:4]]
    assert steps == ["upload long.gcode", "check long.gcode", "upload big.gcode", "check big.gcode"]
    assert "answers meanwhile: " in result.stdout
    assert "every line sent once, in order: True" in result.stdout


ESTIMATE = Path(__file__).parent.parent / "bench" / "estimate.py"


@pytest.mark.timeout(120)
def test_estimate_bench_prints_each_files_figures_beside_the_slicers() -> None:
    result = subprocess.run(
        [sys.executable, str(ESTIMATE)], capture_output=True, text=True, timeout=110
    )
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| cone")]
    assert len(rows) == 1 and ("(-" in rows[0] or "(+" in rows[0])
    assert "sphere-prusaslicer.gcode | 3,175 |" in result.stdout  # PrusaSlicer's 52m 55s


TIME_LEFT = Path(__file__).parent.parent / "bench" / "time_left.py"


@pytest.mark.timeout(200)
@pytest.mark.slow
def test_time_left_bench_reports_each_point_of_a_job_and_each_printers_pace() -> None:
    """The time left against the fake whose moves and heat-up take their planned time (the
    cone's first two layers and its heat-up, at x16), on both links: a row for a printer's
    first job and its next, a figure at each point, the next job started from the pace its
    first measured (its history's record). The bench's own figures come within a few %; the
    bounds here are looser, since a loaded machine's fake strays from its plan, but plumbing
    gone wrong (the heat-up not counted, a lost pace, a wrong line) is off by 20 % or more."""
    _, header, table = quick_table(TIME_LEFT, 190)
    points = ["1 s", "5%", "10%", "25%", "50%", "75%", "90%"]
    assert header == [
        "link", "job", "pace it starts from", *points,
        "largest rise s", "largest gap s", "None", "pace measured",
    ]  # fmt: skip
    rows = {(row[0], row[1]): dict(zip(header, row, strict=True)) for row in table}
    links = ("reprap", "hyrel")
    assert list(rows) == [
        (link, job) for link in links for job in ("first: never seen", "next: its history")
    ]
    first, following = rows["reprap", "first: never seen"], rows["reprap", "next: its history"]
    assert float(first["pace it starts from"]) == 1.0  # never seen: the plan's
    assert float(first["pace measured"]) == pytest.approx(1.1, rel=0.05)  # 10 % slower
    # Its next job starts from what its first measured, through the record beside its history.
    assert float(following["pace it starts from"]) == pytest.approx(
        float(first["pace measured"]), abs=0.002
    )
    # From a quarter of the job on, every point has a figure on both links.
    assert all(row[point] != "None" for row in rows.values() for point in points[3:])
    # The printer with history: its heat-up counted from the first second (without it, the
    # figure at 1 s is short by the heat-up's share, 40 %), and its remainder after.
    for point in ("1 s", "25%", "50%", "75%"):
        assert abs(float(following[point].rstrip("%"))) <= 15, (point, following)
