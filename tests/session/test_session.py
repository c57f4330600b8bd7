"""The printer session, the same cases on the in-process simulator and on the pty fake,
over the RepRap link and over Hyrel's own (as python-can runs one test file on every
backend)."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

import repetrel_host as rh
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.gcode.heaters import off_lines
from repetrel_host.links import SimLink
from repetrel_host.pytest_plugin.facade import callers_commands
from repetrel_host.session import identify
from tests.support.helpers import (
    EXAMPLE,
    HYREL_SAFE_STOP,
    MARLIN_SAFE_STOP,
    job_commands,
    job_file,
    run,
)

pytestmark = pytest.mark.timeout(60)


@dataclass
class Rig:
    """How to reach one kind of controller, and what it executed."""

    kind: str
    tmp_path: Path
    protocol: str = "reprap"
    move_time: float = 0.0
    faults: str = ""
    # Each line the session sent, as it first went: (command, the host's own).
    sent: list[tuple[str, bool]] = field(default_factory=list)

    def connect(self, **options: Any) -> Any:
        options.setdefault("poll_interval", None)
        options["protocol"] = self.protocol
        options["line_tap"] = self.note
        if self.kind == "sim":
            settings = ControllerSettings(
                latency=0.0005,
                move_time=self.move_time,
                faults=Faults.parse(self.faults),
                rx_buffer=8192 if self.hyrel else 128,
                banner=not self.hyrel,
            )
            return rh.connect("sim", sim=settings, **options)
        args = ["--move-time", str(self.move_time)]
        if self.faults:
            args += ["--faults", self.faults]
        return rh.connect("fake", fake_log=self.log, fake_args=args, **options)

    def note(self, command: str, own: bool) -> None:
        """The session's line tap: what it sent, its own lines told apart."""
        self.sent.append((command, own))

    @property
    def hyrel(self) -> bool:
        return self.protocol == "hyrel"

    @property
    def safe_stop(self) -> list[str]:
        """The profile's that M115 chooses: a Hyrel controller's, or Marlin's."""
        return HYREL_SAFE_STOP if self.hyrel else MARLIN_SAFE_STOP

    @property
    def pause_sync(self) -> str:
        """What an M0 becomes: the controller's own M0 on Hyrel's link, else M400."""
        return "M0" if self.hyrel else "M400"

    @property
    def log(self) -> Path:
        return self.tmp_path / "executed.log"

    def everything_executed(self, printer: rh.Printer) -> list[str]:
        """What the controller executed, the session's own lines too."""
        if isinstance(printer.link, SimLink):
            simulator = printer.link.controller.simulator
            assert simulator is not None
            return list(simulator.executed)
        return self.log.read_text().splitlines() if self.log.exists() else []

    def executed(self, printer: rh.Printer) -> list[str]:
        """What the controller executed, without the session's own lines (its greeting, its
        probes and syncs, M115)."""
        return callers_commands(self.everything_executed(printer), self.sent)


@pytest.fixture(
    params=[("sim", "reprap"), ("fake", "reprap"), ("sim", "hyrel"), ("fake", "hyrel")],
    ids=["sim", "fake", "sim-hyrel", "fake-hyrel"],
)
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    kind, protocol = request.param
    return Rig(kind, tmp_path, protocol)


def temperatures(reply: rh.Reply) -> str:
    """The reply's temperature report: in its ok (Marlin), or its line (Hyrel's >ST:)."""
    return reply.lines[0] if reply.lines else reply.ok_line


async def settle(rig: Rig, printer: rh.Printer, count: int, timeout: float = 10.0) -> list[str]:
    """Wait until the controller executed ``count`` commands (the fake's log lags a little)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while len(done := rig.executed(printer)) < count:
        assert asyncio.get_running_loop().time() < deadline, done
        await asyncio.sleep(0.02)
    return done


# --- connecting and commands ---------------------------------------------------------


def test_connect_greets_and_asks_who_the_controller_is(rig: Rig) -> None:
    async def scenario() -> None:
        async with rig.connect() as printer:
            assert printer.state is rh.State.READY
            assert printer.firmware is not None
            reply = await printer.command("M115")
            assert reply.ok is True and reply.ok_line == "ok"
            if rig.hyrel:  # greeted with a ping, who said it is a Hyrel controller
                assert printer.probe is rh.ProbeKind.ANSWER
                assert printer.firmware.name == ">Hy: repetrel-host-fake_1.0"
                assert printer.profile.name == "hyrel"
                assert reply.lines == [
                    "FIRMWARE_NAME:>Hy: repetrel-host-fake_1.0 PROTOCOL_VERSION:1.0 "
                    "MACHINE_TYPE:HYREL_HYDRA HYREL_PROTOCOL:1"
                ]
            else:
                assert printer.probe is rh.ProbeKind.COMMAND
                assert printer.firmware.name.startswith("repetrel-host fake controller")
                assert printer.firmware.can("AUTOREPORT_TEMP")
                assert reply.lines[0].startswith("FIRMWARE_NAME:repetrel-host fake controller")
                assert reply.lines[1:] == ["Cap:AUTOREPORT_TEMP:1", "Cap:EMERGENCY_PARSER:1"]
            reply = await printer.command("M105")
            # (On Hyrel's link a status report the host asked for may come with it.) Marlin
            # reports hundredths, this fake of Hyrel's tenths.
            tenths = "T:21.0 /0.0 B:21.0 /0.0" if rig.hyrel else "T:21.00 /0.00 B:21.00 /0.00"
            assert f"{tenths} @:0 B@:0" in temperatures(reply)
            assert printer.temperatures["T"] == (21.0, 0.0)
            reply = await printer.command("M104 S200 ; a comment is fine")
            # On Hyrel's link the reply is complete once it ran: its notice is in it.
            assert reply.lines == ([">MC:M104: S200:"] if rig.hyrel else [])
            heated = "T:200.0 /200.0" if rig.hyrel else "T:200.00 /200.00"
            assert heated in temperatures(await printer.command("M105"))
        assert printer.state is rh.State.CLOSED

    run(scenario)


def test_host_owned_words_and_bad_commands_are_refused(rig: Rig) -> None:
    async def scenario() -> None:
        async with rig.connect() as printer:
            with pytest.raises(rh.UsageError, match="M110"):
                await printer.command("M110 N5")
            with pytest.raises(rh.UsageError, match="line numbers and checksums"):
                await printer.command("N5 M105 S0*9999")  # the probe
            with pytest.raises(rh.UsageError, match="line numbers and checksums"):
                await printer.command("n5 g1 x1")
            with pytest.raises(rh.UsageError, match="empty"):
                await printer.command("; only a comment")
            with pytest.raises(rh.JobError, match="not ASCII"):
                await printer.command("M117 café")
            assert "T:21.0" in temperatures(await printer.command("M105"))

    run(scenario)


def test_a_port_that_cannot_open_fails_connect_with_one_sentence(tmp_path: Path) -> None:
    async def scenario() -> None:
        with pytest.raises(rh.LinkError, match="no such port"):
            await rh.connect(str(tmp_path / "ttyUSB9"))
        with pytest.raises(rh.LinkError) as folder:
            await rh.connect(str(tmp_path))
        assert str(folder.value) == f"cannot open {tmp_path}: it is a folder, not a serial port"

    run(scenario)


def test_temperatures_come_as_events_while_idle(rig: Rig) -> None:
    async def scenario() -> None:
        async with rig.connect(poll_interval=0.2) as printer:
            await printer.command("M140 S60")
            async for event in printer.events():
                if isinstance(event, rh.Temperatures) and event.readings["B"] == (60.0, 60.0):
                    break
            # Marlin advertised auto-reports: the session asked for them (M155); the Hyrel
            # controller did not: it is asked with its status byte (0x05), not a line.
            executed = rig.everything_executed(printer)
            if rig.hyrel:
                assert "M105" not in executed
            else:
                assert "M155 S1" in executed

    run(scenario)


# --- jobs --------------------------------------------------------------------------


def test_two_jobs_on_one_connection_run_exactly_once(rig: Rig, tmp_path: Path) -> None:
    first = job_commands(EXAMPLE)
    second = [f"G1 X{i} Y{i % 7}" for i in range(200)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(EXAMPLE, history=tmp_path / "first.gcode")
            summary = await job.wait()
            assert summary.outcome is rh.Outcome.COMPLETED and summary.lines == len(first)
            assert printer.state is rh.State.READY
            job = await printer.print(job_file(tmp_path, second), history=tmp_path / "second.gcode")
            events = [event async for event in job.events()]
            assert isinstance(events[-1], rh.Done) and events[-1].summary.lines == len(second)
            assert isinstance(events[-2], rh.Progress) and events[-2].lines == len(second)
            assert rig.executed(printer) == first + second
            assert "T:" in temperatures(await printer.command("M105"))

    run(scenario)
    # No second greeting: the line numbers went on counting (after the RepRap link's last
    # probe, a numbered M105; after Hyrel's last M115, and what control bytes followed it:
    # a status request).
    first_wire = (tmp_path / "first.gcode").read_bytes()
    second_wire = (tmp_path / "second.gcode").read_bytes()
    lines = [line for line in first_wire.splitlines() if line.strip(b"\x01\x05\x0e")]
    last = lines[-1]
    number = int(last.split()[0][1:])
    assert second_wire.startswith(f"N{number + 1} G1 X0 Y0{'' if rig.hyrel else '*'}".encode())


def test_commands_wait_while_printing_and_work_while_paused(rig: Rig, tmp_path: Path) -> None:
    if rig.hyrel:
        pytest.skip("the controller holds a paused job on Hyrel's link: see the next test")
    rig.move_time = 0.003
    commands = [f"G1 X{i % 100} Y{i % 50}" for i in range(400)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            with pytest.raises(rh.UsageError, match="printing"):
                await printer.command("M105")
            await printer.pause()
            assert printer.state is rh.State.PAUSED
            paused_at = len(await settle(rig, printer, 1))
            await asyncio.sleep(0.5)
            # Nothing more ran: every line sent was executed, none was sent since.
            executed = rig.executed(printer)
            assert executed == commands[: len(executed)]
            assert len(executed) - paused_at <= 20  # the planner's and slots' lines finish
            await asyncio.sleep(0.3)
            assert len(rig.executed(printer)) == len(executed)
            reply = await printer.command("M105")  # e.g. to move a head during a pause
            assert reply.ok_line.startswith("ok T:")
            await printer.resume()
            assert printer.state is rh.State.PRINTING
            await job.wait()
            kinds = [type(e).__name__ async for e in job.events()]
            assert "Paused" in kinds and "Resumed" in kinds
        assert rig.executed(printer) == [
            *commands[: len(executed)],
            "M105",
            *commands[len(executed) :],
        ]

    run(scenario)


def test_a_jog_and_an_extrusion_while_paused_are_undone_before_the_job_goes_on(
    rig: Rig, tmp_path: Path
) -> None:
    """A person jogs, extrudes with M83 and changes the feed during a pause: before the
    job's next line, the head is back where the job stood, its E position, absolute
    extrusion and its feed rate are the file's again (else its next G1 E would be taken as
    relative, and its next move would go at the jog's speed)."""
    if rig.hyrel:
        pytest.skip("the controller holds a paused job on Hyrel's link: no command then")
    rig.move_time = 0.003
    commands = ["G90", "M82", "G92 E0", "G1 Z0.3 F600", "G1 F1800"]
    commands += [f"G1 X{10 + i % 80} Y{20 + i % 40} E{i * 0.05:.2f}" for i in range(1, 400)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await asyncio.sleep(0.3)
            await printer.pause()
            stood = job.last
            assert stood is not None
            for command in ("G91", "G1 Z10 F600", "G90", "M83", "G1 E5 F100", "M105"):
                await printer.command(command)
            await printer.resume()
            await job.wait()
        ran = rig.executed(printer)
        at = ran.index("G1 E5 F100") + 2  # after the person's M105
        line = commands[stood.source_line - 1]
        x, y, e = (float(w[1:]) for w in line.split()[1:])
        assert ran[at : at + 7] == [
            "G90",
            f"G0 X{x:g} Y{y:g} F3000",
            "G0 Z0.3 F600",
            f"G92 E{e:g}",
            "M82",
            "G1 F1800",
            commands[stood.source_line],  # the job's next line
        ]
        assert ran[at + 6 :] == commands[stood.source_line :]

    run(scenario)


@pytest.mark.parametrize("at_layer_end", [False, True])
@pytest.mark.slow
def test_a_pause_holds_the_job_in_the_controller_until_resume(
    rig: Rig, tmp_path: Path, at_layer_end: bool
) -> None:
    if not rig.hyrel:
        pytest.skip("the RepRap link has no way to hold what the controller holds")
    rig.move_time = 0.01
    commands = [f"G1 X{i % 100} Y{i % 50}" for i in range(1000)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await settle(rig, printer, 30)
            await printer.pause(at_layer_end=at_layer_end)  # 0x03, or 0x02
            assert printer.state is rh.State.PAUSED
            await asyncio.sleep(0.3)
            held = len(rig.executed(printer))
            await asyncio.sleep(0.5)
            # Held within a move (or two, with the round trip), with hundreds of lines
            # in the controller's buffer: none of them ran.
            assert len(rig.executed(printer)) == held < 80
            with pytest.raises(rh.UsageError, match="holds the paused job"):
                await printer.command("M105")
            await printer.resume()  # end-wait (0x01)
            assert (await job.wait()).outcome is rh.Outcome.COMPLETED
            kinds = [type(e).__name__ async for e in job.events()]
            assert "Paused" in kinds and "Resumed" in kinds
        assert rig.executed(printer) == commands

    run(scenario)


def test_cancel_runs_the_safe_stop_then_a_new_job_runs(rig: Rig, tmp_path: Path) -> None:
    rig.move_time = 0.003
    commands = [f"G1 X{i % 100} Y{i % 50}" for i in range(2000)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await settle(rig, printer, 50)
            await printer.cancel()
            summary = await job.wait()
            assert summary.outcome is rh.Outcome.CANCELLED
            assert printer.state is rh.State.READY
            executed = rig.executed(printer)
            safe_stop = rig.safe_stop
            sent = executed[: -len(safe_stop)]
            assert executed[-len(safe_stop) :] == safe_stop
            assert 50 <= len(sent) < len(commands) and sent == commands[: len(sent)]
            job = await printer.print(job_file(tmp_path, ["G28", "G1 X1"], "next.gcode"))
            assert (await job.wait()).outcome is rh.Outcome.COMPLETED
            assert rig.executed(printer)[-2:] == ["G28", "G1 X1"]

    run(scenario)


def test_cancel_aborts_what_the_controller_holds_and_the_safe_stop_runs_first(
    rig: Rig, tmp_path: Path
) -> None:
    if not rig.hyrel:
        pytest.skip("the RepRap link cannot take back what the controller holds")
    rig.move_time = 0.02
    commands = [f"G1 X{i % 100} Y{i % 50}" for i in range(2000)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            while job.lines < 400:  # received: hundreds of lines ahead of the machine
                await asyncio.sleep(0.02)
            ran = len(rig.executed(printer))
            await printer.cancel()  # abort (0x08), then the safe stop as urgent lines
            executed = rig.executed(printer)
            sent = executed[: -len(rig.safe_stop)]
            assert executed[-len(rig.safe_stop) :] == rig.safe_stop
            assert sent == commands[: len(sent)]
            # Within one reply: what ran after the cancel is what the planner held (16
            # moves) and what ran while the abort was on its way, not what the buffer held.
            assert len(sent) < ran + 40 and len(sent) < job.lines - 300

    run(scenario)


def test_leaving_the_session_during_a_job_stops_it_safely_first(rig: Rig, tmp_path: Path) -> None:
    rig.move_time = 0.003
    commands = [f"G1 X{i % 100}" for i in range(2000)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await settle(rig, printer, 20)
        assert (await job.wait()).outcome is rh.Outcome.CANCELLED
        executed = await settle(rig, printer, 0)
        assert executed[-len(rig.safe_stop) :] == rig.safe_stop

    run(scenario)


def test_m112_goes_out_at_once_and_ends_the_job(rig: Rig, tmp_path: Path) -> None:
    rig.move_time = 0.003
    commands = ["M104 S200"] + [f"G1 X{i % 100}" for i in range(2000)]

    async def scenario() -> None:
        async with rig.connect(reconnect=False) as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await settle(rig, printer, 20)
            reply = await printer.command("M112")  # allowed while printing
            assert reply == rh.Reply("M112", [], "") and reply.ok is False
            with pytest.raises(rh.ControllerError, match="emergency stop"):
                await job.wait()
            executed = await settle(rig, printer, 21)
            while "M112" not in executed:
                await asyncio.sleep(0.02)  # the fake's log lags behind
                executed = rig.executed(printer)
            # Within what was already in the controller's buffer, then no job line (on
            # Hyrel's link, the abort before it dropped what the buffer held): only the
            # safe stop's heater-off lines (a heater is on), where the controller still
            # answers (Hyrel's).
            stopped = executed.index("M112")
            assert executed[:stopped] == commands[:stopped]
            assert stopped < 200
            await asyncio.sleep(0.5)
            after = rig.executed(printer)[stopped + 1 :]
            offs = off_lines(printer.safe_stop)
            assert offs and after == ([] if rig.protocol == "reprap" else offs)

    run(scenario)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_m108_goes_out_at_once_and_ends_a_heat_wait(protocol: str) -> None:
    rig = Rig("sim", Path(), protocol)

    async def scenario() -> None:
        settings = ControllerSettings(heat_rate=1.0, rx_buffer=8192)  # 229 s to 250 degrees
        connecting = rh.connect(
            "sim", sim=settings, poll_interval=None, protocol=protocol, line_tap=rig.note
        )
        async with connecting as printer:
            heating = asyncio.create_task(printer.command("M109 S250"))
            await asyncio.sleep(0.2)
            assert not heating.done() and printer.pending == ["M109 S250"]
            # Marlin's emergency parser reads M108; on Hyrel's link it is end-wait (0x01).
            assert await printer.command("M108") == rh.Reply("M108", [], "")
            reply = await asyncio.wait_for(heating, 2)
            assert reply.ok_line == "ok" and printer.pending == []
            # Marlin's M108 line then runs in its turn (a no-op) and draws an ok, which
            # the link counts as the M108's: the next command gets its own reply.
            assert rig.executed(printer) == ["M109 S250", *(["M108"] if not rig.hyrel else [])]
            assert (await printer.command("M114")).ok_line == "ok"
            assert rig.executed(printer)[-1] == "M114"

    run(scenario)


# --- losing the link, resets -----------------------------------------------------------


def test_an_unplugged_controller_comes_back_ready(rig: Rig) -> None:
    async def scenario() -> None:
        async with rig.connect() as printer:
            states = printer.events()
            with pytest.raises(rh.LinkError, match="lost"):
                await printer.command("!!DEBUG:link_drop 0.5")
            seen = []
            async for event in states:
                if isinstance(event, rh.StateChanged):
                    seen.append(event.state)
                    if seen[-2:] == [rh.State.CONNECTING, rh.State.READY] and len(seen) > 2:
                        break
            assert rh.State.DISCONNECTED in seen
            assert printer.state is rh.State.READY
            assert "T:" in temperatures(await printer.command("M105"))

    run(scenario)


def test_a_job_fails_when_the_link_goes_and_is_never_resumed(rig: Rig, tmp_path: Path) -> None:
    # The dwell lets the ACKs of the lines before it come, and the lines after it are
    # more than a Hyrel controller holds.
    commands = [f"G1 X{i}" for i in range(30)] + ["G4 P100", "!!DEBUG:link_drop 0.5"]
    commands += [f"G1 Y{i}" for i in range(3000)]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            with pytest.raises(rh.LinkError, match="lost") as error:
                await job.wait()
            assert "the last line the controller acknowledged is job.gcode:" in str(error.value)
            await printer.wait_for(rh.State.READY, timeout=15)
            assert "T:" in temperatures(await printer.command("M105"))
            await asyncio.sleep(0.3)
            done = rig.executed(printer)
            # Once the link was back, the safe stop the job could not send went first.
            assert done[-1] == "M105"
            assert done[-1 - len(rig.safe_stop) : -1] == rig.safe_stop
            ran = done[: -1 - len(rig.safe_stop)]
            if not rig.hyrel:  # the owed stop's M108 first, should a heat wait hold it up
                assert ran[-1] == "M108"
                ran = ran[:-1]
            # What was on its way when the cable went, and nothing after the reconnect.
            assert ran == [c for c in commands if not c.startswith("!!")][: len(ran)]
            assert len(ran) < 1000  # the 8 KB a Hyrel controller holds, at most

    run(scenario)


def test_without_reconnect_a_lost_link_stays_lost(rig: Rig) -> None:
    async def scenario() -> None:
        async with rig.connect(reconnect=False) as printer:
            with pytest.raises(rh.LinkError):
                await printer.command("!!DEBUG:link_drop 0.2")
            await asyncio.sleep(0.6)
            assert printer.state is rh.State.DISCONNECTED
            with pytest.raises(rh.LinkError, match="not connected"):
                await printer.command("M105")

    run(scenario)


def test_a_controller_reset_between_jobs_is_greeted_again(rig: Rig, tmp_path: Path) -> None:
    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, ["G28", "G1 X1"]), history=False)
            await job.wait()
            with pytest.raises(rh.ControllerError, match="reset"):
                await printer.command("!!DEBUG:reset")
            await printer.wait_for(rh.State.READY, timeout=10)
            job = await printer.print(job_file(tmp_path, ["G1 X2", "G1 X3"], "b.gcode"))
            await job.wait()
            assert rig.executed(printer) == ["G28", "G1 X1", "G1 X2", "G1 X3"]

    run(scenario)


# --- host actions ----------------------------------------------------------------------


def test_an_m0_pauses_until_resume(rig: Rig, tmp_path: Path) -> None:
    job_path = tmp_path / "m0.gcode"
    job_path.write_text("G28\nG1 X1\nM0 ;Remove the part ; SAY done\nG1 X2\n")
    performed: list[str] = []

    async def record(action: rh.job.HostAction) -> bool:
        performed.extend(verb for verb, _ in action.actions)
        return True

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_path, history=False, on_action=record)
            async for event in job.events():
                if isinstance(event, rh.Paused):
                    assert event == rh.Paused(rh.PauseReason.M0, "Remove the part", "m0.gcode:3")
                    break
            assert printer.state is rh.State.PAUSED
            assert await settle(rig, printer, 3) == ["G28", "G1 X1", rig.pause_sync]
            await asyncio.sleep(0.2)
            assert len(rig.executed(printer)) == 3
            if rig.hyrel:  # the controller waits at its M0: a command would wait behind it
                with pytest.raises(rh.UsageError, match="holds the paused job"):
                    await printer.command("M105")
            await printer.resume()  # on Hyrel's link, end-wait (0x01) ends the M0
            await job.wait()
            assert rig.executed(printer) == ["G28", "G1 X1", rig.pause_sync, "G1 X2"]
        assert performed == ["SAY"]

    run(scenario)


def test_snapshot_markers_are_told_before_done_and_hold_nothing_up(
    rig: Rig, tmp_path: Path
) -> None:
    job_path = job_file(tmp_path, ["G28", "M790", "G1 X1", "M791", "G1 X2", "M791"])
    performed: list[tuple[str, str]] = []

    async def record(action: rh.job.HostAction) -> bool:
        performed.append((action.kind.value, action.position))
        if action.source_line == 4:
            raise RuntimeError("the camera fell over")  # told, and the job goes on
        return True

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_path, history=False, on_action=record)
            told = [
                (event.kind.value, event.position)
                async for event in job.events()
                if isinstance(event, rh.Action)
            ]
            assert (await job.wait()).outcome is rh.Outcome.COMPLETED
            assert told == [("layer", "job.gcode:2"), ("snapshot", "job.gcode:4"),
                            ("snapshot", "job.gcode:6")]  # fmt: skip
            assert await settle(rig, printer, 3) == ["G28", "G1 X1", "G1 X2"]
        assert performed == told

    run(scenario)


def test_an_action_that_declines_stops_the_job_safely(rig: Rig, tmp_path: Path) -> None:
    job_path = job_file(tmp_path, ["G28", "M792 ; BEEP", "G1 X1"])

    async def decline(action: rh.job.HostAction) -> bool:
        return False

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_path, history=False, on_action=decline)
            assert (await job.wait()).outcome is rh.Outcome.CANCELLED
            assert rig.executed(printer) == ["G28", *rig.safe_stop]

    run(scenario)


def test_a_bad_line_mid_job_stops_with_the_safe_stop_first(rig: Rig, tmp_path: Path) -> None:
    job_path = tmp_path / "bad.gcode"
    job_path.write_bytes(b"G28\nG1 X1\nM117 caf\xe9\nG1 X2\n")

    async def scenario() -> None:
        async with rig.connect() as printer:
            plan = printer.plan(job_path)  # a plan is not checked before: as a huge job
            job = await printer.print(plan, history=False)
            with pytest.raises(rh.JobError, match=r"bad\.gcode:3") as error:
                await job.wait()
            assert "acknowledged is bad.gcode:2" in str(error.value)
            assert rig.executed(printer) == ["G28", "G1 X1", *rig.safe_stop]
            with pytest.raises(rh.JobError, match="not ASCII"):
                await printer.print(job_path)  # checked first: nothing moves

    run(scenario)


# --- controllers that answer differently -------------------------------------------------


def test_a_controller_counting_lines_its_own_way_prints_through(tmp_path: Path) -> None:
    # OctoPrint's virtual printer's answer to a bad checksum, with its resend requests
    # for accepted lines and lines it drops with only an error.
    rig = Rig("sim", tmp_path, faults="counted_resend=1 spurious_resend=0.01 drop_with_error=0.01")
    commands = job_commands(EXAMPLE)

    async def scenario() -> None:
        async with rig.connect() as printer:
            assert printer.probe is rh.ProbeKind.COMMAND
            for _ in range(2):
                summary = await (await printer.print(EXAMPLE, history=False)).wait()
                assert summary.resends > 0
            # The probes are M105 lines that ran; the job ran exactly once, twice.
            ran = [c for c in rig.executed(printer) if c not in ("M105", "M115")]
            assert ran == commands + commands

    run(scenario)


def test_a_pyserial_url_reaches_a_controller_over_tcp() -> None:
    # socket://host:port, as ser2net or an ESP32 bridge serves a printer's port.
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        simulator = ControllerSimulator(ControllerSettings(banner=False), now=loop.time())

        class Serve(asyncio.Protocol):
            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                assert isinstance(transport, asyncio.Transport)
                self.transport = transport

            def data_received(self, data: bytes) -> None:
                now = loop.time()
                simulator.receive(data, now)
                simulator.advance(now)
                self.transport.write(simulator.take_output(now))

        server = await loop.create_server(Serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        sent: list[tuple[str, bool]] = []
        url = f"socket://127.0.0.1:{port}"
        async with rh.connect(
            url, poll_interval=None, line_tap=lambda *s: sent.append(s)
        ) as printer:
            assert printer.firmware is not None
            summary = await (await printer.print(EXAMPLE, history=False)).wait()
            assert summary.lines == len(job_commands(EXAMPLE))
        server.close()
        assert callers_commands(simulator.executed, sent) == job_commands(EXAMPLE)

    run(scenario)


def test_a_controller_slow_to_say_who_it_is_is_used_without_its_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A round trip of half a second, and the session waits only 0.3 s for M115's answer.
    monkeypatch.setattr(identify, "FIRMWARE_PATIENCE", 0.3)
    settings = ControllerSettings(latency=0.25)

    async def scenario() -> None:
        async with rh.connect("sim", sim=settings, poll_interval=None) as printer:
            assert printer.state is rh.State.READY and printer.firmware is None
            # M115's late answer stays its own: M105 gets only its temperatures.
            reply = await printer.command("M105")
            assert reply.lines == [] and reply.ok_line.startswith("ok T:21.0")
            reply = await printer.command("M115")
            assert reply.lines[0].startswith("FIRMWARE_NAME:")

    run(scenario)


def test_a_hyrel_controller_slow_to_answer_m115_is_known_by_its_pings_answer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(identify, "FIRMWARE_PATIENCE", 0.3)
    settings = ControllerSettings(latency=0.25, rx_buffer=8192, banner=False)

    async def scenario() -> None:
        connecting = rh.connect("sim", sim=settings, poll_interval=None, protocol="hyrel")
        async with connecting as printer:
            assert printer.firmware is not None
            assert printer.firmware.name == ">Hy: repetrel-host fake controller (Hyrel link)"
            assert printer.profile.name == "hyrel"
            # M115's late answer stays its own: M105 gets only its temperatures.
            assert (await printer.command("M105")).lines == [
                ">ST: T:21.0 /0.0 B:21.0 /0.0 @:0 B@:0"
            ]

    run(scenario)


def test_a_stop_under_way_is_not_abandoned_by_leaving_the_session(rig: Rig, tmp_path: Path) -> None:
    rig.move_time = 0.003
    commands = ["M104 S200", *(f"G1 X{i % 100}" for i in range(2000))]

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_file(tmp_path, commands), history=False)
            await settle(rig, printer, 20)
            assert not job.stop()  # the safe stop starts...
        # ...and closing the session waits for it rather than abandoning it.
        assert (await job.wait()).outcome is rh.Outcome.CANCELLED
        assert job.safe_stop_missing == []
        assert rig.executed(printer)[-len(rig.safe_stop) :] == rig.safe_stop

    run(scenario)


def test_a_host_action_that_breaks_stops_the_job_safely(rig: Rig, tmp_path: Path) -> None:
    job_path = job_file(tmp_path, ["G28", "M792 ; SHELL echo", "G1 X1"])

    async def broken(action: rh.job.HostAction) -> bool:
        raise ValueError("no closing quotation")

    async def scenario() -> None:
        async with rig.connect() as printer:
            job = await printer.print(job_path, history=False, on_action=broken)
            with pytest.raises(rh.JobError, match="host action failed"):
                await asyncio.wait_for(job.wait(), 10)
            assert rig.executed(printer) == ["G28", *rig.safe_stop]
            assert printer.state is rh.State.READY

    run(scenario)
