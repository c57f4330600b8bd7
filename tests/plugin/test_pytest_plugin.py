"""The pytest plugin, through pytest itself: each case runs pytest in a subprocess on a
small test file (pytester), as a lab's project would, with the plugin found through the
installed package's entry point."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import MARLIN_SAFE_STOP
from tests.support.paths import ROOT

ROOT = ROOT

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(autouse=True)
def no_printer_in_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("PORT", "MACHINE", "LOADOUT", "FLOW", "BAUD", "PROTOCOL"):
        monkeypatch.delenv(f"HYREL_{name}", raising=False)


def run(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    return pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "--timeout=60", *args, timeout=150
    )


def one_line(text: str) -> str:
    return " ".join(text.split())


@pytest.mark.slow
def test_help_lists_the_options_in_a_hyrel_group_with_their_defaults(
    pytester: pytest.Pytester,
) -> None:
    result = run(pytester, "--help")
    assert result.ret == 0
    text = result.stdout.str()
    group = one_line(text[text.index("Hyrel printers (repetrel-host):") :])
    for option in ("PORT", "MACHINE", "LOADOUT", "FLOW", "BAUD", "PROTOCOL"):
        assert f"--hyrel-{option.lower()}={option}" in group
        assert f"HYREL_{option}" in group
        assert f"hyrel_{option.lower()} (string)" in group  # the ini key
    assert "default: the built-in fake controller, fresh for each test" in group
    assert "default: the machine profile's (115200)" in group


@pytest.mark.slow
def test_options_come_from_the_command_line_then_the_environment_then_the_ini_file(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytester.makepyprojecttoml(
        """
        [tool.pytest.ini_options]
        hyrel_machine = "marlin"
        hyrel_flow = "buffered"
        hyrel_baud = "9600"
        """
    )
    pytester.makepyfile(
        """
        def test_options(hyrel_options):
            assert hyrel_options.port == "fake" and not hyrel_options.hardware
            assert hyrel_options.machine == "marlin"  # the ini file
            assert hyrel_options.flow == "unbuffered"  # the environment over the ini file
            assert hyrel_options.baud == 250000  # the command line over both
            assert hyrel_options.loadout is None
        """
    )
    monkeypatch.setenv("HYREL_FLOW", "unbuffered")
    monkeypatch.setenv("HYREL_BAUD", "57600")
    run(pytester, "--hyrel-baud", "250000").assert_outcomes(passed=1)

    for args, message in (
        (["--hyrel-flow", "sideways"], "--hyrel-flow: 'sideways' is not buffered or unbuffered"),
        (["--hyrel-machine", "nosuch"], "hyrel: unknown machine 'nosuch' (known: 30m, ehr,"),
        (["--hyrel-loadout", "nosuch"], "hyrel: "),
    ):
        result = run(pytester, *args)
        assert result.ret == pytest.ExitCode.USAGE_ERROR
        assert message in result.stderr.str()
        assert "Traceback" not in result.stderr.str() + result.stdout.str()
    monkeypatch.setenv("HYREL_FLOW", "fast")
    result = run(pytester)
    assert "HYREL_FLOW: 'fast' is not buffered or unbuffered" in result.stderr.str()
    assert run(pytester, "--help").ret == 0  # help whatever the options say


@pytest.mark.slow
def test_a_port_given_after_a_space_is_warned_about(pytester: pytest.Pytester) -> None:
    pytester.makepyfile("def test_nothing():\n    pass\n")
    result = run(pytester, "--hyrel-port", "/dev/null")
    result.assert_outcomes(passed=1, warnings=1)
    assert (
        "--hyrel-port /dev/null made pytest look for its configuration from /dev "
        "(rootdir /dev); write --hyrel-port=/dev/null" in one_line(result.stdout.str())
    )


@pytest.mark.slow
def test_markers_are_registered_and_skip_with_their_reasons(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.hyrel_hardware
        def test_on_the_bench():
            raise AssertionError("must not run on the fake")

        @pytest.mark.hyrel_fake_only
        def test_with_faults():
            pass

        @pytest.mark.hyrel_machine("30m")
        def test_for_a_30m(hyrel_printer):
            raise AssertionError("must not run on another machine")

        @pytest.mark.hyrel_machine("marlin", "hyrel")
        def test_for_marlin(hyrel_printer):
            assert hyrel_printer.firmware is not None

        @pytest.mark.hyrel_fake(heat_rate=5, faults="drop_ok=0.01")
        def test_with_fake_settings(hyrel_printer):
            assert hyrel_printer.command("M105").ok_line.startswith("ok")
        """
    )
    result = run(pytester, "--strict-markers", "-rs")
    result.assert_outcomes(passed=3, skipped=2)
    report = one_line(result.stdout.str())
    assert "needs a real printer: give --hyrel-port=PORT (or HYREL_PORT)" in report
    assert (
        "for machine 30m; this run's machine is marlin "
        "(from the firmware: repetrel-host fake controller (Marlin replies))" in report
    )
    markers = one_line(run(pytester, "--markers").stdout.str())
    for marker in ("hyrel_hardware:", "hyrel_fake_only:", "hyrel_machine(*names):", "hyrel_fake("):
        assert f"@pytest.mark.{marker}" in markers

    # --hyrel-machine decides without a printer; a mistyped name is an error, not a skip.
    run(pytester, "--hyrel-machine", "30m", "-k", "30m").assert_outcomes(failed=1)
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.hyrel_machine("hyrel30m")
        def test_typo(hyrel_printer):
            pass

        @pytest.mark.hyrel_fake(heat_rat=5)
        def test_bad_setting(hyrel_printer):
            pass

        @pytest.mark.hyrel_fake("heat_rate=5")
        def test_unnamed_setting(hyrel_printer):
            pass

        @pytest.mark.hyrel_fake(log="mine.log")
        def test_the_plugins_setting(hyrel_printer):
            pass

        @pytest.mark.hyrel_machine("30m")
        def test_machine_without_a_session():
            pass
        """
    )
    result = run(pytester)
    result.assert_outcomes(errors=5)
    report = one_line(result.stdout.str())
    assert "hyrel_machine('hyrel30m'): name known machine profiles (30m, ehr," in report
    assert "hyrel_fake(--heat-rat 5): " in report and "unrecognized arguments" in report
    assert "hyrel_fake: name each setting (as in hyrel_fake(heat_rate=20))" in report
    assert "hyrel_fake: log is the plugin's" in report
    assert "hyrel_machine: this test's machine is known from --hyrel-machine" in report


@pytest.mark.slow
def test_sync_fixtures_command_print_and_drive_the_fake(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import time
        import pytest
        import repetrel_host as rh

        def test_command(hyrel_printer):
            reply = hyrel_printer.command("M115")
            assert reply.lines[0].startswith("FIRMWARE_NAME:repetrel-host fake controller")
            assert hyrel_printer.firmware.name.startswith("repetrel-host fake controller")
            assert hyrel_printer.state is rh.State.READY

        def test_a_job_runs_exactly_once_under_faults(
            hyrel_printer, hyrel_controller, hyrel_job
        ):
            job = hyrel_job("G28\\n" + "".join(f"G1 X{i} F3000\\n" for i in range(300)))
            before = len(hyrel_controller.executed)
            hyrel_controller.set_faults("corrupt=0.05 drop_ok=0.05 seed=4")
            result = hyrel_printer.print(job)
            assert result.completed and result.summary.resends > 0
            assert result.acknowledged == result.commands
            assert result.commands[:2] == ["G28", "G1 X0 F3000"] and len(result.commands) == 301
            assert result.last_line == 301
            assert hyrel_controller.executed[before:] == result.commands
            counts = hyrel_controller.fault_counts
            assert counts["corrupted_lines"] > 0 and counts["dropped_oks"] > 0

        def test_text_and_paths_are_not_confused(hyrel_printer, hyrel_job, tmp_path):
            with pytest.raises(ValueError, match=r"for a file, hyrel_job\\(Path\\('part."):
                hyrel_job("part.gcode")
            with pytest.raises(ValueError, match=r"for G-code text, use hyrel_job\\(text\\)"):
                hyrel_printer.print("G28\\nG1 X1\\n")
            part = tmp_path / "part.gcode"
            part.write_text("G1 X7\\n")
            assert hyrel_printer.print(part).acknowledged == ["G1 X7"]
            assert hyrel_printer.print(hyrel_job(part)).acknowledged == ["G1 X7"]

        @pytest.mark.hyrel_fake(heat_rate=100)
        def test_heating_takes_time(hyrel_printer, hyrel_controller):
            hyrel_printer.command("M104 S80")
            assert hyrel_controller.temperatures["T"][0] < 60
            assert abs(hyrel_printer.wait_for_temperature("T", 80, timeout=10) - 80) <= 2
            with pytest.raises(AssertionError, match="T did not reach 300 .* in 0.5 s"):
                hyrel_printer.wait_for_temperature("T", 300, timeout=0.5)

        @pytest.mark.hyrel_fake(faults="counted_resend=1")
        def test_an_interop_switch_from_the_start(hyrel_printer, hyrel_job):
            result = hyrel_printer.print(hyrel_job("G1 X1\\nG1 X2\\n"))
            assert result.completed
            assert hyrel_printer.session.probe is rh.ProbeKind.COMMAND

        def test_unplug_and_reconnect(hyrel_printer, hyrel_controller):
            events = hyrel_printer.events(timeout=10)
            states = [next(events).state]  # subscribed (the current state first), then unplug
            hyrel_controller.unplug(0.5)
            for event in events:
                if isinstance(event, rh.StateChanged):
                    states.append(event.state)
                    if event.state is rh.State.READY and len(states) > 1:
                        break
            assert states[:2] == [rh.State.READY, rh.State.DISCONNECTED]
            assert states[-1] is rh.State.READY
            assert hyrel_printer.command("M105").ok_line.startswith("ok T:")

        @pytest.mark.hyrel_fake(move_time=0.005)
        def test_a_failing_job_says_where_it_stopped(hyrel_printer, hyrel_job, hyrel_controller):
            running = hyrel_printer.start(hyrel_job("G1 X1\\n" * 200))
            while running.lines < 10:
                time.sleep(0.01)
            hyrel_controller.reset()
            result = running.wait(check=False)
            assert isinstance(result.error, rh.ControllerError)
            assert len(result.acknowledged) < 200
            assert f"job1.gcode:{result.last_line}" in str(result.error)
        """
    )
    run(pytester).assert_outcomes(passed=7)


@pytest.mark.slow
def test_async_fixture_from_pytest_asyncio_and_from_asyncio_run(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import asyncio
        import pytest
        import repetrel_host as rh

        @pytest.mark.asyncio
        async def test_with_pytest_asyncio(hyrel_aprinter, hyrel_job):
            reply = await hyrel_aprinter.command("M105")
            assert reply.ok_line.startswith("ok T:")
            result = await hyrel_aprinter.print(hyrel_job("G28\\nG1 X5\\n"))
            assert result.acknowledged == ["G28", "G1 X5"]
            running = await hyrel_aprinter.start(hyrel_job("G1 X1\\n" * 5000))
            cancelled = await running.cancel()
            assert not cancelled.completed and cancelled.error is None
            assert cancelled.safe_stop_missing == [] and len(cancelled.acknowledged) < 5000
            async for event in hyrel_aprinter.events():
                assert event == rh.StateChanged(rh.State.READY, None)
                break

        def test_on_a_loop_of_its_own(hyrel_aprinter):
            async def main():
                return await hyrel_aprinter.command("M115")
            assert asyncio.run(main()).lines[0].startswith("FIRMWARE_NAME:")
        """
    )
    run(pytester, "-W", "ignore::pytest.PytestDeprecationWarning").assert_outcomes(passed=2)


def ran_but_probes(where: Path) -> list[str]:
    """The fake's log (its path written at ``where``) without the host's probes: M105 lines
    that run, which none of these tests sends itself."""
    return [c for c in Path(where.read_text()).read_text().splitlines() if c != "M105"]


@pytest.mark.slow
def test_a_failing_test_reports_the_wire_and_leaves_the_fake_safe(
    pytester: pytest.Pytester,
) -> None:
    pytester.makepyfile(
        """
        import time
        from pathlib import Path
        import pytest

        @pytest.mark.hyrel_fake(move_time=0.01)
        def test_fails_mid_job(hyrel_printer, hyrel_controller, hyrel_job):
            Path("mid-job.log").write_text(str(hyrel_controller.log_path))
            running = hyrel_printer.start(hyrel_job("G28\\n" + "G1 X1\\nG1 X2\\n" * 250))
            while running.lines < 20:
                time.sleep(0.01)
            assert running.lines > 10_000, "the bench says no"

        def test_fails_with_a_heater_on(hyrel_printer, hyrel_controller):
            Path("heater.log").write_text(str(hyrel_controller.log_path))
            hyrel_printer.command("M104 S200")
            assert False, "the nozzle looks wrong"

        @pytest.mark.hyrel_fake(heat_rate=1)
        def test_fails_while_heating(hyrel_printer, hyrel_controller):
            Path("heating.log").write_text(str(hyrel_controller.log_path))
            hyrel_printer.command("M109 S250", timeout=0.5)  # 229 s to go

        @pytest.mark.xfail(strict=True)
        def test_known_to_fail(hyrel_printer, hyrel_controller):
            Path("xfail.log").write_text(str(hyrel_controller.log_path))
            hyrel_printer.command("M140 S90")
            assert False

        def test_fails_on_a_hung_controller(hyrel_printer, hyrel_controller):
            hyrel_controller.hang()
            assert False
        """
    )
    result = run(pytester)
    result.assert_outcomes(failed=4, xfailed=1, errors=1)
    out = result.stdout.str()
    assert "hyrel: last lines on the wire (> sent, < received)" in out
    # (The greeting: M110, its probe, M115, M155: the job's G28 is line 4.)
    assert "> N4 G28*" in out and "< ok" in out
    assert "hyrel: controller messages and session states" in out
    assert "state: printing (job1.gcode)" in out
    mid_job = ran_but_probes(pytester.path / "mid-job.log")
    assert mid_job[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    assert mid_job.count("G1 X1") < 250  # stopped, not streamed to the end
    heater = ran_but_probes(pytester.path / "heater.log")
    assert heater[-len(MARLIN_SAFE_STOP) - 1 :] == ["M104 S200", *MARLIN_SAFE_STOP]
    # M108 ends the heat wait the test left behind, so the safe stop does not wait for it.
    assert "TimeoutError: M109 S250: no reply within 0.5 s" in out
    heating = ran_but_probes(pytester.path / "heating.log")
    # (M108's own line then runs in its turn, as on Marlin, a no-op.)
    assert heating[-len(MARLIN_SAFE_STOP) - 2 :] == ["M109 S250", "M108", *MARLIN_SAFE_STOP]
    xfail = ran_but_probes(pytester.path / "xfail.log")
    assert xfail[-len(MARLIN_SAFE_STOP) - 1 :] == ["M140 S90", *MARLIN_SAFE_STOP]
    assert (
        "hyrel: after the test, the safe stop was not confirmed within 10 s (missing: M107, "
        "M104 S0, M140 S0, G91, G0 Z10, G90, M84); sent M112 (emergency stop): check the machine"
        in one_line(out)
    )


@pytest.mark.slow
def test_an_interrupted_run_stops_the_job_safely(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import time
        from pathlib import Path
        import pytest

        @pytest.mark.hyrel_fake(move_time=0.01)
        def test_interrupted(hyrel_printer, hyrel_controller, hyrel_job):
            Path("log.txt").write_text(str(hyrel_controller.log_path))
            running = hyrel_printer.start(hyrel_job("G1 X1\\nG1 X2\\n" * 250))
            while running.lines < 20:
                time.sleep(0.01)
            raise KeyboardInterrupt  # as Ctrl-C would
        """
    )
    result = run(pytester)
    assert result.ret == pytest.ExitCode.INTERRUPTED
    executed = ran_but_probes(pytester.path / "log.txt")
    assert executed[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    assert executed.count("G1 X1") < 250


@pytest.mark.slow
def test_a_pty_given_as_the_port_stands_for_the_bench(
    pytester: pytest.Pytester, tmp_path: Path
) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.hyrel_hardware
        def test_bench_only(hyrel_printer, hyrel_controller):
            assert not hyrel_controller.is_fake
            assert hyrel_printer.port == hyrel_controller.port
            hyrel_printer.command("M140 S50")

        @pytest.mark.hyrel_fake_only
        def test_fake_only(hyrel_printer):
            raise AssertionError("must not run on the bench")

        def test_the_fake_parts_skip(hyrel_printer, hyrel_controller, hyrel_job):
            assert hyrel_printer.print(hyrel_job("G1 X3\\n")).completed
            hyrel_controller.set_faults("drop_ok=0.5")

        def test_same_session(hyrel_printer):
            assert hyrel_printer.command("M105").ok_line.startswith("ok T:")
        """
    )
    log = tmp_path / "bench.log"
    with BuiltInFake(log) as bench:
        result = run(pytester, f"--hyrel-port={bench.port}", "-rs")
    result.assert_outcomes(passed=2, skipped=2)
    report = one_line(result.stdout.str())
    assert f"needs the fake controller's fault injection; this run drives {bench.port}" in report
    assert f"fault injection needs the fake controller; this run drives {bench.port}" in report
    executed = log.read_text().splitlines()
    assert sum(c.startswith("M110") for c in executed) == 1  # one session for the whole run
    assert executed[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP  # left safe at the end
    assert "M140 S50" in executed and "G1 X3" in executed


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_the_hil_examples_pass_on_the_fake(protocol: str) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "examples/hil",
            "-p",
            "no:cacheprovider",
            "-q",
            f"--hyrel-protocol={protocol}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert " passed" in result.stdout and "failed" not in result.stdout


@pytest.mark.slow
def test_each_test_gets_a_fresh_fake(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        ports = []

        def test_one(hyrel_controller):
            ports.append(hyrel_controller.port)
            hyrel_controller.set_faults("drop_ok=1")

        def test_two(hyrel_controller, hyrel_printer):
            assert hyrel_controller.port not in ports  # a new fake: no faults carried over
            assert hyrel_printer.command("M105").ok_line.startswith("ok")
        """
    )
    run(pytester).assert_outcomes(passed=2)


def test_the_wire_recorder_joins_lines_split_across_reads_and_caps_noise() -> None:
    from repetrel_host.pytest_plugin.report import WIRE_LINE_MAX, WireRecorder

    recorder = WireRecorder()
    recorder.tap(True, b"N1 G28*18\nN2 G1")
    recorder.tap(False, b"o")
    mark = recorder.mark()
    recorder.tap(True, b" X1*99\n")
    recorder.tap(False, b"k\r\n" + b"\xff" * (WIRE_LINE_MAX + 1))
    lines = [text.split(maxsplit=1)[1] for _, text in recorder.wire]  # without the time
    assert lines[:3] == ["> N1 G28*18", "> N2 G1 X1*99", "< ok"]
    assert lines[3] == "< " + "\\xff" * (WIRE_LINE_MAX + 1)  # shown, not held back
    assert len(recorder.since(recorder.wire, mark)) == 3  # what came after the mark


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
@pytest.mark.slow
def test_executed_holds_what_the_test_sent_on_either_link(
    pytester: pytest.Pytester, protocol: str
) -> None:
    # Written the obvious way: the host's own lines (the greeting's M110 and M115, polls,
    # the syncs of Hyrel's link) are not in executed; the test's own M115 and M105 are.
    pytester.makepyfile(
        f"""
        def test_what_ran_is_what_the_test_sent(hyrel_printer, hyrel_controller, hyrel_job):
            assert hyrel_printer.command("M115").ok
            lines = "".join(f"G1 X{{i}} F3000\\nM115\\n" for i in range(150))
            job = hyrel_job("M105\\n" + lines)
            result = hyrel_printer.print(job)
            hyrel_printer.command("M105")
            assert result.completed and len(result.commands) == 301
            assert hyrel_controller.executed == ["M115", *result.commands, "M105"]
            everything = hyrel_controller.all_executed
            assert everything.count("M115") > 151  # the greeting's M115 too
            assert everything[0].startswith("M110" if {protocol!r} == "reprap" else "M115")
        """
    )
    run(pytester, f"--hyrel-protocol={protocol}").assert_outcomes(passed=1)


@pytest.mark.slow
def test_hyrel_protocol_runs_the_same_tests_over_hyrels_link(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        def test_the_controller_says_it_is_a_hyrel(hyrel_printer):
            assert hyrel_printer.command("M115").lines[0].startswith("FIRMWARE_NAME:>Hy:")
            assert hyrel_printer.session.settings.protocol == "hyrel"

        def test_a_job_runs_exactly_once_with_acks_lost(
            hyrel_printer, hyrel_controller, hyrel_job
        ):
            job = hyrel_job("G28\\n" + "".join(f"G1 X{i} F3000\\n" for i in range(600)))
            before = len(hyrel_controller.executed)
            hyrel_controller.set_faults("drop_ok=0.1 garble=0.02 seed=3")
            result = hyrel_printer.print(job)
            assert result.completed and result.acknowledged == result.commands
            ran = hyrel_controller.executed[before:]  # without the host's syncs
            assert ran == result.commands and hyrel_controller.fault_counts["dropped_oks"] > 10

        @pytest.mark.hyrel_fake(protocol="reprap")
        def test_the_fakes_protocol_is_the_sessions(hyrel_printer):
            pass
        """
    )
    result = run(pytester, "--hyrel-protocol=hyrel")
    result.assert_outcomes(passed=2, errors=1)
    assert "hyrel_fake: protocol is the plugin's: give --hyrel-protocol" in result.stdout.str()
    result = run(pytester, "--hyrel-protocol=marlin")
    assert result.ret != 0
    assert "--hyrel-protocol: 'marlin' is not reprap or hyrel" in result.stderr.str()


@pytest.mark.slow
def test_an_async_test_runs_without_pytest_asyncios_warning(pytester: pytest.Pytester) -> None:
    # A lab's first async test, with no pytest-asyncio settings of its own.
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.asyncio
        async def test_the_printer_answers(hyrel_aprinter):
            assert (await hyrel_aprinter.command("M105")).ok
        """
    )
    result = run(pytester, "-W", "error::pytest.PytestDeprecationWarning")
    result.assert_outcomes(passed=1)
    assert "asyncio_default_fixture_loop_scope=function" in result.stdout.str()
    # The lab's own setting wins.
    result = run(pytester, "-o", "asyncio_default_fixture_loop_scope=module")
    result.assert_outcomes(passed=1)
    assert "asyncio_default_fixture_loop_scope=module" in result.stdout.str()


@pytest.mark.slow
def test_without_pytest_timeout_a_printer_test_fails_in_one_sentence(
    pytester: pytest.Pytester,
) -> None:
    pytester.makepyfile(
        """
        def test_needs_the_printer(hyrel_printer):
            pass

        def test_without_it():
            pass
        """
    )
    result = pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "-p", "no:timeout", timeout=150
    )
    result.assert_outcomes(passed=1, errors=1)
    assert (
        "hyrel: the plugin needs pytest-timeout, so that a printer that stops answering fails "
        "its test instead of hanging the run: pip install -e '.[hil]' in repetrel-host's clone"
    ) in one_line(result.stdout.str())
