"""The motion state the session keeps from the commands the controller ran (pure)."""

from __future__ import annotations

import pytest

from repetrel_host.session.motion_state import MotionState, after

HOMED = MotionState(homed="xyz")


@pytest.mark.parametrize(
    ("state", "command", "hyrel", "homed"),
    [
        (MotionState(), "G28", False, "xyz"),  # Marlin homes all three
        (MotionState(), "G28", True, None),  # Hyrel's homes only what it names
        (MotionState(), "G28 X0 Y0", True, "xy"),
        (MotionState(), "g28 z ; the bed", False, "z"),
        (MotionState(homed="xy"), "G28 Z", False, "xyz"),
        (HOMED, "M84", False, ""),
        (HOMED, "M18 X Y", False, "z"),
        (HOMED, "M84 S120", False, None),  # Marlin's idle timeout, nothing turned off
        (HOMED, "M84 E", False, None),  # the extruder's motor only
        (HOMED, "G1 X5", False, None),
    ],
)
def test_homing_and_motors_off(
    state: MotionState, command: str, hyrel: bool, homed: str | None
) -> None:
    found = after(state, command, hyrel)
    assert (found.homed if found is not None else None) == homed


def test_marlins_factors_and_not_hyrels_flow_set_up() -> None:
    assert after(MotionState(), "M220 S150", False) == MotionState(speed_factor=1.5)
    assert after(MotionState(), "M221 S95", False) == MotionState(extrude_factor=0.95)
    assert after(MotionState(), "M221 T11 S1.0 P77 W0.5 Z0.3", True) is None
    assert after(MotionState(), "M220 B", False) is None  # Marlin's backup: no factor given
