"""Reading a job: source positions, host-side codes, lines the host keeps to itself."""

from pathlib import Path

import pytest

from repetrel_host.errors import JobError
from repetrel_host.session.job import ActionKind, HostAction, Job, JobLine, parse_actions


def items(tmp_path: Path, text: bytes, pause_sync: str = "M400") -> list[object]:
    path = tmp_path / "job.gcode"
    path.write_bytes(text)
    return list(Job(path, pause_sync=pause_sync).items())


def test_lines_keep_their_source_positions(tmp_path: Path) -> None:
    got = items(tmp_path, b"; start\nG28\n\nG1 X1 ; move\r\n")
    assert got == [JobLine(1, 2, "G28", 12, "job.gcode"), JobLine(2, 4, "G1 X1", 27, "job.gcode")]
    assert got[1].position == "job.gcode:4"  # type: ignore[attr-defined]


def test_m0_becomes_a_sync_then_a_pause_with_its_message(tmp_path: Path) -> None:
    got = items(tmp_path, b"G1 X1\nM0 ;Remove the part\nG1 X2\n", pause_sync="G4 P1")
    assert got[1] == JobLine(2, 2, "G4 P1", 26, "job.gcode")
    assert got[2] == HostAction(ActionKind.PAUSE, "Remove the part", (), 2, "job.gcode")
    assert got[3] == JobLine(3, 3, "G1 X2", 32, "job.gcode")


def test_m0_and_m792_actions(tmp_path: Path) -> None:
    got = items(tmp_path, b"M0 ; SAY Hello Wilbur ; PIC C:\\mr_ed.png\nM792 ; BEEP ; SEND hi\n")
    pause = got[1]
    assert isinstance(pause, HostAction)
    assert pause.actions == (("SAY", "Hello Wilbur"), ("PIC", "C:\\mr_ed.png"))
    actions = (("BEEP", ""), ("SEND", "hi"))
    assert got[2] == HostAction(ActionKind.ACTIONS, "", actions, 2, "job.gcode")
    assert len(got) == 3  # M792 itself is not forwarded


def test_logging_codes(tmp_path: Path) -> None:
    got = items(tmp_path, b"M719 P10 S1\nM718\n")
    assert got[0] == JobLine(1, 1, "M719 P10 S1", 12, "job.gcode")
    assert isinstance(got[1], HostAction) and got[1].kind is ActionKind.LOG_START
    assert isinstance(got[2], HostAction) and got[2].kind is ActionKind.LOG_STOP
    assert len(got) == 3


def test_m790_and_m791_are_the_hosts_camera_codes(tmp_path: Path) -> None:
    got = items(tmp_path, b"G1 Z0.2\nM790 ; new layer\nG1 X1\nM791\n")
    assert got[1] == HostAction(ActionKind.LAYER, "", (), 2, "job.gcode")
    assert got[3] == HostAction(ActionKind.SNAPSHOT, "", (), 4, "job.gcode")
    assert [i.command for i in got if isinstance(i, JobLine)] == ["G1 Z0.2", "G1 X1"]


def test_host_owned_lines_are_not_sent(tmp_path: Path) -> None:
    # M110 would desynchronise numbering; Hyrel's bare N14 only sets a logging number.
    got = items(tmp_path, b"N14 ; set line numbers\nM110 N0\nN7 G28*99\nG1 X1\n")
    assert [i.command for i in got if isinstance(i, JobLine)] == ["G28", "G1 X1"]


def test_parse_actions_keeps_free_text() -> None:
    assert parse_actions(" Remove the part ; BEEP") == ("Remove the part", (("BEEP", ""),))
    assert parse_actions("") == ("", ())


def test_a_bad_line_names_its_position(tmp_path: Path) -> None:
    with pytest.raises(JobError, match=r"^job.gcode:2: the command is not ASCII text$"):
        items(tmp_path, b"G28\nM117 caf\xe9\n")
