"""The in-process simulated controller, greeted as the fake tests start it."""

from repetrel_host.fakes.settings import ControllerSettings
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.protocol.framing import frame


def wire(*commands: str, first: int = 1) -> bytes:
    """``commands`` framed as numbered lines from ``first``."""
    return b"".join(frame(first + i, c) for i, c in enumerate(commands))


def started(settings: ControllerSettings) -> ControllerSimulator:
    """A simulator on ``settings`` that took ``M110 N0`` (and said ``start``)."""
    sim = ControllerSimulator(settings)
    sim.receive(frame(0, "M110 N0"), 0.0)
    sim.advance(0.0)
    assert sim.take_output(0.0) == b"start\nok\n"
    return sim
