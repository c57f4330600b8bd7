"""The safe stop's lines, as the gcode package makes them."""

from repetrel_host.gcode.heaters import safe_stop_commands


def test_safe_stop_uses_the_firmwares_groups() -> None:
    v4 = safe_stop_commands("v4")
    assert v4[:4] == ["M107 T100", "M620 T100 E0", "M104 T100 S0", "M140 T90 S0"]
    assert v4[-1] == "M84"
    assert "M104 T47 S0" in safe_stop_commands("v5")
