"""One pass over a G-code file: the slicer's marks, the layers' byte offsets, and
OctoPrint's gcodeAnalysis (estimate, filament per tool, boxes), on hand-written G-code and
on real PrusaSlicer output. The figures for hand-written files are worked out in the
comments. OctoPrint's own interpreter (octoprint/util/gcodeInterpreter.py) gives the same
lengths and boxes for the two slicer files and the hand-written ones but where this pass
reads more than it does: ``G28 X`` without a number (it homes every axis), a clockwise arc
through south (it misses arcs that sweep over east), words glued, spaced or in lower case
(it skips or misreads them)."""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from octorest import OctoRest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.gcode import analysis
from repetrel_host.gcode.analysis import Box, Filament, FileSummary, analyse
from repetrel_host.gcode.estimate import estimate_file
from repetrel_host.gcode.marks import Layer
from tests.support.paths import DATA
from tests.support.server import KEY, Server, wait_for

DATA = DATA
CONE = DATA / "cone-prusaslicer.gcode"
SPHERE = DATA / "sphere-prusaslicer.gcode"


def write(tmp_path: Path, text: str, newline: str = "\n", name: str = "job.gcode") -> Path:
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def lengths(summary: FileSummary | None) -> dict[str, float]:
    assert summary is not None
    return {tool: round(used.length, 6) for tool, used in summary.filament.items()}


def test_absolute_e_with_g92_resets_and_a_retraction_counts_what_was_pushed_out(
    tmp_path: Path,
) -> None:
    path = write(
        tmp_path,
        "G90\nM82\nG92 E0\n"
        "G1 X0 Y0 Z0.2 F3000\n"  # travel from the origin
        "G1 X10 Y0 E1\n"  # +1
        "G1 E0.2\n"  # retract 0.8: not negative filament
        "G1 X20 Y5\n"  # travel
        "G1 E1\n"  # back 0.8: not counted twice
        "G1 X20 Y15 E2\n"  # +1
        "G92 E0\n"  # the register, not the count
        "G1 X5 Y15 E1.5\n"  # +1.5
        "G1 E-1\n",  # a last retraction takes nothing back
    )
    summary = analyse(path).summary
    assert lengths(summary) == {"tool0": 3.5}
    assert summary is not None and summary.printing_area == Box(0, 0, 0, 20, 15, 0.2)
    assert summary.travel_area == Box(0, 0, 0, 20, 15, 0.2)
    volume = 3.5 * math.pi * (1.75 / 2) ** 2 / 1000  # no diameter in the file: 1.75 mm
    assert summary.filament["tool0"].volume == pytest.approx(volume, abs=1e-5)


def test_relative_e_retractions_and_moves_that_do_not_extrude(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "M83\nG1 X5 Y5 Z0.3\n"
        "G1 X10 Y5 E2\n"  # +2 from (5, 5)
        "G1 E-0.8\nG1 X50 Y50\nG1 E0.8\n"  # retract, travel, back
        "G1 X50 Y60 E1\n"  # +1
        "G0 X90 Y90 Z5\n"  # travel only: the travel box
        "G1 E-3\n",
    )
    summary = analyse(path).summary
    assert lengths(summary) == {"tool0": 3.0}
    assert summary is not None and summary.printing_area == Box(5, 5, 0, 50, 60, 0.3)
    assert summary.travel_area == Box(0, 0, 0, 90, 90, 5)
    found = summary.gcode_analysis()
    assert found["dimensions"] == {"width": 45, "depth": 55, "height": 0.3}
    assert found["printingArea"] == {
        "minX": 5,
        "minY": 5,
        "minZ": 0,
        "maxX": 50,
        "maxY": 60,
        "maxZ": 0.3,
    }
    assert found["travelDimensions"] == {"width": 90, "depth": 90, "height": 5}
    assert "slicerEstimatedPrintTime" not in found  # no slicer estimate in the file
    assert "estimatedPrintTime" not in found  # the moves' time not asked for


def test_each_tool_keeps_its_own_e_and_diameter(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "; filament_diameter = 1.75,2.85\nG90\nM82\n"
        "T0\nG92 E0\nG1 X1 Y1 E2\n"
        "T1\nG92 E0\nG1 X2 Y1 E3\n"
        "T0\nG1 X3 Y1 E3\n"  # T0's register is still 2: +1
        "T1\nG1 X4 Y1 E2.5\n",  # a retraction on T1
    )
    summary = analyse(path).summary
    assert lengths(summary) == {"tool0": 3.0, "tool1": 3.0}
    assert summary is not None
    assert summary.filament["tool1"].volume == pytest.approx(
        3 * math.pi * (2.85 / 2) ** 2 / 1000, abs=1e-5
    )


def test_g91_moves_everything_relative_and_g28_homes(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "G28\nG1 Z1\nG91\nG1 X10 Y10 E1\nG1 X5 E1\nG1 Z2\nG90\nG28 X\nG1 Y30 E5\n",
    )
    summary = analyse(path).summary
    # E is relative under G91 (as in OctoPrint): 1 + 1; then absolute: 5 - 2 = +3.
    assert lengths(summary) == {"tool0": 5.0}
    assert summary is not None and summary.printing_area == Box(0, 0, 0, 15, 30, 3)


def test_arcs_reach_past_their_ends(tmp_path: Path) -> None:
    counter = write(tmp_path, "M83\nG1 X10 Y0\nG3 X-10 Y0 I-10 J0 E3\n", name="g3.gcode")
    summary = analyse(counter).summary
    assert summary is not None and summary.printing_area == Box(-10, 0, 0, 10, 10, 0)
    clockwise = write(tmp_path, "M83\nG1 X10 Y0\nG2 X-10 Y0 I-10 J0 E3\n", name="g2.gcode")
    summary = analyse(clockwise).summary
    assert summary is not None and summary.printing_area == Box(-10, -10, 0, 10, 0, 0)


def test_glued_spaced_and_lower_case_words_are_read(tmp_path: Path) -> None:
    path = write(tmp_path, "M83\nG1X10Y10E1\ng1 x20 e1\n  G1 X 30 E1 ; spaced\n")
    summary = analyse(path).summary
    assert lengths(summary) == {"tool0": 3.0}
    assert summary is not None and summary.printing_area == Box(0, 0, 0, 30, 10, 0)


def test_a_file_without_extrusion_is_openprints_empty_result(tmp_path: Path) -> None:
    summary = analyse(write(tmp_path, "G28\nG1 X10 Y10\nM84\n")).summary
    assert summary is not None
    found = summary.gcode_analysis()
    assert found["_empty"] is True and found["filament"] == {}
    assert found["printingArea"] == dict.fromkeys(
        ("minX", "minY", "minZ", "maxX", "maxY", "maxZ"), 0
    )
    assert found["dimensions"] == {"width": 0, "depth": 0, "height": 0}
    assert summary.travel_area == Box(0, 0, 0, 10, 10, 0)


@pytest.mark.parametrize(
    ("path", "layers", "seconds", "length", "volume", "box"),
    [
        (CONE, 82, 753, 1083.86, 2.61, Box(79.379, 79.379, 0, 120.621, 120.621, 24.65)),
        (SPHERE, 155, 3175, 6903.72, 16.61, Box(76.981, 76.985, 0, 123.02, 123.02, 46.55)),
    ],
)
def test_prusaslicer_files_as_the_slicer_and_octoprint_measure_them(
    path: Path, layers: int, seconds: float, length: float, volume: float, box: Box
) -> None:
    found = analyse(path)
    summary = found.summary
    assert summary is not None
    assert summary.slicer == "PrusaSlicer 2.5.0"
    assert summary.layers == len(found.marks.layers) == len(found.layer_offsets) == layers
    assert summary.slicer_seconds == found.marks.total_seconds == seconds
    assert summary.filament == {"tool0": Filament(length, volume)}  # the slicer's figures
    assert summary.printing_area == box
    content = path.read_bytes()
    assert all(content[at:].startswith(b";LAYER_CHANGE\n") for at in found.layer_offsets)
    lines = content.decode().splitlines()
    assert [lines[layer.line - 1] for layer in found.marks.layers] == [";LAYER_CHANGE"] * layers


def test_without_the_slicers_figures_the_moves_say_the_same(tmp_path: Path) -> None:
    text = CONE.read_text()
    stripped = "".join(
        line for line in text.splitlines(True) if not line.startswith("; filament used")
    )
    summary = analyse(write(tmp_path, stripped)).summary
    assert lengths(summary) == {"tool0": 1083.86367}  # OctoPrint's: 1083.8636699999993
    assert summary is not None
    assert summary.filament["tool0"].volume == pytest.approx(2.61, abs=0.005)


def test_the_slicers_layer_marks_win_over_m790_and_m790_counts_alone(tmp_path: Path) -> None:
    both = write(
        tmp_path,
        "G28\nM790\n;LAYER_CHANGE\n;Z:0.2\nG1 Z0.2\nM790\n;LAYER_CHANGE\n;Z:0.4\nG1 Z0.4\n",
    )
    found = analyse(both)
    assert found.marks.layers == [Layer(1, 3, 0.2), Layer(2, 7, 0.4)]
    content = both.read_bytes()
    assert [content[at:].split(b"\n")[0] for at in found.layer_offsets] == [b";LAYER_CHANGE"] * 2
    hyrel = write(tmp_path, "G28\nM790\nG1 Z0.2\nM790 ; next\nG1 Z0.4\n", name="m790.gcode")
    found = analyse(hyrel)
    assert found.marks.layers == [Layer(1, 2, 0.2), Layer(2, 4, 0.4)]
    content = hyrel.read_bytes()
    assert [content[at:].split(b"\n")[0] for at in found.layer_offsets] == [
        b"M790",
        b"M790 ; next",
    ]


def test_offsets_and_lines_hold_whatever_the_line_ends_and_pieces(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = "".join(f";LAYER_CHANGE\n;Z:{n}\n  G1 X{n} E{n}\n" for n in range(1, 60))
    whole = {}
    for newline in ("\n", "\r\n", "\r"):
        path = write(tmp_path, text, newline)
        found = analyse(path)
        content = path.read_bytes()
        assert [layer.line for layer in found.marks.layers] == list(range(1, 178, 3))
        assert all(content[at:].startswith(b";LAYER_CHANGE") for at in found.layer_offsets)
        assert all(content[at - 1 : at] in (b"", b"\n", b"\r") for at in found.layer_offsets)
        whole[newline] = found
    monkeypatch.setattr(analysis, "_CHUNK", 7)
    for newline, before in whole.items():
        found = analyse(write(tmp_path, text, newline))
        assert found.layer_offsets == before.layer_offsets, repr(newline)
        assert found.marks.layers == before.marks.layers
        assert found.summary == before.summary
        assert lengths(found.summary) == {"tool0": 59}


def test_the_marks_alone_are_those_of_the_whole_pass() -> None:
    for path in (CONE, SPHERE):
        whole, marks_only = analyse(path), analyse(path, moves=False)
        assert marks_only.summary is None
        assert marks_only.layer_offsets == whole.layer_offsets
        assert marks_only.marks == whole.marks


def test_cura_marks_and_filament_in_metres(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        ";FLAVOR:Marlin\n;TIME:600\n;Filament used: 1.5m\n;Generated with Cura_SteamEngine 5.2.1\n"
        "M82\n;LAYER:0\nG0 X1 Y1 Z0.2\nG1 X5 E1\n;TIME_ELAPSED:100.5\n"
        ";LAYER:1\nG0 X2 Z0.4\nG1 X6 E2\n;TIME_ELAPSED:600\n",
    )
    found = analyse(path)
    assert found.marks.layers == [Layer(1, 6, 0.2), Layer(2, 10, 0.4)]
    assert found.summary is not None and found.summary.slicer == "Cura 5.2.1"
    assert found.summary.slicer_seconds == 600
    assert lengths(found.summary) == {"tool0": 1500}  # the slicer's, not the moves' 2


def test_a_summary_is_kept_and_read_back_whole() -> None:
    summary = analyse(CONE, planned=True).summary
    assert summary is not None
    assert summary.planned_seconds is not None and summary.slicer_seconds == 753
    assert summary.planned_limits_from == "the file's slicer settings"
    assert FileSummary.from_dict(json.loads(json.dumps(summary.as_dict()))) == summary
    empty = FileSummary()
    assert FileSummary.from_dict(empty.as_dict()) == empty
    keys = set(summary.gcode_analysis())
    assert keys == {
        "estimatedPrintTime",
        "slicerEstimatedPrintTime",
        "filament",
        "dimensions",
        "printingArea",
        "travelDimensions",
        "travelArea",
    }
    assert summary.as_json()["layers"] == 82


# --- through the server: octorest, the native API, a restart -------------------------------


def layered_job(layers: int = 3, moves: int = 300) -> str:
    """A job with Hyrel's M790 beside PrusaSlicer's mark at each layer, relative E."""
    text = "G28\nM83\n"
    for layer in range(1, layers + 1):
        text += f"M790\n;LAYER_CHANGE\n;Z:{layer * 0.2:.1f}\nG1 Z{layer * 0.2:.1f} F600\n"
        text += "".join(f"G1 X{i + 1} Y{layer} E0.5 F3000\n" for i in range(moves))
    return text


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_the_servers_files_and_job_carry_the_analysis_kept_across_a_restart(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.01")
    server = servers({"bench": fake.port})
    rest = OctoRest(url=server.url, apikey=KEY)
    with CONE.open("rb") as handle:
        rest.upload(("cone.gcode", handle))
    with server.client() as client:  # octorest sends the folder's name as JSON: form data
        assert client.post("/api/files/local", data={"foldername": "sub"}).status_code == 201
    rest.move("cone.gcode", "sub")  # its analysis goes with it
    # The print time from the moves follows the upload's analysis, made in the background.
    wait_for(
        lambda: "estimatedPrintTime" in rest.files_info("local", "sub/cone.gcode")["gcodeAnalysis"],
        what="the cone's print time",
    )
    cone = rest.files_info("local", "sub/cone.gcode")["gcodeAnalysis"]
    planned = estimate_file(CONE).seconds  # from the moves, PrusaSlicer's figure beside it
    assert cone["estimatedPrintTime"] == planned and cone["slicerEstimatedPrintTime"] == 753
    assert cone["filament"] == {"tool0": {"length": 1083.86, "volume": 2.61}}
    assert cone["dimensions"] == {"width": 41.242, "depth": 41.242, "height": 24.65}
    assert cone["printingArea"] == {
        "minX": 79.379,
        "minY": 79.379,
        "minZ": 0,
        "maxX": 120.621,
        "maxY": 120.621,
        "maxZ": 24.65,
    }
    with server.client() as client:
        wait_for(lambda: client.get("/api/job").json()["state"] == "Operational", what="ready")
        native = {f["path"]: f["analysis"] for f in client.get("/v1/files").json()}
        assert native["sub/cone.gcode"]["layers"] == 82
        assert native["sub/cone.gcode"]["slicer"] == "PrusaSlicer 2.5.0"
        assert native["sub/cone.gcode"]["filament"] == cone["filament"]
        assert native["sub/cone.gcode"]["estimatedPrintTime"] == planned
        assert native["sub/cone.gcode"]["slicerEstimatedPrintTime"] == 753
        limits = native["sub/cone.gcode"]["estimatedPrintTimeLimitsFrom"]
        assert limits == "the file's slicer settings"
    rest.select("sub/cone.gcode")
    selected = rest.job_info()["job"]
    assert selected["estimatedPrintTime"] == planned and selected["filament"] == cone["filament"]
    assert selected["slicerEstimatedPrintTime"] == 753

    # A file put there by hand is listed, and analysed in the background.
    shutil.copy(SPHERE, server.data_dir / "files" / "sphere.gcode")

    def sphere() -> dict[str, Any] | None:
        found: dict[str, Any] | None = rest.files_info("local", "sphere.gcode").get("gcodeAnalysis")
        return found

    assert wait_for(sphere, what="the sphere's analysis")["filament"]["tool0"]["length"] == 6903.72

    # A job with M790 beside each ;LAYER_CHANGE has as many layers as the slicer made.
    with server.client() as client:  # octorest sends print=true as JSON: form data
        upload = ("layers.gcode", layered_job().encode())
        started = client.post("/api/files/local", files={"file": upload}, data={"print": "true"})
        assert started.status_code == 201, started.text

        def printing_job() -> dict[str, Any] | None:
            job: dict[str, Any] = client.get("/api/job").json()["job"]
            return job if job["file"]["name"] == "layers.gcode" and job["filament"] else None

        job = wait_for(printing_job, what="the job's analysis")
        assert job["file"]["name"] == "layers.gcode"
        assert job["filament"]["tool0"]["length"] == 450  # 3 x 300 x 0.5, from the moves
        printing = wait_for(
            lambda: (
                (now := client.get("/v1/printers/bench").json()["job"]) and now["layer"] and now
            ),
            what="the first layer",
        )
        assert printing["layers"] == 3 and printing["layer"] <= 3
        running = wait_for(
            lambda: (
                ((now := client.get("/v1/printers/bench").json()["job"]) and now["estimated_time"])
                and now
            ),
            what="the running job's estimate",
        )
        layers_file = server.data_dir / "files" / "layers.gcode"
        split = ("estimated_moving", "estimated_heating", "estimated_tool_changes")
        # Its plan, split; the whole is what it ran and has left (at its pace).
        assert sum(running[key] for key in split) == pytest.approx(
            estimate_file(layers_file).seconds
        )
        assert running["estimated_time_limits_from"] == "Marlin's defaults"
        assert running["slicer_estimated_time"] is None
        # No slicer's estimate in the file: the time from its moves all the same.
        assert job["slicerEstimatedPrintTime"] is None
        job_now = client.get("/api/job").json()["job"]  # the same figure, a moment later
        assert job_now["estimatedPrintTime"] == pytest.approx(running["estimated_time"], rel=0.1)
        wait_for(lambda: client.get("/api/job").json()["progress"]["completion"] == 100)
        assert client.get("/api/job").json()["job"]["filament"] == job["filament"]

    # Kept in the data folder: a restart reads it from there (the figure written there is
    # the one answered), not from the file.
    server.stop()
    kept = list((server.data_dir / "analysis").glob("*.json"))
    assert len(kept) == 3  # cone, sphere, layers
    for path in kept:
        entry = json.loads(path.read_text())
        if entry["file"] == "files/sub/cone.gcode":
            entry["analysis"]["planned_seconds"] = 1234.0
            entry["analysis"]["slicer_seconds"] = 1200.0
            path.write_text(json.dumps(entry))
    again = servers({"bench": fake.port})
    answer = OctoRest(url=again.url, apikey=KEY).files_info("local", "sub/cone.gcode")
    assert answer["gcodeAnalysis"]["estimatedPrintTime"] == 1234.0
    assert answer["gcodeAnalysis"]["slicerEstimatedPrintTime"] == 1200.0


def test_numbers_too_big_for_a_float_are_left_out_not_answered_as_infinity(
    tmp_path: Path,
) -> None:
    huge = "9" * 400
    path = write(
        tmp_path,
        f";TIME:{huge}\n;Z:1.2.3\n;Z:{huge}\n"
        f";LAYER_CHANGE\nM73 P{huge} R5\nM83\nG1 X1 Y1 E1\nG1 X{huge} E1\n"
        f"G1 Xinf E1\nG1 Ynan Z{huge}\nG1 E{huge}\nT{huge * 20}\n",
    )
    found = analyse(path)
    summary = found.summary
    assert summary is not None
    assert summary.slicer_seconds is None
    assert summary.printing_area is None and summary.travel_area is None
    assert summary.filament == {}  # an infinite length is none
    assert found.marks.layers == [Layer(1, 4, 1.2)]  # ;Z:1.2.3 read as far as it goes
    assert found.marks.progress == [(5, None, 5)]
    json.dumps(summary.as_json(), allow_nan=False)  # what a JSON answer needs
    # The moves' time: none past a float's range, and the rest of the summary stands.
    planned = analyse(path, planned=True).summary
    assert planned is not None
    unplanned = replace(planned, planned_seconds=None, planned_limits_from=None, planned_points=())
    assert unplanned == summary
    json.dumps(planned.as_json(), allow_nan=False)
    beyond = write(tmp_path, f"G1 X{huge}\nG1 Y5\n", name="beyond.gcode")  # inf - inf: NaN
    beyond_summary = analyse(beyond, planned=True).summary
    assert beyond_summary is not None and beyond_summary.printing_area is None
    json.dumps(beyond_summary.as_json(), allow_nan=False)


def test_the_time_from_the_moves_stands_beside_the_slicers_never_in_its_place(
    tmp_path: Path,
) -> None:
    cone = analyse(CONE, planned=True).summary
    assert cone is not None
    assert cone.planned_seconds == estimate_file(CONE).seconds
    assert cone.slicer_seconds == 753  # PrusaSlicer's "12m 33s", kept
    octoprint = cone.gcode_analysis()
    assert octoprint["estimatedPrintTime"] == cone.planned_seconds
    assert octoprint["slicerEstimatedPrintTime"] == 753
    native = cone.as_json()
    assert native["estimatedPrintTime"] == cone.planned_seconds
    assert native["estimatedPrintTimeLimitsFrom"] == "the file's slicer settings"
    assert native["slicerEstimatedPrintTime"] == 753

    # Moves and no time comment (hand-written, Cura's flavours): ours alone.
    bare = write(tmp_path, "G28\nG1 X10 Y10 F3000\nG1 X50 E2\nG1 Y60 E2\n", name="bare.gcode")
    summary = analyse(bare, planned=True).summary
    assert summary is not None and summary.slicer_seconds is None
    assert summary.planned_seconds == estimate_file(bare).seconds
    assert summary.planned_seconds is not None and summary.planned_seconds > 0
    assert summary.planned_limits_from == "Marlin's defaults"
    assert summary.gcode_analysis()["estimatedPrintTime"] == summary.planned_seconds
    assert "slicerEstimatedPrintTime" not in summary.gcode_analysis()
    assert summary.as_json()["slicerEstimatedPrintTime"] is None

    # No moves: no figure, as OctoPrint leaves it out.
    still = analyse(write(tmp_path, "M104 S200\nM84\n", name="still.gcode"), planned=True)
    assert still.summary is not None and still.summary.planned_seconds is None
    assert "estimatedPrintTime" not in still.summary.gcode_analysis()
    assert still.summary.as_json()["estimatedPrintTime"] is None

    # A part of the file (a recovery's read) has no whole-job time.
    part = analyse(CONE, until_line=100, planned=True).summary
    assert part is not None and part.planned_seconds is None


def test_a_planned_file_keeps_its_time_at_a_few_lines_for_a_job_from_a_line() -> None:
    cone = analyse(CONE, planned=True).summary
    assert cone is not None and cone.planned_seconds is not None
    points = cone.planned_points
    assert 2 <= len(points) <= analysis.PLANNED_POINTS
    assert [line for line, _ in points] == sorted({line for line, _ in points})
    assert points[-1][1] == pytest.approx(cone.planned_seconds, abs=0.01)
    # From the start, all of it; past the last move, nothing; in between, less and less.
    assert cone.planned_after(0) == pytest.approx(cone.planned_seconds)
    assert cone.planned_after(points[-1][0]) == pytest.approx(0, abs=0.01)
    middle = points[len(points) // 2][0]
    assert cone.planned_seconds > cone.planned_after(middle) > cone.planned_after(middle + 500)
    # A summary kept before the points were has none: what a job from a line has left is
    # not known, and said so (None), never guessed.
    kept = cone.as_dict()
    del kept["planned_points"]
    older = FileSummary.from_dict(json.loads(json.dumps(kept)))
    assert older.planned_points == () and older.planned_after(middle) is None
    assert FileSummary.from_dict(json.loads(json.dumps(cone.as_dict()))) == cone


def test_a_files_rest_at_a_pace_keeps_the_heat_waits_still_ahead_as_planned() -> None:
    summary = analysis.FileSummary(
        planned_seconds=100.0, planned_heating=20.0, planned_points=((10, 30.0), (20, 100.0))
    )
    assert summary.planned_after(0, 0.5) == pytest.approx(80 * 0.5 + 20)  # the heat-up first
    assert summary.planned_after(10, 0.5) == pytest.approx(70 * 0.5)  # past it: moves only
    assert summary.planned_after(10) == pytest.approx(70.0)
