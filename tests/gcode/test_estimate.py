"""The print time from the moves (gcode/estimate): the planner's arithmetic on moves worked
out by hand, and the figure against PrusaSlicer's own on a real file."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from itertools import pairwise
from pathlib import Path

import pytest

from repetrel_host.gcode.estimate import (
    DEFAULT_LIMITS,
    Estimator,
    Limits,
    estimate,
    estimate_file,
)

DATA = Path(__file__).parent.parent / "data"

# One axis matters at a time below: X moves at up to 200 mm/s, accelerates at 1000 mm/s².
X_ONLY = Limits(
    max_feedrate={"X": 200.0, "Y": 200.0, "Z": 10.0, "E": 50.0},
    max_acceleration={"X": 5000.0, "Y": 5000.0, "Z": 100.0, "E": 5000.0},
    jerk={"X": 10.0, "Y": 10.0, "Z": 0.4, "E": 5.0},
    print_acceleration=1000.0,
    retract_acceleration=1000.0,
    travel_acceleration=1000.0,
    source="the test's",
)


def lines(*commands: str) -> list[tuple[int, str]]:
    return list(enumerate(commands, 1))


def test_one_move_is_a_trapezoid_from_the_jerk_speed_and_back() -> None:
    # 100 mm at 100 mm/s, 1000 mm/s²: it starts and ends at the jerk's 10 mm/s; up to 100 mm/s
    # over (100² - 10²) / 2000 = 4.95 mm in 0.09 s, the same down, 90.1 mm cruising.
    result = estimate(lines("G1 X100 F6000"), X_ONLY)
    assert result.seconds == pytest.approx(0.09 + 0.09 + 90.1 / 100, rel=1e-9)
    assert result.moves == 1


def test_a_short_move_never_reaches_its_feed_rate() -> None:
    # 2 mm: no room to reach 100 mm/s; up to sqrt(10² + 1000 * 2) = 45.8 mm/s halfway, down.
    top = math.sqrt(10**2 + 1000 * 2)
    result = estimate(lines("G1 X2 F6000"), X_ONLY)
    assert result.seconds == pytest.approx(2 * (top - 10) / 1000, rel=1e-9)


def test_moves_in_a_line_go_on_at_speed_and_a_reversal_stops() -> None:
    straight = estimate(lines("G1 X50 F6000", "G1 X100"), X_ONLY).seconds
    one = estimate(lines("G1 X100 F6000"), X_ONLY).seconds
    assert straight == pytest.approx(one, rel=1e-9)  # no slowing at the junction
    back = estimate(lines("G1 X100 F6000", "G1 X0"), X_ONLY).seconds
    assert back == pytest.approx(2 * one, rel=1e-9)  # down to the jerk's speed, and up again


def test_the_axes_limits_cap_the_feed_rate() -> None:
    # Z at F6000 asks 100 mm/s; Z's own limit is 10 mm/s, 100 mm/s², jerk 0.4 mm/s: up from
    # 0.4 to 10 mm/s in 0.096 s over 0.4992 mm, the same down, the rest at 10 mm/s.
    ramp = (10**2 - 0.4**2) / (2 * 100)
    result = estimate(lines("G1 Z10 F6000"), X_ONLY)
    assert result.seconds == pytest.approx(2 * (10 - 0.4) / 100 + (10 - 2 * ramp) / 10, rel=1e-9)


def test_dwells_feed_overrides_and_relative_moves_count() -> None:
    base = estimate(lines("G1 X100 F600"), X_ONLY).seconds  # 10 mm/s: all at the jerk speed
    assert base == pytest.approx(10.0, rel=1e-9)
    assert estimate(lines("G1 X100 F600", "G4 S3"), X_ONLY).seconds == pytest.approx(13.0)
    assert estimate(lines("G4 P500"), X_ONLY).seconds == pytest.approx(0.5)
    written_otherwise = estimate(lines("g01 x100 f600", "G1X200"), X_ONLY).seconds
    assert written_otherwise == pytest.approx(20.0, rel=1e-9)  # as the controller reads them
    assert estimate(lines("M220 S50", "G1 X100 F1200"), X_ONLY).seconds == pytest.approx(10.0)
    relative = estimate(lines("G91", "G1 X50 F600", "G1 X50"), X_ONLY).seconds
    assert relative == pytest.approx(10.0, rel=1e-9)
    assert estimate(lines("G92 X100", "G1 X100 F600"), X_ONLY).seconds == 0.0  # no move
    bare = estimate(lines("G1 X100 F600", "G92", "G1 X100"), X_ONLY).seconds  # X is 0 again
    assert bare == pytest.approx(20.0, rel=1e-9)
    inches = estimate(lines("G20", "G1 X1 F24"), X_ONLY).seconds  # 25.4 mm at 10.16 mm/s
    assert inches == pytest.approx(2.5, rel=1e-4)


def test_m400_ends_the_moves_so_the_next_starts_from_rest() -> None:
    # Two moves in a line join at speed; with M400 between, each ramps up and down alone.
    joined = estimate(lines("G1 X50 F6000", "G1 X100"), X_ONLY).seconds
    apart = estimate(lines("G1 X50 F6000", "M400", "G1 X100"), X_ONLY).seconds
    alone = estimate(lines("G1 X50 F6000"), X_ONLY).seconds
    assert apart == pytest.approx(2 * alone, rel=1e-9)
    assert apart > joined


def test_the_files_own_m201_to_m205_lines_set_the_limits() -> None:
    slow = estimate(lines("M203 X1", "G1 X10 F6000"), X_ONLY)
    assert slow.seconds == pytest.approx(10.0, rel=1e-9)  # 1 mm/s, below the jerk: no ramp
    assert slow.limits_from == "the file's M201-M205 lines"
    gentle = estimate(lines("M204 P100 T100", "G1 X100 F6000"), X_ONLY).seconds
    assert gentle > estimate(lines("G1 X100 F6000"), X_ONLY).seconds


def test_the_time_at_each_line_grows_to_the_total() -> None:
    told: list[tuple[int, float]] = []
    estimator = Estimator(X_ONLY, on_time=lambda line, seconds: told.append((line, seconds)))
    moves = [f"G1 X{(i % 2) * 50} Y{i} F3000" for i in range(1, 301)]
    for number, command in lines(*moves, "G4 S1"):
        estimator.feed(number, command)
    total = estimator.finish().seconds
    assert [line for line, _ in told] == list(range(1, 302))
    assert all(a[1] < b[1] for a, b in pairwise(told))
    assert told[-1][1] == pytest.approx(total)


def test_a_real_file_is_within_half_a_percent_of_its_slicers_figure(tmp_path: Path) -> None:
    # PrusaSlicer 2.5 wrote "12m 33s" (its normal mode) and its machine limits at the end.
    text = (DATA / "cone-prusaslicer.gcode").read_text(encoding="utf-8")
    assert "; estimated printing time (normal mode) = 12m 33s" in text
    stripped = tmp_path / "cone.gcode"
    stripped.write_text(
        "\n".join(
            ln
            for ln in text.splitlines()
            if not ln.startswith("M73") and "estimated printing time" not in ln
        ),
        encoding="utf-8",
    )
    result = estimate_file(stripped)
    assert result.limits_from == "the file's slicer settings"
    assert result.moving == pytest.approx(12 * 60 + 33, rel=0.005)
    # Its M104 S200, a home, then M109 S200: from 25 degrees at the default 2 degrees a
    # second, less what the heater gained during the moves between; counted apart.
    assert 80 < result.heating <= (200 - 25) / 2.0


def test_a_file_with_no_limits_anywhere_gets_more_than_distance_over_feed(
    tmp_path: Path,
) -> None:
    text = (DATA / "cone-prusaslicer.gcode").read_text(encoding="utf-8")
    bare = [ln for ln in text.splitlines() if not re.match(r"; machine_max_", ln)][:3000]
    path = tmp_path / "bare.gcode"
    path.write_text("\n".join(bare), encoding="utf-8")
    result = estimate_file(path)
    assert result.limits_from == DEFAULT_LIMITS.source
    x = y = z = 0.0
    feed = 1500.0
    plain = 0.0
    for ln in bare:
        command = ln.split(";", 1)[0].split()
        if command and command[0] in ("G0", "G1"):
            words = {w[0]: float(w[1:]) for w in command[1:]}
            feed = words.get("F", feed)
            new = (words.get("X", x), words.get("Y", y), words.get("Z", z))
            plain += math.dist((x, y, z), new) / (feed / 60)
            x, y, z = new
    assert plain > 0 and result.seconds > plain


def test_odd_lines_of_a_file_cost_no_crash() -> None:
    # A zero acceleration or feed rate (M204 P0, F0) is no limit; a G1 with no move is nothing.
    result = estimate(lines("M204 P0 T0 R0", "M201 X0", "G1 X10 F600", "G1 X20 F0", "G1"), X_ONLY)
    assert result.seconds == pytest.approx(1.0, rel=1e-2)  # the F0 move: no time (PrusaSlicer)
    assert result.moves == 2


def trapezoid(distance: float, acceleration: float, start: float, top: float, end: float) -> float:
    """The seconds of a move that reaches ``top`` (it must) from ``start``, down to ``end``."""
    up = (top * top - start * start) / (2 * acceleration)
    down = (top * top - end * end) / (2 * acceleration)
    return (top - start) / acceleration + (top - end) / acceleration + (distance - up - down) / top


def test_an_arc_runs_as_marlins_straight_pieces_whichever_way_it_is_written() -> None:
    # A quarter circle of radius 50 at 10 mm/s: no axis goes faster than its 10 mm/s jerk,
    # so the pieces run at full speed throughout: the arc's length over the speed.
    centre = estimate(lines("G1 X50 Y0 F600", "G3 X0 Y50 I-50 J0"), X_ONLY)
    radius = estimate(lines("G1 X50 Y0 F600", "G3 X0 Y50 R50"), X_ONLY)
    first = 50 / 10
    assert centre.seconds == pytest.approx(first + math.pi / 2 * 50 / 10, rel=1e-3)
    assert radius.seconds == pytest.approx(centre.seconds, rel=1e-9)
    assert centre.moves == 1 + 78  # 78.5 mm in pieces of about a millimetre
    # Clockwise the other way round is three quarters of the circle.
    long_way = estimate(lines("G1 X50 Y0 F600", "G2 X0 Y50 I-50 J0"), X_ONLY)
    assert long_way.seconds == pytest.approx(first + 3 * math.pi / 2 * 50 / 10, rel=1e-3)


def test_junction_deviation_takes_a_corner_at_marlins_speed() -> None:
    limits = replace(X_ONLY, junction_deviation=0.05)
    result = estimate(lines("G1 X100 F6000", "G1 Y100"), limits)
    # 90 degrees: sqrt(a * J * sin(45°) / (1 - sin(45°))) = 10.99 mm/s at the corner; each
    # move starts or ends at Marlin's least speed, 0.05 mm/s.
    sin_half = math.sqrt(0.5)
    corner = math.sqrt(1000 * 0.05 * sin_half / (1 - sin_half))
    expected = trapezoid(100, 1000, 0.05, 100, corner) + trapezoid(100, 1000, corner, 100, 0.05)
    assert result.seconds == pytest.approx(expected, rel=1e-6)
    # M205 J in the file turns it on.
    assert estimate(lines("M205 J0.05", "G1 X100 F6000", "G1 Y100"), X_ONLY).seconds == (
        pytest.approx(expected, rel=1e-6)
    )


def test_heat_waits_count_from_where_each_heater_is() -> None:
    cold = Estimator(X_ONLY)
    for number, command in lines("M104 S200", "M109 S200", "M190 S60", "M109 S200"):
        cold.feed(number, command)
    result = cold.finish()
    assert result.heating == pytest.approx((200 - 25) / 2.0 + (60 - 25) / 0.5, rel=1e-9)
    assert result.seconds == pytest.approx(result.heating)
    hot = Estimator(X_ONLY, temperatures={"T0": 200.0, "B": 60.0})
    for number, command in lines("M109 S200", "M190 S60"):
        hot.feed(number, command)
    assert hot.finish().heating == 0.0
    # A heater set early heats during the moves: the wait is what is left.
    early = estimate(lines("M104 S45", "G1 X100 F600", "M109 S45"), X_ONLY)
    assert early.heating == pytest.approx(max(0.0, 10 - 100 / 10), abs=0.2)


def test_a_tool_change_takes_the_profiles_time_once_per_change() -> None:
    limits = replace(X_ONLY, tool_change=5.0)
    result = estimate(lines("T0", "T1", "T1", "T0"), limits)
    assert result.tool_changes == 2
    assert result.seconds == pytest.approx(10.0)


def test_hyrels_g0_runs_at_its_rapid_speed_and_its_f_is_for_that_move_only() -> None:
    def hyrel(*commands: str) -> float:
        estimator = Estimator(X_ONLY, hyrel=True)
        for number, command in lines(*commands):
            estimator.feed(number, command)
        return estimator.finish().seconds

    one = estimate(lines("G1 X100 F6000"), X_ONLY).seconds  # 100 mm at 100 mm/s
    assert hyrel("G1 F600", "M203 X6000", "G0 X100") == pytest.approx(one, rel=1e-9)
    # Without M203 a G0 goes at the axis's top speed (200 mm/s here), not at F.
    assert hyrel("G1 F600", "G0 X100") < one
    # G0 F600 goes at 10 mm/s once; the G1 after it at the F it had (6000).
    assert hyrel("G1 F6000", "G0 X10 F600", "G1 X110") == pytest.approx(1.0 + one, rel=1e-9)
    # M674 S5: a G1 that does not print, longer than 5 mm, is a G0.
    assert hyrel("M203 X6000", "G1 F600", "M674 S5", "G1 X100") == pytest.approx(one, rel=1e-9)
    # E holds nothing back: an E-only move takes no time; a prime dwells where printing starts.
    assert hyrel("G1 E10 F60") == 0.0
    # (as a G4 there, stopping the motion), not where it goes on printing.
    dwelt = hyrel("G1 F6000", "G1 X100", "G4 P250", "G1 X200 E1", "G1 X300 E2")
    primed = hyrel("M722 S10000 E100 P250 T0", "G1 F6000", "G1 X100", "G1 X200 E1", "G1 X300 E2")
    assert primed == pytest.approx(dwelt, rel=1e-9)


def test_numbers_no_machine_reaches_are_not_moves() -> None:
    huge = "9" * 400  # a float of it is infinite
    result = estimate(lines(f"G1 X{huge} F6000", "G1 Y5", f"G92 X{huge}", "G1 X5"), X_ONLY)
    assert math.isfinite(result.seconds) and result.moves == 2
