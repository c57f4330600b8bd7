"""Checks before sending, one finding per problem with its file line."""

import pytest

from repetrel_host.gcode.commands import command_word
from repetrel_host.gcode.lint import Finding, Linter, Severity, lint


def check(text: str, **kwargs: object) -> list[Finding]:
    commands = [(n, line) for n, line in enumerate(text.splitlines(), start=1) if line]
    return lint(commands, **kwargs)  # type: ignore[arg-type]


def test_tool_change_to_an_empty_slot_is_an_error() -> None:
    findings = check("G28\nT0\nT3\n", firmware="v5", positions=5, loaded_tools=frozenset({0, 1}))
    assert findings == [
        Finding(3, Severity.ERROR, "T3 selects yoke 1, slot 4, which has no head loaded"),
    ]
    assert findings[0].format("job.gcode") == (
        "job.gcode:3: error: T3 selects yoke 1, slot 4, which has no head loaded"
    )


def test_tool_change_past_the_machine_is_an_error_even_without_a_loadout() -> None:
    findings = check("T7\n", firmware="v5", positions=5)
    assert [f.severity for f in findings] == [Severity.ERROR]
    assert "not a tool position" in findings[0].message
    assert check("T7\n") == []  # nothing known, nothing to say


def test_m229_e1_d0_is_illegal() -> None:
    (finding,) = check("M229 E1 D0\n")
    assert (finding.line, finding.severity) == (1, Severity.ERROR)
    assert "illegal" in finding.message


def test_m703_and_m723_do_not_work_with_e_values_on_the_motion_controller() -> None:
    (finding,) = check("M229 E1 D1\nG1 X1\nM703 T13 S11\n")
    assert finding.line == 3
    assert finding.severity is Severity.ERROR
    assert "M703 (line 3)" in finding.message and "M229 E1 D1 (line 1)" in finding.message
    (finding,) = check("M723 S500 E50000 T0\nM229 E1 D1\n")
    assert finding.line == 2 and "M723" in finding.message
    assert check("M229 E0 D0\nM723 S500 E50000 T0\n") == []


def test_codes_outside_the_chart_are_warned_once_with_a_count() -> None:
    findings = check("M73 P1\nG1 X1\nM73 P2\nM73 P3\nM900 K0\nG2.1 X1\n")
    assert findings == [
        Finding(1, Severity.WARNING, "M73 is not in Hyrel's code chart (and 2 more lines)"),
        Finding(5, Severity.WARNING, "M900 is not in Hyrel's code chart"),
    ]


def test_unsupported_codes_are_warned() -> None:
    (finding,) = check("G10\n")
    assert "unsupported" in finding.message


def test_head_variable_for_an_empty_slot_hints_at_v4_files() -> None:
    (finding,) = check("M104 T12 S200\n", firmware="v5", positions=5, loaded_tools=frozenset({1}))
    assert finding.severity is Severity.WARNING
    assert "T12" in finding.message and "v4" in finding.message
    assert check("M104 T12 S200\n", firmware="v4", positions=5, loaded_tools=frozenset({1})) == []
    assert check("M140 T24 S60\n", firmware="v5", positions=5, loaded_tools=frozenset({1})) == []


def test_a_clean_slicer_file_has_no_findings() -> None:
    text = "M107\nM104 S200\nG28\nG1 Z5 F5000\nM109 S200\nG21\nG90\nM82\nG92 E0\nM106 S255\nM84\n"
    assert check(text, firmware="v5", positions=5, loaded_tools=frozenset({0})) == []


def test_streaming_linter_reports_each_problem_as_its_line_is_read() -> None:
    linter = Linter(firmware="v5", positions=5, loaded_tools=frozenset({0}), streaming=True)
    lines = ["M999", "G1 X1", "M999", "M229 E1 D1", "M703 T0", "T3"]
    seen = [linter.check(number, text) for number, text in enumerate(lines, start=1)]
    assert [[(f.line, f.severity) for f in found] for found in seen] == [
        [(1, Severity.WARNING)],  # an unknown code: reported once, at its first use
        [],
        [],
        [],
        [(5, Severity.ERROR)],  # M703 with M229 E1 D1 earlier: known once both were read
        [(6, Severity.ERROR)],
    ]
    assert linter.commands == 6
    assert (
        linter.unknown_codes()[0].message == "M999 is not in Hyrel's code chart (and 1 more lines)"
    )


@pytest.mark.parametrize(
    ("command", "word"),
    [
        ("G1 X10.5 Y20 E0.5", "G1"),
        ("G1X5", "G1"),
        ("g01 x5", "G1"),
        ("G01 X1", "G1"),
        ("G00", "G0"),
        ("G 1 X1", "G1"),
        ("G1\tX1", "G1"),
        ("G92.1 X0", "G92.1"),
        ("M104 S200", "M104"),
        ("T12", "T12"),
        ("M", "M"),
    ],
)
def test_command_word_normalises_the_first_word(command: str, word: str) -> None:
    assert command_word(command) == word
