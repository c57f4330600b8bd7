"""The print time as hyrel-send says it: ``--check``'s figure at the printer's pace from its
print history, split as planned; the summary's planned figure beside the real duration; and
one way to write a duration and a clock time."""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from repetrel_host.cli.times import clock_at, clock_time, duration
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session import history
from tests.support.helpers import CONE, hyrel_send

pytestmark = pytest.mark.timeout(90)

# A duration in the one format: 4.2s, 42s, 13m 05s, 1h 02m 03s.
DURATION = r"(?:\d+h \d\dm \d\ds|\d+m \d\ds|\d+s|\d\.\ds)"


def seconds_of(text: str) -> float:
    """A duration in the one format read back (its inverse, for the tests' sums)."""
    units = {"h": 3600, "m": 60, "s": 1}
    return sum(float(n) * units[u] for n, u in re.findall(r"([\d.]+)([hms])", text))


def past_job(folder: Path, port: str, machine: str, pace: float, minutes_ago: int = 60) -> None:
    """A finished run's stream and record in the history ``folder``, as a run leaves them."""
    started = datetime.now() - timedelta(minutes=minutes_ago)
    stream = folder / f"{started:%Y%m%d-%H%M%S}-part.gcode"
    folder.mkdir(parents=True, exist_ok=True)
    stream.write_text("G28\n")
    record = history.Record(
        job="part.gcode",
        outcome=history.COMPLETED,
        lines=1,
        seconds=600.0,
        where="the last line the controller acknowledged: part.gcode:1",
        port=port,
        started=started.isoformat(timespec="seconds"),
        ended=(started + timedelta(minutes=10)).isoformat(timespec="seconds"),
        machine=machine,
        pace=pace,
    )
    history.write_record(stream, record)


def test_duration_and_clock_time_have_one_format_each() -> None:
    assert [duration(s) for s in (0.04, 4.24, 9.96, 42, 785, 3723, 36000)] == [
        "0.0s",
        "4.2s",
        "10s",
        "42s",
        "13m 05s",
        "1h 02m 03s",
        "10h 00m 00s",
    ]
    now = datetime.now().replace(hour=20, minute=5)
    assert clock_time(now) == "20:05"
    assert clock_time(now - timedelta(days=1)) == f"{now - timedelta(days=1):%Y-%m-%d} 20:05"
    # A server's time (ISO 8601 in UTC, or seconds since the epoch) in the local clock.
    utc = now.astimezone(UTC).isoformat()
    assert clock_at(utc) == "20:05" and clock_at(now.timestamp()) == "20:05"
    assert clock_at(None) is None


@pytest.mark.slow
def test_check_gives_the_plan_split_and_the_printers_pace_from_its_history(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "history"
    check = ("--check", "--history", str(folder))
    result = hyrel_send(str(CONE), *check)
    assert result.returncode == 0, result.stderr
    # No past job: the plan's own figure, and why.
    found = re.search(
        rf"cone-prusaslicer.gcode: estimated time ({DURATION}) as planned \(({DURATION}) "
        rf"moving, ({DURATION}) heating\): no past job on port fake with the marlin profile "
        r"tells its pace; limits from the file's slicer settings; the slicer's: 12m 33s\n",
        result.stdout,
    )
    assert found, result.stdout
    whole, moving, heating = (seconds_of(found.group(i)) for i in (1, 2, 3))
    assert abs(whole - moving - heating) <= 1  # the split adds up
    assert 12 * 60 < moving < 13 * 60 and heating > 60  # the M109's wait, apart
    # The same port and profile's past jobs give the pace (their median): the whole at it.
    for minutes_ago, pace in ((30, 0.8), (60, 0.9), (90, 0.7)):
        past_job(folder, "fake", "marlin", pace, minutes_ago)
    past_job(folder, "/dev/ttyUSB0", "marlin", 2.0, 10)  # another printer's: not this one's
    past_job(folder, "fake", "hyrel", 2.0, 120)  # another profile's, before
    result = hyrel_send(str(CONE), *check)
    assert result.returncode == 0, result.stderr
    paced = re.search(
        rf"estimated time ({DURATION}) at this printer's pace \(0\.80 of the plan, from its "
        rf"past jobs\), {found.group(1)} as planned \({found.group(2)} moving, "
        rf"{found.group(3)} heating\); limits from",
        result.stdout,
    )
    assert paced, result.stdout
    assert abs(seconds_of(paced.group(1)) - (0.8 * moving + heating)) <= 1
    assert "machine profile marlin (the last job on this port)" in result.stdout
    # The port's last job ran as another profile (its firmware said so): planned as that.
    past_job(folder, "fake", "hyrel", 2.0, 5)
    result = hyrel_send(str(CONE), *check)
    assert "machine profile hyrel (the last job on this port)" in result.stdout
    assert "at this printer's pace (2.00 of the plan" in result.stdout
    # Another port named: its own history (none).
    result = hyrel_send(str(CONE), *check, "--port", "/dev/ttyUSB7")
    assert "as planned (" in result.stdout
    assert "no past job on port /dev/ttyUSB7 with the marlin profile" in result.stdout


@pytest.mark.slow
def test_the_summary_gives_the_planned_time_beside_the_real_one(tmp_path: Path) -> None:
    job = tmp_path / "part.gcode"
    moves = "".join(f"G1 X{10 if i % 2 == 0 else 0} F3000\n" for i in range(40))
    job.write_text(f"G28\n{moves}; estimated printing time (normal mode) = 7s\n")
    folder = tmp_path / "history"
    # Moves that take their planned time: the plan is made long before the job ends.
    with BuiltInFake(extra_args=["--time-scale", "1"]) as fake:
        past_job(folder, fake.port, "marlin", 0.5)
        options = ("--port", fake.port, "--history", str(folder))
        # --check's figure for that printer, before the run records its own pace.
        check = hyrel_send(str(job), "--check", "--machine", "marlin", *options)
        result = hyrel_send(str(job), *options)
    assert result.returncode == 0, result.stderr
    expected = re.search(rf"estimated time ({DURATION}) at this printer's pace", check.stdout)
    assert expected, check.stdout
    summary = re.search(
        rf"part.gcode: done: 41 lines in {DURATION} \(planned {expected.group(1)} at this "
        r"printer's pace; the slicer's 7\.0s\), \d+ lines/s, 0 resend requests",
        result.stdout,
    )
    assert summary, result.stdout
