"""What explains a silence: the moves' planned time, dwells, heat waits, busy lines, and the
pace and margin learnt from the controller's own answers."""

import math

import pytest

from repetrel_host.gcode.estimate import Estimator
from repetrel_host.protocol.reports import residency_left
from repetrel_host.protocol.silence import (
    BUSY_GAPS,
    BUSY_INTERVAL,
    HEAT_SETTLE,
    MARGIN,
    MAX_MARGIN,
    MAX_PACE,
    REPORT_GAP,
    UNBUFFERED_GRACE,
    Silence,
)

LONG_MOVE = 100 / (600 / 60)  # 100 mm at F600: 10 s, give or take the accelerations


def send_and_ack(silence: Silence, commands: list[str], at: float, every: float = 0.0) -> float:
    for command in commands:
        silence.sent(command)
        silence.acknowledged(at)
        at += every
    return at - every


def long_moves(count: int) -> list[str]:
    return [f"G1 X{100 * ((i + 1) % 2)} F600" for i in range(count)]


def test_nothing_explains_a_silence_after_everything_was_answered() -> None:
    silence = Silence()
    send_and_ack(silence, ["G28", "M104 S200"], 0.0)
    assert silence.explained_until(1.0, 1.5) == 1.0


def test_a_planner_full_of_long_moves_explains_a_silence_of_a_move() -> None:
    silence = Silence()
    # Sixteen 10 s moves taken at once (the planner fills), the seventeenth waits for room:
    # its ok comes once the first move ends. Nothing has told the controller's pace yet:
    # it is taken as slow as it may be.
    send_and_ack(silence, long_moves(16), 0.0)
    silence.sent("G1 X0 F600")
    until = silence.explained_until(0.0, 0.5) / MARGIN / MAX_PACE
    assert LONG_MOVE <= until <= LONG_MOVE + 1


def test_a_command_that_waits_for_the_moves_is_explained_until_they_all_ran() -> None:
    silence = Silence()
    send_and_ack(silence, long_moves(4), 0.0)
    silence.sent("M400")
    drained = silence.explained_until(0.0, 0.5) / MARGIN / MAX_PACE
    assert 4 * LONG_MOVE <= drained <= 4 * (LONG_MOVE + 1)
    silence.acknowledged(40.0)
    silence.sent("G4 S5")  # a dwell: nothing left to run before it
    assert silence.explained_until(40.0, 40.5) == pytest.approx(40.0 + 5 * MARGIN)


def test_the_pace_of_a_controller_faster_than_the_plan_shortens_the_explanation() -> None:
    silence = Silence()
    # A fake that runs moves at once: 200 long moves answered a millisecond apart.
    at = send_and_ack(silence, long_moves(200), 0.0, every=0.001)
    silence.sent("G1 X0 F600")
    assert silence.explained_until(at, at + 0.01) - at < 0.01


def test_a_heat_wait_is_explained_while_its_reports_say_the_heater_is_getting_there() -> None:
    silence = Silence()
    silence.sent("M190 S60")
    now = 0.0
    for second in range(120):  # a slow bed: 120 s, reported every second
        now = float(second)
        silence.temperatures({"B": (21.0 + second / 4, 60.0), "T": (21.0, 0.0)}, now)
        assert silence.explained_until(0.0, now) >= now
    # Once it is there (and settled), its ok is due: the reports no longer explain.
    for second in range(120, 200):
        now = float(second)
        silence.temperatures({"B": (60.0, 60.0)}, now)
    assert silence.explained_until(0.0, now) < now
    # A hotend's heat-up does not explain a bed's wait: its bed there all along and no
    # residency said, the wait was over at once (its ok due within a report's gap).
    other = Silence()
    other.sent("M190 S60")
    other.temperatures({"T": (100.0, 200.0), "B": (60.0, 60.0)}, 100.0)
    assert other.explained_until(0.0, 100.0) == pytest.approx(REPORT_GAP)


def test_a_heat_wait_at_its_target_holds_what_its_residency_says_and_no_longer() -> None:
    assert residency_left(" T:200.00 /200.00 B:21.00 /0.00 @:0 B@:0 W:9") == 9.0
    assert residency_left(" T:150.00 /200.00 B:21.00 /0.00 @:0 B@:0 W:?") == math.inf
    assert residency_left(" T:200.00 /200.00 B:21.00 /0.00 @:0 B@:0") is None
    # Marlin reports at once: "W:9", nine seconds more.
    settling = Silence()
    settling.sent("M109 S200")
    settling.temperatures({"T": (200.0, 200.0)}, 1.0, residency=9.0)
    until = settling.explained_until(0.0, 2.0)
    assert until == pytest.approx(1.0 + 9.0 + REPORT_GAP)
    # "W:?": its heater is not there yet, the wait holds on while the reports come.
    heating = Silence()
    heating.sent("M109 S200")
    heating.temperatures({"T": (150.0, 200.0)}, 1.0, residency=math.inf)
    assert heating.explained_until(0.0, 2.0) >= HEAT_SETTLE
    # Its heater there already and no residency said (Marlin built without one): its one
    # report at once, then its ok; a lost ok is suspected a report's gap later, not after
    # the half minute a heat wait is given when nothing is heard.
    there = Silence()
    there.sent("M109 S200")
    there.temperatures({"T": (200.0, 200.0)}, 0.01)
    assert there.explained_until(0.0, 1.0) == pytest.approx(REPORT_GAP)


def test_a_heat_wait_whose_reports_stopped_is_explained_no_longer_than_its_settling() -> None:
    silence = Silence()
    silence.sent("M109 S200")
    silence.temperatures({"T": (100.0, 200.0)}, 1.0)
    until = silence.explained_until(0.0, 60.0)
    assert until == pytest.approx(max(HEAT_SETTLE, 1.0 + REPORT_GAP))


def test_busy_lines_explain_two_intervals_each() -> None:
    silence = Silence()
    silence.sent("G28")
    silence.busy(10.0)
    until = silence.explained_until(0.0, 11.0)
    assert until == pytest.approx(max(10.0 + BUSY_GAPS * BUSY_INTERVAL, UNBUFFERED_GRACE))
    silence.busy(15.0)  # every 5 s (M113 S5): two of them say so
    assert silence.explained_until(0.0, 16.0) == pytest.approx(15.0 + BUSY_GAPS * 5.0)


def test_a_needless_probe_widens_the_margin_and_a_needed_one_does_not() -> None:
    silence = Silence()
    send_and_ack(silence, long_moves(16), 0.0)
    silence.sent("G1 X0 F600")
    first = silence.explained_until(0.0, 0.5)
    silence.suspected(0.0, first)
    silence.acknowledged(2 * first, counted=False)  # the probe's answer confirmed it
    assert silence.margin == MARGIN
    since = 2 * first
    silence.sent("G1 X100 F600")
    until = silence.explained_until(since, since)
    assert until > since  # the moves still run
    silence.suspected(since, until)
    silence.acknowledged(since + 3 * (until - since), counted=True)  # its own ok, late
    assert MARGIN < silence.margin <= MAX_MARGIN


def test_a_homing_that_takes_long_teaches_no_margin() -> None:
    silence = Silence()
    silence.sent("G28")
    until = silence.explained_until(0.0, 0.1)
    silence.suspected(0.0, until)
    silence.acknowledged(60.0)  # a slow homing: nothing the plan said
    assert silence.margin == MARGIN


def test_the_estimate_runs_only_when_a_silence_needs_it_and_restarts_where_it_matters(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fed = []
    feed = Estimator.feed
    monkeypatch.setattr(Estimator, "feed", lambda self, *a: fed.append(a) or feed(self, *a))
    lines = ["M83", "M204 S500"] + [
        f"G1 X{(i * 37) % 200}.5 Y{(i * 11) % 150}.25 E0.125 F{1800 + (i % 7) * 600}"
        for i in range(5000)
    ]
    lazy, eager = Silence(), Silence()
    for index, line in enumerate(lines):
        for silence in (lazy, eager):
            silence.sent(line)
        if index % 100 == 0:  # silences all along: the estimate runs on every line
            eager.explained_until(index * 0.05, index * 0.05)
        for silence in (lazy, eager):
            silence.acknowledged(index * 0.05)
    assert fed and len(fed) < len(lines) + 10
    fed.clear()
    for silence in (lazy, eager):
        silence.sent("M400")
    end = (len(lines) - 1) * 0.05
    eagerly = eager.explained_until(end, end)
    assert len(fed) < 100  # only the lines since its last silence
    fed.clear()
    # A silence after 5,000 lines never planned: the last few hundred, planned from where
    # the lines before them left the axes (and with the file's modes and limits).
    lazily = lazy.explained_until(end, end)
    assert len(fed) <= 256 + 10
    assert lazily == pytest.approx(eagerly, rel=0.05) and lazily > end
