"""A healthy link draws no error from the firmware, and its silences draw no probe.

The fake is Marlin 2.1's, as it is by default: 4 command slots, 16 planner blocks whose
moves take their planned time (here a twentieth of it), a 128-byte receive ring, the ring
emptied on every error, busy lines every 2 s, a heat wait's reports every second. It
counts every error it answers. On simulated time: the same run every time.
"""

import pytest

from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.fakes.simulator import ControllerSimulator, QueuedCommand
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.session.loopback import run_loopback

SCALE = 20.0  # a print of 20 minutes in one
MARLIN = ControllerSettings(
    bandwidth=11_520, latency=0.002, time_scale=SCALE, heat_rate=20.0, residency=2.0
)


def heated_job(moves: list[str]) -> list[str]:
    """A job as a slicer writes one: heat-up waits, homing, the moves, a dwell, the end."""
    return [
        "M140 S60", "M104 S200", "M190 S60", "M109 S200", "G28", "G92 E0",
        *moves,
        "G4 S2", "M400", "M104 S0", "M140 S0",
    ]  # fmt: skip


def long_moves(feed: int, count: int = 40) -> list[str]:
    return [f"G1 X{200 * (i % 2)} Y{100 + 10 * (i % 3)} F{feed}" for i in range(count)]


@pytest.mark.parametrize("mode", list(FlowMode))
def test_a_slicer_job_on_marlin_draws_no_error_and_no_probe_but_the_syncs(
    mode: FlowMode, cone_commands: list[str]
) -> None:
    commands = cone_commands[:3000]
    result = run_loopback(commands, FlowControl(mode), MARLIN)
    assert result.failure is None and result.executed == commands
    controller, host = result.controller, result.host
    assert controller.link.errors == 0
    assert host.stats.stalls_recovered == 0
    assert host.stats.pings == 3  # the greeting's, and the two that confirm the end


@pytest.mark.parametrize("feed", [60, 300, 1200, 6000, 30000])
def test_long_moves_at_every_speed_are_waited_for_not_probed(feed: int) -> None:
    commands = heated_job(long_moves(feed))
    result = run_loopback(commands, FlowControl(), MARLIN)
    assert result.failure is None and result.executed == commands
    assert result.controller.link.errors == 0
    assert result.host.stats.stalls_recovered == 0 and result.host.stats.pings == 3
    if feed <= 300:  # moves of 20 s and more: the planner was full, and silent, for long
        assert result.seconds > 40 * 200 / (feed / 60) / SCALE


def test_heat_waits_homing_and_dwells_one_line_at_a_time_are_waited_for() -> None:
    commands = heated_job(["G1 X100 F600", "G4 S10", "G28 X", "G4 P1500", "M400"] * 3)
    slow_heaters = ControllerSettings(
        bandwidth=11_520, latency=0.002, time_scale=SCALE, heat_rate=2.0, residency=10.0
    )
    result = run_loopback(commands, FlowControl(FlowMode.UNBUFFERED), slow_heaters)
    assert result.failure is None and result.executed == commands
    assert result.controller.link.errors == 0
    assert result.host.stats.stalls_recovered == 0
    assert result.seconds > (200 - 21) / 2.0  # the hotend's heat-up, at 2 degrees a second


class SlowHoming(ControllerSimulator):
    def _duration(self, command: QueuedCommand) -> float:
        return 20.0 if command.word == "G28" else super()._duration(command)


def test_a_silence_nothing_explains_costs_a_probe_that_runs_not_an_error() -> None:
    # Marlin built without its host keepalive, and no M155: a homing of 20 s says nothing.
    quiet = ControllerSettings(bandwidth=11_520, latency=0.002, keepalive=None)
    commands = ["G28", "G1 X10 F600"]
    result = run_loopback(commands, FlowControl(), controller=SlowHoming(quiet))
    assert result.failure is None and result.executed == commands
    assert result.controller.link.errors == 0
    # Asked after the grace a homing has, and seldom after: M105s that ran after it.
    assert 1 <= result.host.stats.stalls_recovered <= 2
    probes = result.controller.executed.count("M105")
    assert probes == result.host.stats.pings


class LosesTheHeatWaitsOk(ControllerSimulator):
    """Its first heat wait's ok is lost on the way (its reports are not)."""

    lost = False

    def _answer(self, command: QueuedCommand, now: float) -> None:
        if command.word == "M109" and not self.lost:
            self.lost = True
            self._set_heater(command, now)
            return
        super()._answer(command, now)


@pytest.mark.parametrize("residency", [0.0, 5.0])
def test_a_heat_waits_lost_ok_is_suspected_once_its_reports_say_it_is_over(
    residency: float,
) -> None:
    # The hotend is there at once. Marlin's heat wait still reports at once (with "W:5",
    # five seconds of residency left, where it has one) and then its ok: lost here. Its
    # reports tell when the wait ends; a heat wait heard nothing of is given 30 s.
    settings = ControllerSettings(bandwidth=11_520, latency=0.002, residency=residency)
    commands = ["M109 S200", "G1 X10 F600"]
    flow = FlowControl(FlowMode.UNBUFFERED)
    result = run_loopback(commands, flow, controller=LosesTheHeatWaitsOk(settings))
    assert result.failure is None and result.executed == commands
    assert result.controller.link.errors == 0
    assert result.host.stats.stalls_recovered == 1
    assert residency < result.seconds < residency + 10  # its reports' word, a report's gap
