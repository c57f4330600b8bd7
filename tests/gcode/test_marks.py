"""Slicer marks: layers, Z, M73 and time estimates, by source line."""

from __future__ import annotations

from pathlib import Path

from repetrel_host.gcode import analysis
from repetrel_host.gcode.analysis import scan_marks
from repetrel_host.gcode.marks import Layer
from repetrel_host.session.job import Job
from tests.support.paths import DATA

DATA = DATA


def write(tmp_path: Path, text: str, newline: str = "\n") -> Path:
    path = tmp_path / "job.gcode"
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def test_prusaslicer_layers_have_their_z_and_the_estimate_scales_by_bytes() -> None:
    found = scan_marks(DATA / "cone-prusaslicer.gcode")
    assert found.layers[:2] == [Layer(1, 24, 0.35), Layer(2, 599, 0.65)]
    assert found.total_seconds == 12 * 60 + 33
    lines = (DATA / "cone-prusaslicer.gcode").read_text().splitlines()
    assert lines[found.layers[-1].line - 1] == ";LAYER_CHANGE"
    where = found.at(600, fraction=0.5)
    assert (where.layer, where.z) == (Layer(2, 599, 0.65), 0.65)
    assert where.seconds_left == 753 / 2
    assert found.at(10).layer is None and found.at(10).z is None


def test_cura_layers_from_one_z_from_moves_time_from_elapsed(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        ";TIME:600\n;LAYER_COUNT:2\n;LAYER:0\nG0 F600 X1 Y1 Z0.2\nG1 X5 E1\n"
        ";TIME_ELAPSED:100.5\n;LAYER:1\nG10\nG0 X2 Z0.4\nG1 X6 E2\n;TIME_ELAPSED:600\n",
    )
    found = scan_marks(path)
    assert found.layers == [Layer(1, 3, 0.2), Layer(2, 7, 0.4)]
    assert found.at(8).seconds_left == 600 - 100.5
    assert found.at(9).z == 0.4
    assert found.layer(2) == Layer(2, 7, 0.4) and found.layer(3) is None


def test_m73_gives_percent_and_minutes_left(tmp_path: Path) -> None:
    path = write(tmp_path, "M73 P0 R10\n;LAYER_CHANGE\n;Z:0.2\nG1 Z.2\nM73 P50 R4\nG1 X1\n")
    where = scan_marks(path).at(6)
    assert (where.percent, where.seconds_left, where.z) == (50, 240, 0.2)


def test_line_numbers_agree_with_the_job_whatever_the_line_endings(tmp_path: Path) -> None:
    text = "G28\n;LAYER_CHANGE\n;Z:0.3\nG1 Z0.3\n\nM790\n;LAYER_CHANGE\nG1 X1\n"
    for newline in ("\n", "\r\n", "\r"):
        path = write(tmp_path, text, newline)
        found = scan_marks(path)
        assert [layer.line for layer in found.layers] == [2, 7], repr(newline)
        assert [n for n, *_ in Job(path).commands()] == [1, 4, 6, 8]


def test_chunk_boundaries_do_not_move_lines(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    text = "".join(f";LAYER_CHANGE\n;Z:{n}\nG1 X{n}\n" for n in range(1, 200))
    monkeypatch.setattr(analysis, "_CHUNK", 7)
    for newline in ("\n", "\r\n", "\r"):
        found = scan_marks(write(tmp_path, text, newline))
        assert [layer.line for layer in found.layers] == list(range(1, 597, 3))
        assert found.layers[-1].z == 199


def test_hyrel_m790_layers_and_an_unreadable_file(tmp_path: Path) -> None:
    path = write(tmp_path, "M790\nG1 Z1\nM790\nG1 Z2\n")
    assert [(x.line, x.z) for x in scan_marks(path).layers] == [(1, 1), (3, 2)]
    assert scan_marks(tmp_path / "missing.gcode").layers == []


def test_until_line_reads_no_further_than_needed(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    text = "".join(f";LAYER_CHANGE\n;Z:{n}\nG1 Z{n}\n" for n in range(1, 100))
    monkeypatch.setattr(analysis, "_CHUNK", 20)
    found = scan_marks(write(tmp_path, text), until_line=10)
    assert 4 <= len(found.layers) < 99  # the piece holding line 10, not the whole file
    assert found.at(10).layer == Layer(4, 10, 4)
    assert found.z_changes == [(2 + 3 * n, n + 1) for n in range(len(found.layers))]


def test_the_slicers_estimate_is_read_from_the_files_ends(tmp_path: Path) -> None:
    from repetrel_host.gcode.analysis import slicer_estimate

    body = "".join(f"G1 X{i % 100} Y1 F3000\n" for i in range(20000))  # 400 KB between
    prusa = tmp_path / "prusa.gcode"
    prusa.write_text("M73 P0 R12\n" + body + "; estimated printing time (normal mode) = 12m 33s\n")
    assert slicer_estimate(prusa) == 753.0  # the footer's, to the second
    cura = tmp_path / "cura.gcode"
    cura.write_text(";TIME:4567\n" + body)
    assert slicer_estimate(cura) == 4567.0
    m73 = tmp_path / "m73.gcode"
    m73.write_text("M73 P0 R30\n" + body)
    assert slicer_estimate(m73) == 1800.0
    small = tmp_path / "small.gcode"
    small.write_text(";TIME:60\nG28\n")
    assert slicer_estimate(small) == 60.0
    none = tmp_path / "none.gcode"
    none.write_text(body)
    assert slicer_estimate(none) is None
    assert slicer_estimate(tmp_path / "missing.gcode") is None
