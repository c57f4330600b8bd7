"""T addressing against the reference's tables (T addressing v5 page, M703 table, footer)."""

import pytest

from repetrel_host.gcode import addressing as a

# "Device Addresses - Individual Physical Heads": yoke rows, position columns.
V5_HEADS = [
    [0, 1, 2, 3, 4],
    [5, 6, 7, 8, 9],
    [10, 11, 12, 13, 14],
    [15, 16, 17, 18, 19],
]


@pytest.mark.parametrize("yoke", [1, 2, 3, 4])
@pytest.mark.parametrize("slot", [1, 2, 3, 4, 5])
def test_v5_unified_addresses(yoke: int, slot: int) -> None:
    expected = V5_HEADS[yoke - 1][slot - 1]
    assert a.tool_number(yoke, slot) == expected
    assert a.head_variable("v5", yoke, slot) == expected
    assert a.position_of_tool(expected) == (yoke, slot)
    assert a.position_of_variable("v5", expected) == (yoke, slot)


@pytest.mark.parametrize(("slot", "variable"), [(1, 11), (2, 12), (3, 13), (4, 14), (5, 15)])
def test_v4_head_variables_follow_the_m703_table(slot: int, variable: int) -> None:
    # "Clone Address T11 T12 T13 T14 T15" for the 1st..5th slot; tool changes stay T0..T4.
    assert a.head_variable("v4", 1, slot) == variable
    assert a.tool_number(1, slot) == slot - 1
    assert a.position_of_variable("v4", variable) == (1, slot)


def test_v4_is_known_for_yoke_one_only() -> None:
    with pytest.raises(ValueError, match="yoke 1"):
        a.head_variable("v4", 2, 1)


def test_special_devices_and_groups() -> None:
    assert a.describe_variable("v5", 21) == "CO2 laser"
    assert a.describe_variable("v5", 24) == "Bed1 / Chamber1"
    assert a.describe_variable("v5", 40) == "all devices"
    assert a.describe_variable("v5", 42) == "yoke 2, all heads"
    assert a.describe_variable("v5", 48) == "all virtual devices (T30-T39)"
    assert a.describe_variable("v5", 33).startswith("virtual head")
    assert a.describe_variable("v5", 2) == "the head in yoke 1, slot 3"
    assert a.position_of_variable("v5", 21) is None


def test_footer_groups() -> None:
    # The standard footer: "M104 T100 S0 ; head temps", "M140 T90 S0 ; bed temps".
    assert a.all_heads_variable("v4") == 100
    assert a.all_beds_variable("v4") == 90
    assert a.describe_variable("v4", 100) == "all heads"
    assert a.all_beds_variable("v5") == 46


def test_parsing_t_words() -> None:
    assert a.tool_change("T3") == 3
    assert a.tool_change("t12") == 12
    assert a.tool_change("M104 T1 S200") is None
    assert a.t_parameter("M104 T12 S200") == 12
    assert a.t_parameter("M107") is None
    assert a.t_parameter("M117 TEXT") is None
    assert a.position_of_tool(20) is None


@pytest.mark.parametrize(("yoke", "slot"), [(0, 1), (5, 1), (1, 0), (1, 6)])
def test_positions_out_of_range(yoke: int, slot: int) -> None:
    with pytest.raises(ValueError):
        a.tool_number(yoke, slot)
