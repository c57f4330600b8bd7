"""A stop leaves the machine safe, or says at once that it cannot (issue 21).

Each case runs hyrel-send (or a session) for real against the pty fake, and reads what the
fake executed and where its heaters stand, never the host's own account of it.
"""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session.job import Job
from tests.support.helpers import (
    DATA,
    HYREL_SAFE_STOP,
    MARLIN_SAFE_STOP,
    executed,
    hyrel_send,
    wait_for_log,
)
from tests.support.helpers import heater_targets as targets

pytestmark = pytest.mark.timeout(90)
HEAT = DATA / "heat.gcode"  # G28, M140 S60, M190 S60, M104 S200, M109 S200, moves
RESUME = "To resume from the first line not acknowledged: "


def start(job: Path, port: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", str(job), "--port", port, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )


def job_lines(job: Path) -> list[tuple[int, str]]:
    return [(line.source_line, line.command) for line in Job(job).lines()]


def resume_line(stdout: str) -> int:
    (line,) = [text for text in stdout.splitlines() if text.startswith(RESUME)]
    command = shlex.split(line[len(RESUME) :])
    return int(command[command.index("--from-line") + 1])


def assert_resume_runs_nothing_twice(job: Path, ran: list[str], stdout: str) -> None:
    """The job's lines the fake ran (``ran``) are exactly those before the resume point."""
    first = resume_line(stdout)
    before = [command for number, command in job_lines(job) if number < first]
    assert ran == before, (first, ran)


def test_a_stop_during_the_first_heat_up_breaks_the_wait_and_runs_the_safe_stop(
    tmp_path: Path,
) -> None:
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--heat-rate", "1"], control=True) as fake:
        sender = start(HEAT, fake.port, "--no-history")
        wait_for_log(log, "M140 S60")  # M190 S60 waits now: 39 s to go
        time.sleep(0.5)
        sender.send_signal(signal.SIGINT)
        stdout, stderr = sender.communicate(timeout=30)
        time.sleep(0.3)
        heaters = targets(fake)
        everything = executed(log)
    assert sender.returncode == 130, stdout + stderr
    assert "stopping: sending the safe-stop sequence" in stdout
    # M108 broke M190, then M109 in its turn (each M108's own line then runs, a no-op);
    # what the controller still held ran, its oks counted; then the safe stop.
    assert everything.count("M108") >= 2
    done = [c for c in everything if c != "M108"]
    assert done[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    assert heaters == {"T": 0.0, "B": 0.0}
    assert "M109 S200" in done
    assert_resume_runs_nothing_twice(HEAT, done[: -len(MARLIN_SAFE_STOP)], stdout)


def test_without_an_emergency_parser_the_held_stop_is_told_at_once(tmp_path: Path) -> None:
    log = tmp_path / "fake.log"
    args = ["--heat-rate", "1", "--no-emergency-parser"]
    with BuiltInFake(log, args, control=True) as fake:
        sender = start(HEAT, fake.port, "--no-history")
        wait_for_log(log, "M140 S60")
        time.sleep(0.5)
        sender.send_signal(signal.SIGINT)
        time.sleep(1.5)
        assert sender.poll() is None  # it waits for the safe stop, saying why
        sender.send_signal(signal.SIGINT)  # leave without it
        stdout, stderr = sender.communicate(timeout=30)
        heaters = targets(fake)
    assert sender.returncode == 5, stdout + stderr
    warning = " ".join(stdout.split())
    assert "the safe stop is held up: the controller is waiting for a heater (M190 S60" in warning
    assert "no emergency parser" in warning and "bed" in warning and "power switch" in warning
    said = stderr.split("\n", 1)
    assert said[0].startswith("connecting to ")  # said at once, then the last word
    last = " ".join(said[1].split())
    assert last.startswith("not safe: the safe stop was abandoned before the controller confirmed")
    assert "heaters that may be on: bed" in last and "hotend T0" in last
    assert heaters["B"] == 60.0  # truly on: the sentence was true


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_paused_then_unplugged_the_sender_reconnects_and_sends_the_safe_stop(
    tmp_path: Path, protocol: str
) -> None:
    from tests.support.terminal import Screen

    job = tmp_path / "hot.gcode"
    job.write_text(
        "M140 S60\nM104 S220\nG28\n" + "".join(f"G1 X{i % 50} F600\n" for i in range(400))
    )
    log = tmp_path / "fake.log"
    link = ["--protocol", protocol]
    with BuiltInFake(log, ["--move-time", "0.02", *link], control=True) as fake:
        screen = Screen(str(job), "--port", fake.port, "--no-history", *link, home=tmp_path)
        try:
            screen.expect("Keys: p pauses")
            wait_for_log(log, "G1 X5 F600")
            screen.send("p")
            screen.expect("Paused at hot.gcode:")
            assert targets(fake) == {"T": 220.0, "B": 60.0}
            assert fake.request("link_drop 3")["ok"]
            screen.expect("trying to reach the controller again to send it")
            screen.expect("sending the safe stop the interrupted job missed", timeout=20)
            status = screen.wait(timeout=30)
        finally:
            screen.child.close(force=True)
        text = " ".join(screen.text().split())
        heaters = targets(fake)
        done = executed(log)
    assert status == 3, text[-2000:]
    assert "link failure: the serial link was lost" in text
    assert "the safe stop went once the controller answered again" in text
    assert heaters == {"T": 0.0, "B": 0.0}
    # On Hyrel's link the controller held the paused job's lines: they were dropped (an
    # abort) before the safe stop, not left to run after it, nor to hold it up.
    stop = MARLIN_SAFE_STOP if protocol == "reprap" else HYREL_SAFE_STOP
    done = [c for c in done if c != "M115"]  # Hyrel's link: the host's syncs among them
    assert done[-len(stop) :] == stop, " | ".join(done[-40:])
    assert done.count("G1 X399 F600") == 0


@pytest.mark.slow
def test_a_safe_stop_cut_by_a_link_drop_is_finished_not_sent_again(tmp_path: Path) -> None:
    import json

    job = tmp_path / "job.gcode"
    job.write_text("M104 S200\n" + "".join(f"G1 X{i % 50} F600\n" for i in range(300)))
    log, history = tmp_path / "fake.log", tmp_path / "history"
    # Every command but a move takes half a second: the safe stop takes seconds.
    with BuiltInFake(log, ["--command-time", "0.5", "--move-time", "0.02"], control=True) as fake:
        sender = start(job, fake.port, "--history", str(history))
        wait_for_log(log, "G1 X20 F600")
        sender.send_signal(signal.SIGINT)
        wait_for_log(log, "G0 Z10")  # the lift ran; the rest of the safe stop is to come
        assert fake.request("link_drop 1")["ok"]
        stdout, stderr = sender.communicate(timeout=60)
        done = executed(log)
        heaters = targets(fake)
    assert sender.returncode == 130, stdout + stderr
    assert "the safe stop completed once the controller answered again" in stdout
    # Each line of the safe stop ran, the lift only once; after the reconnect only what
    # the controller had not confirmed went again.
    stop = done[done.index("M107") :]
    assert stop[: len(MARLIN_SAFE_STOP)] == MARLIN_SAFE_STOP, stop
    assert stop.count("G0 Z10") == 1 and stop.count("G91") == 1
    again = [c for c in stop[len(MARLIN_SAFE_STOP) :] if c not in ("M110 N0", "M115", "M155 S2")]
    # G90, M84: their oks were lost; M108 ends a heat wait that might hold them up.
    assert set(again) <= {*MARLIN_SAFE_STOP[-2:], "M108"}, stop
    assert heaters == {"T": 0.0, "B": 0.0}
    (record,) = history.glob("*.json")
    assert json.loads(record.read_text())["outcome"] == "cancelled"


def test_the_marlin_safe_stop_turns_off_every_hotend_the_job_heated(tmp_path: Path) -> None:
    job = tmp_path / "two.gcode"
    job.write_text(
        "M104 T0 S200\nM104 T1 S210\nM140 S60\nT1\n"
        + "".join(f"G1 X{i % 50} F600\n" for i in range(400))
    )
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--extruders", "2", "--move-time", "0.01"], control=True) as fake:
        sender = start(job, fake.port, "--no-history")
        wait_for_log(log, "G1 X20 F600")
        assert targets(fake) == {"T": 200.0, "T1": 210.0, "B": 60.0}
        sender.send_signal(signal.SIGINT)
        stdout, stderr = sender.communicate(timeout=30)
        heaters = targets(fake)
        done = executed(log)
    assert sender.returncode == 130, stdout + stderr
    assert heaters == {"T": 0.0, "T1": 0.0, "B": 0.0}  # T1 was active: T0 too is off
    assert done[-8:] == ["M107", "M104 T0 S0", "M104 T1 S0", "M140 S0", *MARLIN_SAFE_STOP[3:]]


@pytest.mark.slow
def test_a_marlin_board_slow_to_answer_m115_is_known_as_marlin(tmp_path: Path) -> None:
    with BuiltInFake(tmp_path / "fake.log", ["--command-time", "1.5"]) as fake:
        console = hyrel_send("--console", "--port", fake.port, input="M105\n", timeout=60)
    assert console.returncode == 0, console.stderr
    assert "machine profile marlin (from the firmware: repetrel-host fake" in console.stdout
    # The M115 answer is not taken for M105's reply.
    assert "FIRMWARE_NAME" not in console.stdout.split("machine profile", 1)[1]


def test_a_controller_that_never_says_who_it_is_gets_a_safe_stop_for_either_firmware(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import asyncio

    import repetrel_host as rh
    from repetrel_host.fakes.settings import ControllerSettings
    from repetrel_host.session import identify

    monkeypatch.setattr(identify, "FIRMWARE_PATIENCE", 0.2)
    settings = ControllerSettings(latency=0.25)  # M115's answer comes after 0.5 s

    async def scenario() -> None:
        async with rh.connect("sim", sim=settings, poll_interval=None) as printer:
            assert printer.firmware is None and printer.profile.fallback
            assert "for Hyrel's and Marlin's firmware alike" in printer.profile.describe()
            # Marlin refuses M104 T47 (no such hotend) but takes M104 S0, Hyrel the reverse.
            assert printer.safe_stop[:6] == [
                "M107 T47", "M620 T47 E0", "M104 T47 S0", "M104 S0", "M140 T46 S0", "M140 S0"
            ]  # fmt: skip
            await asyncio.sleep(1.0)  # its late answer still decides
            assert printer.firmware is not None and printer.profile.name == "marlin"
            assert printer.safe_stop[:3] == ["M107", "M104 S0", "M140 S0"]

    asyncio.run(scenario())


def test_a_pause_that_comes_as_the_job_ends_says_so(tmp_path: Path) -> None:
    import asyncio

    import repetrel_host as rh
    from repetrel_host.fakes.settings import ControllerSettings

    async def scenario(path: Path) -> None:
        settings = ControllerSettings(latency=0.01)
        async with rh.connect("sim", sim=settings, poll_interval=None) as printer:
            job = await printer.print(path, history=False)
            with pytest.raises(rh.UsageError, match="ended before the pause could hold it"):
                await printer.pause()
            assert (await job.wait()).outcome is rh.Outcome.COMPLETED

    path = tmp_path / "short.gcode"
    path.write_text("G1 X1\nG1 X2\nG1 X3\n")  # all of it in flight at once
    asyncio.run(scenario(path))


@pytest.mark.slow
def test_a_stop_held_up_too_long_offers_the_e_key_for_an_emergency_stop(tmp_path: Path) -> None:
    from tests.support.terminal import Screen

    job = tmp_path / "dwell.gcode"
    job.write_text("M104 S200\nG28\nG4 S120\nG1 X10\nG1 X20\n")  # M108 breaks no dwell
    log = tmp_path / "fake.log"
    with BuiltInFake(log, [], control=True) as fake:
        screen = Screen(str(job), "--port", fake.port, "--no-history", home=tmp_path)
        try:
            screen.expect("Keys: p pauses")
            wait_for_log(log, "G28")
            screen.send("e")  # a stray e while printing does nothing
            screen.send("\x03")
            screen.expect("stopping: sending the safe-stop sequence")
            screen.expect("the safe stop is not confirmed 10 s after the stop", timeout=20)
            screen.expect("G4 S120")
            screen.expect("press e for an emergency stop")
            assert "M112" not in executed(log)
            screen.send("e")
            screen.expect("emergency stop: M112 sent")
            status = screen.wait(timeout=30)
        finally:
            screen.child.close(force=True)
        heaters = targets(fake)
        hung = fake.request("status")["hung"]
    text = " ".join(screen.text().split())
    assert status == 4, text[-2000:]
    assert "stopped by an emergency stop (M112)" in text
    assert hung and heaters == {"T": 0.0, "B": 0.0}


@pytest.mark.slow
def test_after_a_lost_link_the_resume_hint_says_which_lines_may_have_run(tmp_path: Path) -> None:
    """Lines on their way when the link went lost their oks with it: some of them may have
    run. The hint names that window, and a command that repeats them and one that skips
    them: the last line the fake ran lies between the two."""
    job = tmp_path / "job.gcode"
    job.write_text("".join(f"G1 X{i % 50} Y{i} F600\n" for i in range(400)))
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--move-time", "0.02"], control=True) as fake:
        sender = start(job, fake.port, "--no-history")
        wait_for_log(log, "G1 X30 Y30 F600")
        assert fake.request("link_drop 2")["ok"]
        stdout, _ = sender.communicate(timeout=60)
        done = executed(log)
    repeat = resume_line(stdout)
    (window,) = [text for text in stdout.splitlines() if text.startswith("Lines ")]
    skip = int(shlex.split(window.split(": ")[-1])[-1])
    assert f"Lines {repeat} to {skip - 1} were sent and not confirmed" in window, stdout
    moves = [c for c in done if c.startswith("G1 ")]
    last_ran = int(moves[-1].split("Y")[1].split()[0]) + 1  # its line in the file
    assert repeat - 1 <= last_ran <= skip - 1, (repeat, last_ran, skip)
