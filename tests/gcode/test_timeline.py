"""The planned time at a job's lines (sparse, bounded), the time left as a run goes, and
the time until a later line (a running job's, from the move its controller runs)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.gcode.estimate import HeatWait
from repetrel_host.gcode.heat_rates import HeatClimbs, kind_of, learned_heat_rates
from repetrel_host.gcode.timeline import (
    MOST_POINTS,
    RISE_SECONDS,
    Countdown,
    PlannedTime,
    TimeLeft,
    Timeline,
    learned_pace,
)
from tests.support.helpers import job_file, run


def even(lines: int, each: float, start: int = 1) -> Timeline:
    timeline = Timeline()
    for line in range(start, start + lines):
        timeline.add(line, line * each)
    timeline.finish()
    return timeline


def wait(line: int, starts: float, seconds: float, heating: float = 0.0) -> HeatWait:
    """A hotend's wait for 200 degrees at 2 a second, planned at ``starts``."""
    return HeatWait(line, "T0", 200.0, 2.0, starts, seconds, heating or seconds)


def test_a_long_plan_is_kept_in_a_bounded_number_of_points_and_read_between_them() -> None:
    timeline = even(1_000_000, 0.01)  # 10,000 s over a million lines
    assert len(timeline.lines) <= MOST_POINTS
    assert timeline.spacing > 1.0
    assert timeline.total == pytest.approx(10_000)
    for line in (1, 12_345, 500_000, 999_999, 1_000_000):
        assert timeline.at(line)[0] == pytest.approx(line * 0.01, abs=timeline.spacing)
    assert timeline.at(2_000_000) == (pytest.approx(10_000), 0.0)


def wait_after_ten_lines() -> Timeline:
    """Ten lines of 0.3 s, a 50 s heat wait at line 11, nine more lines of 0.3 s."""
    timeline = Timeline()
    for line in range(1, 11):
        timeline.add(line, line * 0.3)
    timeline.heated(wait(11, 3.0, 50.0))
    timeline.add(11, 3.0 + 50.0)
    for line in range(12, 21):
        timeline.add(line, 53.0 + (line - 11) * 0.3)
    timeline.finish()
    return timeline


def test_a_heat_wait_is_a_step_at_its_line_not_spread_over_the_lines_before() -> None:
    timeline = wait_after_ten_lines()
    assert timeline.at(10) == (pytest.approx(3.0), 0.0)
    assert timeline.at(11) == (pytest.approx(53.0), 50.0)
    assert timeline.total_heating == 50.0


def test_a_run_at_the_plans_pace_has_the_plans_remainder_left() -> None:
    timeline = even(1000, 1.0)
    following = TimeLeft(timeline)
    for line in range(1, 1001, 50):
        assert following.left(line, now=float(line)) == pytest.approx(1000 - line)


def test_a_slower_run_is_found_out_and_counts_fully_from_a_tenth_of_the_plan() -> None:
    timeline = even(1000, 1.0)
    following = TimeLeft(timeline, prior=1.0)
    left = 0.0
    for line in range(1, 301):
        left = following.left(line, now=line * 1.1)
    assert following.pace == pytest.approx(1.1)
    # Given as a count down the clock within 5 s of the estimate as the pace was found out.
    assert left == pytest.approx((1000 - 300) * 1.1, abs=RISE_SECONDS)
    following.shown = Countdown()  # the estimate itself
    assert following.left(300, now=300 * 1.1) == pytest.approx((1000 - 300) * 1.1)
    # Earlier, the prior still weighs: 50 s watched (from 30 s settling on), half each.
    early = TimeLeft(timeline, prior=1.0)
    for line in range(1, 82):
        early.left(line, now=line * 1.1)
    assert early.watched_planned == pytest.approx(50)
    assert early.pace == pytest.approx(0.5 * 1.0 + 0.5 * 1.1)
    assert early.measured is None  # a tenth of the plan not watched yet
    early.left(140, now=140 * 1.1)
    assert early.measured == pytest.approx(1.1)


def test_a_printers_prior_pace_is_the_estimate_before_the_run_says_anything() -> None:
    following = TimeLeft(even(1000, 1.0), prior=0.9)
    assert following.left(0, now=0.0) == pytest.approx(900)
    assert following.measured is None


def test_heat_waits_and_pauses_are_not_taken_for_slow_moving() -> None:
    timeline = Timeline()
    timeline.heated(wait(1, 0.0, 100.0))
    timeline.add(1, 100.0)  # a wait planned at 100 s, first thing
    for line in range(2, 1002):
        timeline.add(line, 100.0 + (line - 1))
    timeline.finish()
    following = TimeLeft(timeline)
    following.left(0, now=0.0)
    following.left(1, now=400.0)  # the heaters took 400 s, not 100: the plan's business
    for line in range(2, 300):
        following.left(line, now=400.0 + (line - 1))
    following.left(300, now=700.0, moving=False)  # paused for an hour...
    following.left(300, now=4300.0, moving=False)
    for line in range(301, 400):  # ...and on again at the plan's pace
        following.left(line, now=4300.0 + (line - 300))
    assert following.pace == pytest.approx(1.0, abs=0.01)
    assert following.left(400, now=4400.0) == pytest.approx(1100 - 499, abs=5)


def test_a_printers_pace_is_the_median_of_its_last_five_jobs() -> None:
    assert learned_pace([]) == 1.0
    assert learned_pace([1.1]) == 1.1
    assert learned_pace([1.1, 1.3, 5.0, 1.2, 0.9, 9.9]) == 1.2  # one odd job, the sixth unread


def test_the_burst_that_fills_the_controllers_buffer_is_not_taken_for_speed() -> None:
    # 20 lines acknowledged at once (into the buffer), then one a second: the lead is 20 s.
    following = TimeLeft(even(1000, 1.0))
    following.left(0, now=0.0)
    following.left(20, now=0.1)
    for second in range(1, 200):
        following.left(20 + second, now=0.1 + second)
    assert following.pace == pytest.approx(1.0)


def heat_wait_midway() -> Timeline:
    """Lines 1-100 a second each; line 101 waits 50 s (100 to 200 degrees, as planned);
    lines 102-200 a second each."""
    timeline = Timeline()
    for line in range(1, 101):
        timeline.add(line, float(line))
    timeline.heated(wait(101, 100.0, 50.0))
    timeline.add(101, 150.0)
    for line in range(102, 201):
        timeline.add(line, 150.0 + line - 101)
    timeline.finish()
    return timeline


def test_the_wait_at_hand_counts_from_where_its_heater_reports() -> None:
    following = TimeLeft(heat_wait_midway())
    assert following.left(100, now=100.0) == pytest.approx(149)  # no reports: as planned
    hot = {"T0": (150.0, 200.0)}  # set, and halfway up at 2 degrees a second: 25 s to go
    assert following.left(100, now=101.0, heaters=hot) == pytest.approx(99 + 25)
    # The line waits while it climbs: the time left counts down, and the wait is no slow move.
    for second in range(1, 21):
        left = following.left(100, now=101.0 + second, heaters={"T0": (150 + 2 * second, 200)})
        assert left == pytest.approx(99 + 25 - second)
    assert following.pace == 1.0
    reached = {"T0": (199.5, 200.0)}
    assert following.left(100, now=125.0, heaters=reached) == pytest.approx(99)
    # A heater set elsewhere (or off) says nothing of this wait: the plan's 50 s stand.
    assert following.left(100, now=125.0, heaters={"T0": (150.0, 0.0)}) == pytest.approx(149)


def test_a_heater_set_early_heats_during_the_moves_before_its_wait() -> None:
    following = TimeLeft(heat_wait_midway())
    # 30 s of moves before the wait; 80 degrees to climb (40 s): 10 s are left to wait.
    left = following.left(70, now=70.0, heaters={"T0": (120.0, 200.0)})
    assert left == pytest.approx(30 + 10 + 99)


def test_a_controller_that_took_the_wait_and_the_lines_after_it_still_waits_for_its_heater() -> (
    None
):
    # Hyrel's link acknowledges lines as they enter its buffer: line 120 is taken, the
    # heater still climbs, so the moves from the wait on are all still to run.
    following = TimeLeft(heat_wait_midway(), held=30)
    left = following.left(120, now=100.0, heaters={"T0": (180.0, 200.0)})
    assert left == pytest.approx(10 + 99)
    assert following.left(120, now=110.0, heaters={"T0": (200.0, 200.0)}) == pytest.approx(99)


def test_the_time_until_a_line_is_the_plan_from_the_running_move_at_the_pace() -> None:
    following = TimeLeft(even(1000, 1.0), prior=1.1, held=10)
    left = following.left(100, now=0.0)
    # The controller runs the 90th move (10 held behind line 100's): 410 planned seconds
    # to the end of line 500, 1.1 times as long at this printer's pace.
    assert following.until(500, current=100) == pytest.approx(410 * 1.1)
    assert following.until(95, current=100) == pytest.approx(5 * 1.1)  # held, not run yet
    assert following.until(80, current=100) == 0.0  # run already
    assert following.until(2000, current=100) == pytest.approx(left)  # past the end: all of it


def test_a_heat_wait_before_a_line_counts_as_planned_not_at_the_pace() -> None:
    following = TimeLeft(wait_after_ten_lines(), prior=2.0)
    # From line 5 to the end of line 20: 4.2 s of moves at twice the plan, the 50 s wait.
    assert following.until(20, current=5) == pytest.approx(4.2 * 2 + 50)
    assert following.until(20, current=15) == pytest.approx(1.5 * 2)  # the wait is behind


@pytest.mark.timeout(60)
def test_a_running_jobs_time_until_a_line_once_it_is_planned(tmp_path: Path) -> None:
    path = job_file(tmp_path, [f"G1 X{i % 2 * 50} Y{i % 7} F6000" for i in range(1500)])
    settings = ControllerSettings(latency=0.0005, move_time=0.002)

    async def scenario() -> None:
        async with rh.connect("sim", sim=settings, poll_interval=None) as printer:
            job = await printer.print(path, header=False, history=False)
            assert job.time_until(1000) is None  # not planned yet
            await job.follow_time(after=0)
            while job.lines < 200:
                await asyncio.sleep(0.01)
            assert job.last is not None
            line = job.last.source_line
            left = job.time_left()
            assert left is not None and job.time_until(10**9) == pytest.approx(left)
            assert job.time_until(1) == 0.0
            sooner, later = job.time_until(line + 300), job.time_until(line + 600)
            assert sooner is not None and later is not None and 0 < sooner < later < left
            await job.wait()
            assert job.time_until(1500) is None  # it ended

    run(scenario)


def test_once_every_line_is_acknowledged_what_the_controller_holds_counts_down() -> None:
    # A controller that holds 100 moves: the last line is acknowledged with 100 s to run,
    # and no line moves after it. The time left counts down by the clock, and the wait for
    # the held moves is not taken for a slow run.
    following = TimeLeft(even(1000, 1.0), held=100)
    for line in range(1, 1001, 10):
        following.left(line, now=float(line))
    assert following.left(1000, now=1000.0) == pytest.approx(100)
    assert following.left(1000, now=1040.0) == pytest.approx(60)
    assert following.left(1000, now=1200.0) == 0.0
    assert following.pace == pytest.approx(1.0)


def test_acknowledgements_in_bursts_count_the_whole_stretch_they_end() -> None:
    # Hyrel's controller acknowledges lines as its buffer frees room: 25 at a time here,
    # while the run goes at the plan's pace. Asked four times a second, the time left sees
    # the same line between bursts, the first burst's ending in the first 30 s (settling):
    # no stretch counts the plan's 25 s against its last quarter of a second.
    following = TimeLeft(even(1000, 1.0))
    now = 0.0
    while now < 600:
        following.left(int(now // 25) * 25, now=now)
        now += 0.25
    assert following.pace == pytest.approx(1.0, abs=0.02)


def test_the_time_left_counts_down_through_noise_and_shows_a_real_rise() -> None:
    count = Countdown()
    assert count.show(100.0, 0.0) == 100.0
    # A little above the clock's count (99): drawn toward it by a tenth a second.
    assert count.show(100.0, 1.0) == pytest.approx(99.1)
    assert count.show(90.0, 2.0) == 90.0  # below it: as it is
    assert count.show(93.0, 2.5) == pytest.approx(89.5 + 0.05 * 3.5)  # 3.5 s over: drawn
    assert count.show(95.0, 3.0) == 95.0  # 6 s above the count: the run is behind, shown
    assert count.show(99.0, 9.0, moving=False) == 95.0  # paused: the count stands
    assert Countdown(1000.0, 0.0).show(1015.0, 0.0) == 1000.0  # under 2 % of it
    left = TimeLeft(even(100, 1.0))
    shown = [left.left(line, float(line)) for line in (10, 20, 30)]
    assert shown == sorted(shown, reverse=True)


def test_the_plan_split_adds_up_and_only_its_moving_part_takes_the_pace() -> None:
    planned = PlannedTime(moving=100.0, heating=60.0, tool_changes=10.0)
    assert planned.total() == 170.0
    assert planned.total(0.5) == pytest.approx(55.0 + 60.0)
    timeline = wait_after_ten_lines()
    timeline.tool_changes = 1.0
    assert timeline.planned == PlannedTime(pytest.approx(timeline.total - 51.0), 50.0, 1.0)
    assert timeline.planned.total(2.0) == pytest.approx(2 * (timeline.total - 50) + 50)


def test_on_a_link_that_acknowledges_on_arrival_a_wait_lasts_until_its_heater_says() -> None:
    """Hyrel's controller takes the wait and the lines after it at once: the wait is not
    over until its heater reports its target (the plan's time until a report tells)."""
    timeline = wait_after_ten_lines()
    left = TimeLeft(timeline, held=0, received_only=True)
    after_it = timeline.total - 54.2  # from line 15 (the last is counted down by the clock)
    unreported = left.left(15, 0.0)
    before_it = 54.2 - 53.0  # the moves between the wait and line 15, not yet run
    assert unreported == pytest.approx(50.0 + before_it + after_it, abs=0.01)  # as planned
    climbing = left.left(15, 1.0, heaters={"T0": (150.0, 200.0)})
    # 50 degrees at 2 a second
    assert climbing == pytest.approx(25.0 + before_it + after_it, abs=0.01)
    reached = left.left(15, 2.0, heaters={"T0": (200.0, 200.0)})
    assert reached < after_it + 0.01  # over: the moves after it are all that is left
    # Holding moves back to the wait's end (its buffer's), unreported: still the whole wait.
    held = TimeLeft(timeline, held=4, received_only=True).left(15, 0.0)
    assert held == pytest.approx(50.0 + before_it + after_it, abs=0.01)
    # On Marlin's link the same acknowledgements say the wait is over (M109's ok waits).
    assert TimeLeft(timeline, held=0).left(15, 0.0) <= after_it + 0.01


def test_on_a_link_that_acknowledges_in_bursts_the_time_left_counts_down_between_them() -> None:
    timeline = even(1000, 1.0)  # 1,000 s, a line a second
    left = TimeLeft(timeline, held=100, received_only=True)
    first = left.left(500, 0.0)  # the move that runs: 100 lines back, at 400 s
    assert first == pytest.approx(600.0)
    later = left.left(500, 30.0)  # no line taken since: the clock counts on
    assert later == pytest.approx(570.0)
    # Never past the line taken last (nothing after it has arrived).
    assert left.left(500, 500.0) == pytest.approx(500.0)


def test_a_heaters_climb_is_timed_from_its_reports_and_a_printers_rates_are_the_median() -> None:
    climbs = HeatClimbs()
    climbs.observe({"T0": (20.0, 200.0), "B": (20.0, 0.0)}, 0.0)
    climbs.observe({"T0": (110.0, 200.0), "B": (20.0, 60.0)}, 45.0)
    climbs.observe({"T0": (199.5, 200.0), "B": (40.0, 60.0)}, 90.0)
    climbs.observe({"T0": (200.0, 200.0), "B": (59.5, 60.0)}, 125.0)
    assert climbs.rates == {"hotend": pytest.approx(179.5 / 90), "bed": pytest.approx(39.5 / 80)}
    step = HeatClimbs()  # a later step of a few degrees does not replace the heat-up's rate
    step.observe({"T0": (20.0, 200.0)}, 0.0)
    step.observe({"T0": (200.0, 200.0)}, 90.0)
    step.observe({"T0": (200.0, 215.0)}, 100.0)
    step.observe({"T0": (215.0, 215.0)}, 101.0)
    assert step.rates == {"hotend": 2.0}
    changed = HeatClimbs()  # a target changed midway: timed from the report that showed it
    changed.observe({"T0": (20.0, 200.0)}, 0.0)
    changed.observe({"T0": (100.0, 150.0)}, 10.0)
    changed.observe({"T0": (150.0, 150.0)}, 20.0)
    assert changed.rates == {"hotend": 5.0}
    assert kind_of("T1") == "hotend" and kind_of("B") == "bed" and kind_of("C") == "chamber"
    jobs = [{"hotend": 2.0}, {"hotend": 3.0, "bed": 0.4}, None, {"hotend": 9.0}]
    assert learned_heat_rates(jobs) == {"hotend": 3.0, "bed": 0.4}


def test_on_a_link_that_acknowledges_on_arrival_the_bed_wait_comes_before_the_hotends() -> None:
    """M190 then M109, both taken at once: the bed's wait is the one at hand until the bed
    reports its target, though the hotend is there already."""
    timeline = Timeline()
    timeline.heated(HeatWait(1, "B", 60.0, 0.5, 0.0, 78.0, 78.0))  # 21 to 60 at 0.5 a second
    timeline.add(1, 78.0)
    timeline.heated(HeatWait(2, "T0", 200.0, 2.0, 78.0, 89.5, 167.5))
    timeline.add(2, 167.5)
    for line in range(3, 203):
        timeline.add(line, 167.5 + (line - 2) * 1.0)  # 200 s of moves
    timeline.finish()
    left = TimeLeft(timeline, held=0, received_only=True)
    heaters = {"B": (40.0, 60.0), "T0": (200.0, 200.0)}
    assert left.left(100, 0.0, heaters=heaters) == pytest.approx(40.0 + 200.0, abs=0.5)
    heaters = {"B": (60.0, 60.0), "T0": (200.0, 200.0)}  # both there: the moves after 100
    assert left.left(100, 1.0, heaters=heaters) == pytest.approx(200.0 - 98.0, abs=0.5)
