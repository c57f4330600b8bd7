"""Checks of a job before it is sent, against the machine and the loaded heads.

Errors refuse the job unless forced (as Repetrel's head-mismatch warnings stop
a print); warnings are shown and the job goes on.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from enum import StrEnum

from repetrel_host.gcode import addressing
from repetrel_host.gcode.commands import command_word

# The G-code reference's code chart (every code marked Yes or v5+, and the two
# marked No, which Hyrel knows but does not support).
CODE_CHART = frozenset(
    "G0 G1 G2 G2.1 G2.2 G2.3 G3 G3.1 G3.2 G3.3 G4 G10 G11 G16 G17 G18 G19 G20 G21 G28 "
    "G53 G54 G55 G56 G57 G58 G59 G81 G90 G91 G92 G93 "
    "M0 M3 M4 M5 M6 M7 M8 M9 M17 M18 M30 M82 M83 M84 M104 M106 M107 M109 M116 M140 "
    "M141 M190 M191 M203 M221 M229 M253 M254 M255 M619 M620 M621 M623 M660 M670 M671 "
    "M672 M674 M675 M676 M677 M678 M679 M684 M685 M689 M701 M703 M718 M719 M721 M722 "
    "M723 M728 M756 M772 M773 M783 M790 M791 M792".split()
)
# Described in the reference's sections though missing from the chart.
DOCUMENTED_ELSEWHERE = frozenset({"M1", "M627", "M702", "M704"})
NOT_SUPPORTED = frozenset({"G10", "G11"})


class Severity(StrEnum):
    ERROR = "error"  # refuses the job unless forced
    WARNING = "warning"


@dataclass(frozen=True, slots=True)
class Finding:
    line: int
    severity: Severity
    message: str

    def format(self, source: str) -> str:
        return f"{source}:{self.line}: {self.severity}: {self.message}"


class Linter:
    """Checks ``(source line, command)`` pairs one at a time, so a job can be checked
    while it streams; :func:`lint` checks a whole file.

    ``positions``: the machine's tool positions (yokes x 5 addresses), to catch T
    commands past them; ``loaded_tools``: the T numbers with a head, when known.
    ``streaming``: report a code outside the chart at its first use, not at the end.
    ``code_chart``: warn about codes outside Hyrel's chart (not for other firmwares).
    """

    def __init__(
        self,
        firmware: addressing.Firmware | None = None,
        positions: int | None = None,
        loaded_tools: frozenset[int] | None = None,
        streaming: bool = False,
        code_chart: bool = True,
    ) -> None:
        self.firmware = firmware
        self.code_chart = code_chart
        self.positions = positions
        self.loaded_tools = loaded_tools
        self.streaming = streaming
        self.unknown: dict[str, list[int]] = {}  # code -> [first line, lines using it]
        self._e_values_d1: int | None = None
        self._manual_flow: tuple[int, str] | None = None
        self._combination_reported = False
        self.commands = 0  # commands checked

    def check(self, line: int, command: str) -> list[Finding]:
        """Findings about one command (and any it completes with an earlier one)."""
        self.commands += 1
        findings: list[Finding] = []
        word = command_word(command)
        tool = addressing.tool_change(command)
        if tool is not None:
            finding = _check_tool(line, tool, self.positions, self.loaded_tools)
            return [finding] if finding is not None else findings
        if word == "M229":
            e, d = _parameter(command, "E"), _parameter(command, "D")
            if e == "1" and d == "0":
                findings.append(
                    Finding(line, Severity.ERROR, "M229 E1 D0 is an illegal combination")
                )
            elif e == "1" and d == "1" and self._e_values_d1 is None:
                self._e_values_d1 = line
        elif word in ("M703", "M723") and self._manual_flow is None:
            self._manual_flow = (line, word)
        elif self.code_chart and word not in CODE_CHART and word not in DOCUMENTED_ELSEWHERE:
            uses = self.unknown.setdefault(word, [line, 0])
            uses[1] += 1
            if self.streaming and uses[1] == 1:
                findings.append(_unknown_code(word, line, 1))
        if word in NOT_SUPPORTED:
            findings.append(
                Finding(line, Severity.WARNING, f"{word} is marked unsupported by Hyrel")
            )
        if self.firmware is not None and self.loaded_tools is not None and word.startswith("M"):
            finding = _check_variable(line, command, self.firmware, self.loaded_tools)
            if finding is not None:
                findings.append(finding)
        d1_line, manual = self._e_values_d1, self._manual_flow
        if d1_line is not None and manual is not None and not self._combination_reported:
            self._combination_reported = True
            findings.append(
                Finding(
                    max(manual[0], d1_line),
                    Severity.ERROR,
                    f"{manual[1]} (line {manual[0]}) does not work with M229 E1 D1 "
                    f"(line {d1_line}); use M229 E0 D0",
                )
            )
        return findings

    def unknown_codes(self) -> list[Finding]:
        """One warning per code outside Hyrel's chart, at its first line, with a count."""
        return [_unknown_code(word, line, uses) for word, (line, uses) in self.unknown.items()]

    def check_all(self, commands: Iterable[tuple[int, str]]) -> list[Finding]:
        """Check a whole job's ``(source line, command)`` pairs; findings in line order."""
        findings: list[Finding] = []
        for line, command in commands:
            findings += self.check(line, command)
        findings += self.unknown_codes()
        findings.sort(key=lambda f: f.line)
        return findings


def lint(
    commands: Iterable[tuple[int, str]],
    firmware: addressing.Firmware | None = None,
    positions: int | None = None,
    loaded_tools: frozenset[int] | None = None,
) -> list[Finding]:
    """Check a whole job's ``(source line, command)`` pairs; findings in line order."""
    return Linter(firmware, positions, loaded_tools).check_all(commands)


def _unknown_code(word: str, line: int, uses: int) -> Finding:
    more = f" (and {uses - 1} more lines)" if uses > 1 else ""
    return Finding(line, Severity.WARNING, f"{word} is not in Hyrel's code chart{more}")


def _check_tool(
    line: int, tool: int, positions: int | None, loaded_tools: frozenset[int] | None
) -> Finding | None:
    where = addressing.position_of_tool(tool)
    if where is None or (positions is not None and tool >= positions):
        return Finding(line, Severity.ERROR, f"T{tool} is not a tool position on this machine")
    if loaded_tools is not None and tool not in loaded_tools:
        return Finding(
            line,
            Severity.ERROR,
            f"T{tool} selects yoke {where[0]}, slot {where[1]}, which has no head loaded",
        )
    return None


def _check_variable(
    line: int, command: str, firmware: addressing.Firmware, loaded_tools: frozenset[int]
) -> Finding | None:
    value = addressing.t_parameter(command)
    if value is None:
        return None
    where = addressing.position_of_variable(firmware, value)
    if where is None:
        return None
    if addressing.tool_number(*where) in loaded_tools:
        return None
    hint = " (v4 files name the second slot T12)" if firmware == "v5" and value > 9 else ""
    return Finding(
        line,
        Severity.WARNING,
        f"T{value} addresses {addressing.describe_variable(firmware, value)}, "
        f"which has no head loaded{hint}",
    )


def _parameter(command: str, letter: str) -> str | None:
    for word in command.split()[1:]:
        if word[:1].upper() == letter:
            return word[1:]
    return None
