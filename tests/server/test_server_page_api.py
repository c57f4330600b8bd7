"""The /v1 endpoints the page needed, asked of a real server: presets, the heaters and how
to set them, uploads without printing (folders, the lint's findings), a file's check, a
layer's moves and when the job printing it prints the layer, a stored file queued again or
resumed from a layer, a failed job's resume offer, and time-lapse videos (with ffmpeg, and
the sentence without it)."""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import CONE, run_server_cli
from tests.support.page import part_gcode
from tests.support.server import CAMERA, Server, camera_config, server_config, wait_for

pytestmark = pytest.mark.timeout(120)


@pytest.mark.slow
def test_presets_are_the_configurations_else_common_ones(
    servers: Callable[..., Server], tmp_path: Path
) -> None:
    config = server_config(tmp_path, a={"port": "fake"})
    config.write_text(config.read_text() + "[presets.ASA]\nhead = 255\nbed = 100\n")
    with servers({}, "--config", str(config)).client() as client:
        assert client.get("/v1/presets").json() == {
            "ASA": {"head": 255.0, "bed": 100.0, "chamber": None}
        }
    config.write_text('[printers.a]\nport = "fake"\n[presets.PLA]\nhead = 900\n')
    result = run_server_cli("--config", str(config), "--data-dir", str(tmp_path / "other"))
    assert result.returncode == 2  # a preset a heater could not reach: one sentence
    assert "presets.PLA.head" in result.stderr and "Traceback" not in result.stderr
    with servers({"b": "fake"}, "--data-dir", str(tmp_path / "third")).client() as client:
        defaults = client.get("/v1/presets").json()
    assert defaults["PLA"]["head"] == 210.0 and set(defaults) == {"PLA", "PETG", "ABS"}


@pytest.mark.slow
def test_each_heater_is_named_and_set_by_its_own_command(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--extruders", "2", "--chamber")
    config = server_config(
        tmp_path,
        hyrel={"port": "fake", "loadout": "wiki-two-heads", "protocol": "hyrel"},
        marlin={"port": fake.port},
    )
    with servers({}, "--config", str(config)).client() as client:
        wait_for(lambda: client.get("/v1/printers/marlin").json()["heaters"], what="reports")
        wait_for(lambda: client.get("/v1/printers/hyrel").json()["heaters"], what="reports")
        hyrel = client.get("/v1/printers/hyrel").json()["heaters"]
        marlin = {h["sensor"]: h for h in client.get("/v1/printers/marlin").json()["heaters"]}
    heads = [h for h in hyrel if h["kind"] == "head"]
    # The loadout's heads by slot and type, set by their address inside M-codes.
    assert [h["label"] for h in heads[:2]] == ["T1 · slot 2 · MK1-250", "T2 · slot 3 · SDS-05"]
    assert all(h["command"].startswith("M104 T") for h in heads)
    assert {"T0", "T1", "B", "C"} <= set(marlin) and "T" not in marlin  # T: the active one
    assert marlin["T1"]["command"] == "M104 T1 S{target}"
    assert marlin["B"]["command"] == "M140 S{target}" and marlin["C"]["label"] == "chamber"


def test_an_upload_without_printing_goes_in_its_folder_with_the_lints_findings(
    servers: Callable[..., Server],
) -> None:
    with servers({"a": "fake"}).client() as client:
        # What the check finds depends on what the printer is (Hyrel's code chart or not):
        # both checks below are made once it has said.
        wait_for(lambda: client.get("/v1/printers/a").json()["state"] == "ready", what="ready")
        assert client.post("/v1/folders", json={"path": "parts/brackets"}).status_code == 201
        assert client.post("/v1/folders", json={"path": "parts"}).status_code == 409
        assert client.post("/v1/folders", json={"path": "../out"}).status_code == 400
        answer = client.post(
            "/v1/files",
            data={"folder": "parts/brackets"},
            files={"file": ("bracket.gcode", "G28\nG1 X10 F3000\nG10\n")},
        )
        assert answer.status_code == 201, answer.text
        entry = answer.json()
        assert entry["path"] == "parts/brackets/bracket.gcode"
        assert entry["findings"] == ["warning: bracket.gcode:3: G10 is marked unsupported by Hyrel"]
        assert client.get("/v1/printers/a/jobs").json() == []  # stored, not queued
        assert client.get("/v1/folders").json() == ["parts", "parts/brackets"]
        check = client.get("/v1/files/parts/brackets/bracket.gcode/check?printer=a").json()
        assert check["printer"] == "a" and check["lines"] == 3
        assert check["findings"] == entry["findings"]
        assert client.get("/v1/files/nothing.gcode/check").status_code == 404
        refused = client.post("/v1/files", files={"file": ("bad.gcode", "G28\nM229 E1 D0\n")})
        assert refused.status_code == 400 and refused.json()["findings"]
        assert [f["name"] for f in client.get("/v1/files").json()] == ["bracket.gcode"]
        # A folder in use by a job is kept; an idle one goes with what it holds.
        assert client.delete("/v1/folders/parts").status_code == 204
        assert client.get("/v1/folders").json() == [] and client.get("/v1/files").json() == []
        assert client.delete("/v1/folders/parts").status_code == 404


def test_a_layers_moves_are_read_from_its_place_in_the_file(
    servers: Callable[..., Server],
) -> None:
    cone = CONE.read_text()
    lines = cone.splitlines()
    with servers({"a": "fake"}).client() as client:
        client.post("/v1/files", files={"file": ("cone.gcode", cone)})
        layer = client.get("/v1/files/cone.gcode/layers/2").json()
        assert (layer["layer"], layer["layers"], layer["z"]) == (2, 82, 0.65)
        assert lines[layer["first_line"] - 1] == ";LAYER_CHANGE"
        assert lines[layer["last_line"]] == ";LAYER_CHANGE"  # the next layer's
        moves = layer["moves"]
        assert len(moves) > 400 and sum(move[5] for move in moves) > 400
        for line, _x0, _y0, x1, _y1, _extrudes in moves[:50]:
            text = lines[line - 1]  # each move is the file's line it names
            assert text.startswith("G1") and f"X{x1:g}".rstrip("0") in text.replace("X.", "X0.")
            assert layer["first_line"] <= line <= layer["last_line"]
        area = layer["area"]
        assert all(area["minX"] <= m[3] <= area["maxX"] for m in moves if m[5])
        assert client.get("/v1/files/cone.gcode/layers/83").status_code == 404
        assert client.get("/v1/files/cone.gcode/layers/0").status_code == 400


@pytest.mark.slow
def test_a_layer_of_the_file_a_printer_prints_says_when_it_is_printed(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--time-scale", "20")  # the cone's 14 planned minutes in 42 s
    unknown = dict.fromkeys(("starts_in", "ends_in", "starts_at", "ends_at"))
    with servers({"a": fake.port}).client() as client:
        client.post("/v1/files", files={"file": ("cone.gcode", CONE.read_text())})
        idle = client.get("/v1/files/cone.gcode/layers/40?printer=a").json()
        assert {key: idle[key] for key in unknown} == unknown  # nothing prints it
        assert client.get("/v1/files/cone.gcode/layers/40?printer=b").status_code == 404
        job = client.post("/v1/printers/a/queue", json={"file": "cone.gcode"}).json()

        def planned() -> Any:
            running = client.get("/v1/printers/a").json()["job"]
            return running and running["time_left_from"] in ("plan", "estimate") and running

        running = wait_for(planned, what="the job's plan")
        left, now = running["time_left"], max(running["layer"], 1)
        current = client.get(f"/v1/files/cone.gcode/layers/{now}?printer=a").json()
        later = client.get(f"/v1/files/cone.gcode/layers/{now + 10}?printer=a&moves=false")
        later = later.json()
        client.delete(f"/v1/jobs/{job['id']}")
        assert len(current["moves"]) > 0 and later["moves"] is None  # not read: times only
        assert 0 <= current["starts_in"] < later["starts_in"] <= later["ends_in"] <= left
        assert current["starts_in"] <= current["ends_in"] <= later["starts_in"]
        starts = datetime.fromisoformat(later["starts_at"])
        assert starts.tzinfo is not None
        assert abs(starts.timestamp() - time.time() - later["starts_in"]) < 5
        wait_for(lambda: client.get(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled")
        ended = client.get("/v1/files/cone.gcode/layers/40?printer=a").json()
        assert {key: ended[key] for key in unknown} == unknown  # it no longer prints it


@pytest.mark.slow
def test_a_stored_file_is_queued_again_or_resumed_from_a_layer(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.003")
    text = part_gcode(layers=6, moves=100, thumbnail=False)
    server = servers({"a": fake.port}, "--automatic-transition")
    with server.client() as client:
        client.post("/v1/files", files={"file": ("part.gcode", text)})
        first = client.post("/v1/printers/a/queue", json={"file": "part.gcode"}).json()
        wait_for(lambda: client.get(f"/v1/jobs/{first['id']}").json()["state"] == "printing")
        time.sleep(0.6)
        client.delete(f"/v1/jobs/{first['id']}")
        cancelled = wait_for(
            lambda: (
                (j := client.get(f"/v1/jobs/{first['id']}").json())["state"] == "cancelled" and j
            )
        )
        before = len(fake.log_path.read_text().splitlines()) if fake.log_path else 0
        offer = client.get(f"/v1/jobs/{first['id']}/resume").json()
        assert offer["from_line"] == cancelled["last_line"] + 1
        assert offer["layer_command"] == (
            f"hyrel-send part.gcode --port {fake.port} --from-layer {offer['from_layer']}"
        )
        layer = offer["from_layer"]
        resumed = client.post(
            "/v1/printers/a/queue", json={"file": "part.gcode", "from_layer": layer}
        ).json()
        assert resumed["from_line"] is not None and resumed["path"] == "part.gcode"
        wait_for(
            lambda: client.get(f"/v1/jobs/{resumed['id']}").json()["state"] == "completed",
            60,
        )
        assert client.get(f"/v1/jobs/{resumed['id']}/resume").status_code == 409
        bad = client.post("/v1/printers/a/queue", json={"file": "part.gcode", "from_layer": 9})
        assert bad.status_code == 400 and "6 layers" in bad.json()["error"]
        assert client.post("/v1/printers/a/queue", json={"file": "none.gcode"}).status_code == 404
    # The resumed job ran from its layer's start: that layer's Z, none of the earlier ones.
    after = fake.log_path.read_text().splitlines()[before:] if fake.log_path else []
    z_moves = [c for c in after if c.startswith("G1 Z") and "F600" in c]
    assert z_moves[0] == f"G1 Z{round(0.2 * layer, 2)} F600"
    assert f"G1 Z{round(0.2 * (layer - 1), 2)} F600" not in after


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="needs ffmpeg (.ci/run installs it)")
@pytest.mark.slow
def test_a_jobs_layer_snapshots_make_a_timelapse_video(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.006")
    config = camera_config(tmp_path, {"cam": fake.port}, cam=CAMERA)
    with servers({}, "--config", str(config)).client() as client:
        listed = client.get("/v1/printers/cam/timelapses").json()
        assert listed["ffmpeg"] and listed["missing"] is None and listed["videos"] == []
        job = client.post(
            "/v1/printers/cam/jobs", files={"file": ("p.gcode", part_gcode(5, 60, False))}
        ).json()
        wait_for(lambda: client.get(f"/v1/jobs/{job['id']}").json()["state"] == "completed")
        layers, snapshots = f"-job{job['id']}-layer", "/v1/printers/cam/snapshots"
        wait_for(
            lambda: sum(layers in s["file"] for s in client.get(snapshots).json()) >= 3,
            what="the layer snapshots",
        )
        made = client.post("/v1/printers/cam/timelapses", json={"job": job["id"]})
        assert made.status_code == 201, made.text
        video = client.get(made.json()["url"])
        assert video.status_code == 200 and video.content[4:8] == b"ftyp"  # an MP4
        assert client.get("/v1/printers/cam/timelapses").json()["videos"][0] == made.json()
        none = client.post("/v1/printers/cam/timelapses", json={"job": 99})
        assert none.status_code == 409 and "0 layer snapshots" in none.json()["error"]


def test_without_ffmpeg_the_timelapse_says_so_plainly(
    servers: Callable[..., Server], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bare = tmp_path / "bin"
    bare.mkdir()
    python = Path(os.path.realpath(shutil.which("python3") or "/usr/bin/python3"))
    (bare / "python3").symlink_to(python)
    monkeypatch.setenv("PATH", str(bare))  # the server's: no ffmpeg on it
    config = camera_config(tmp_path, {"cam": "fake"}, cam=CAMERA)
    with servers({}, "--config", str(config)).client() as client:
        listed = client.get("/v1/printers/cam/timelapses").json()
        assert listed["ffmpeg"] is None and "ffmpeg is not installed" in listed["missing"]
        made = client.post("/v1/printers/cam/timelapses", json={"job": 1})
        assert made.status_code == 501 and "apt install ffmpeg" in made.json()["error"]
