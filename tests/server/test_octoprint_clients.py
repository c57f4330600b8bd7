"""OctoPrint's REST face, as clients that other projects wrote use it: ``octoprint-cli``
(its own command, a real process) and ``octorest``, against a real hyrel-server process
and the fake controller, whose executed log says what the printer did."""

from __future__ import annotations

import datetime
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import serial
from octorest import OctoRest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.gcode.estimate import estimate_file
from tests.support.helpers import executed, wait_for_log
from tests.support.paths import DATA
from tests.support.server import KEY, Server, gcode, wait_for

pytestmark = pytest.mark.timeout(180)

CONE = DATA / "cone-prusaslicer.gcode"


def octoprint_cli(config: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """octoprint-cli as a person runs it: its own command, its own config file."""
    command = [str(Path(sys.executable).parent / "octoprint-cli"), "-c", str(config), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=60)


def analysed(
    info: subprocess.CompletedProcess[str],
) -> subprocess.CompletedProcess[str] | None:
    """octoprint-cli's file info once it shows the file's estimate (None before)."""
    return info if "Estimated Print Time" in info.stdout else None


def cli_config(tmp_path: Path, server: Server) -> Path:
    config = tmp_path / "octoprint-cli.ini"
    config.write_text(
        f"[server]\nServerAddress = {server.url}\nApiKey = {KEY}\n"
        "[preferences]\nUpdateCheck = false\nFormattedText = false\n"
        "[print]\nMaxExtruderTemp = 250\nMaxBedTemp = 100\n"
    )
    return config


def heater_targets(fake: BuiltInFake) -> dict[str, Any]:
    readings: dict[str, Any] = fake.request("status")["temperatures"]
    return readings


@pytest.mark.slow
def test_octoprint_cli_status_files_print_temp_and_connection(
    tmp_path: Path, bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.01")
    server = servers({"bench": fake.port})
    config = cli_config(tmp_path, server)
    with server.client() as client:
        wait_for(lambda: client.get("/api/job").json()["state"] == "Operational", what="ready")
        # A file in a folder, with PrusaSlicer's estimate in it.
        upload = client.post(
            "/api/files/local",
            data={"path": "sub"},
            files={"file": ("cone.gcode", CONE.read_bytes())},
        )
        assert upload.status_code == 201, upload.text
        job = "G28\n" + "".join(f"G1 X{i / 10:.1f} F3000\n" for i in range(600))
        client.post("/api/files/local", files={"file": ("part.gcode", job.encode())})

    version = octoprint_cli(config, "version")
    assert version.returncode == 0 and version.stdout.startswith("OctoPrint v1.11"), version
    listed = octoprint_cli(config, "files", "list")
    assert listed.returncode == 0, listed
    assert "sub" in listed.stdout and "part.gcode" in listed.stdout
    assert "Free space" in listed.stdout
    in_folder = octoprint_cli(config, "files", "list", "-p", "sub")
    assert in_folder.returncode == 0 and "cone.gcode" in in_folder.stdout, in_folder
    # The estimate is worked out once a listing showed the file (as OctoPrint analyses an
    # upload in the background): asked again until it is there.
    info = wait_for(
        lambda: analysed(octoprint_cli(config, "files", "info", "sub/cone.gcode")),
        what="cone.gcode's estimate",
    )
    assert info.returncode == 0, info
    assert "Path: sub/cone.gcode" in info.stdout and "Type: machinecode" in info.stdout
    # The time from the moves, as octoprint-cli writes it (PrusaSlicer's 12m 33s is beside it).
    planned = str(datetime.timedelta(seconds=estimate_file(CONE).seconds)).split(".")[0]
    assert f"Estimated Print Time: {planned}\n" in info.stdout
    assert "Successful Prints: 0" in info.stdout
    # A file with moves and no time comment has an estimate all the same.
    bare = wait_for(
        lambda: analysed(octoprint_cli(config, "files", "info", "part.gcode")),
        what="part.gcode's estimate",
    )
    assert bare.returncode == 0 and "Estimated Print Time: 0:00:" in bare.stdout, bare

    temp = octoprint_cli(config, "temp", "extruder", "205")
    assert temp.returncode == 0 and "Extruder temp set to 205" in temp.stdout, temp
    bed = octoprint_cli(config, "temp", "bed", "55")
    assert bed.returncode == 0 and "Bed temp set to 55" in bed.stdout, bed
    targets = heater_targets(fake)
    assert targets["T"][1] == 205 and targets["B"][1] == 55
    status = octoprint_cli(config, "temp", "status")
    assert "Extruder Target: 205" in status.stdout and "Bed Target: 55" in status.stdout, status
    octoprint_cli(config, "temp", "extruder", "0")
    octoprint_cli(config, "temp", "bed", "0")

    selected = octoprint_cli(config, "print", "select", "part.gcode")
    assert selected.returncode == 0 and "part.gcode has been loaded" in selected.stdout
    loaded = octoprint_cli(config, "print", "status")
    assert "Loaded File: part.gcode" in loaded.stdout, loaded
    # The selected file's estimate, from its moves (it was "unavailable": no slicer's comment).
    assert re.search(r"Estimated Print Time: \d\d:\d\d\n", loaded.stdout), loaded
    started = octoprint_cli(config, "print", "start")
    assert started.returncode == 0 and "Starting print" in started.stdout, started
    with server.client() as client:
        wait_for(lambda: client.get("/api/job").json()["state"] == "Printing", what="printing")
        printing = octoprint_cli(config, "print", "status")
        assert printing.stdout.startswith("Printing") and "File: part.gcode" in printing.stdout
        assert octoprint_cli(config, "print", "pause").returncode == 0
        wait_for(lambda: client.get("/api/job").json()["state"] == "Paused", what="paused")
        paused_at = len(executed(fake.log_path))
        assert octoprint_cli(config, "print", "status").stdout.startswith("Paused")
        assert octoprint_cli(config, "print", "resume").returncode == 0
        wait_for(lambda: len(executed(fake.log_path)) > paused_at + 20, what="resumed")
        cancelled = octoprint_cli(config, "print", "cancel")
        assert cancelled.returncode == 0 and "cancelling" in cancelled.stdout, cancelled
        wait_for(lambda: client.get("/api/job").json()["state"].startswith("Operational"))
        assert octoprint_cli(config, "print", "cancel").returncode == 1  # nothing runs
    ran = executed(fake.log_path)
    body = [line for line in ran if line.startswith("G1 X")]
    assert len(body) == len(set(body))  # nothing twice (the X values are all different)
    assert ran[-4:] == ["G91", "G0 Z10", "G90", "M84"]  # the safe stop, last

    # OctoPrint's disconnect frees the port until connect.
    gone = octoprint_cli(config, "connection", "disconnect")
    assert gone.returncode == 0 and "Printer disconnected" in gone.stdout, gone
    serial.Serial(fake.port, 115200, exclusive=True).close()  # free once it says so
    with server.client() as client:
        wait_for(lambda: client.get("/api/connection").json()["current"]["state"] == "Offline")
        assert client.get("/api/printer").status_code == 409
        back = octoprint_cli(config, "connection", "connect")
        assert back.returncode == 0, back
        wait_for(lambda: client.get("/api/printer").status_code == 200, what="connected again")


@pytest.mark.slow
def test_octorest_calls_as_against_octoprint(
    tmp_path: Path, bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.01")
    server = servers({"bench": fake.port})
    rest = OctoRest(url=server.url, apikey=KEY)
    assert rest.version["text"].startswith("OctoPrint")
    wait_for(lambda: rest.state() == "Operational", what="ready")
    part = tmp_path / "part.gcode"
    part.write_text("G28\n" + gcode(400)[5:])
    uploaded = rest.upload(str(part))
    assert uploaded["done"] and uploaded["files"]["local"]["path"] == "part.gcode"
    local = rest.files("local")
    assert [f["name"] for f in local["files"]] == ["part.gcode"]
    entry = local["files"][0]
    assert entry["hash"] and entry["typePath"] == ["machinecode", "gcode"]
    refs = rest.files("part.gcode")["refs"]
    assert refs["download"].endswith("/downloads/files/local/part.gcode")
    download = httpx.get(
        f"{server.url}/downloads/files/local/part.gcode",
        headers={"X-Api-Key": KEY, "Range": "bytes=0-3"},
    )
    assert download.status_code == 206 and download.text == "G28\n"

    profiles = rest.printer_profiles()["profiles"]
    assert profiles["bench"]["extruder"]["count"] == 1
    settings = rest.settings()
    assert (
        settings["plugins"]["discovery"]["upnpUuid"]
        == rest.settings()["plugins"]["discovery"]["upnpUuid"]
    )
    assert rest.system_commands() == {"core": [], "custom": []}

    # Heaters, the print head, the tool: what the fake executed.
    rest.tool_target(210)
    rest.bed_target(60)
    rest.chamber_target(40)
    rest.home(["x", "y"])
    rest.jog(x=10, y=-5)
    rest.feedrate(120)
    rest.flowrate(0.95)
    rest.extrude(2)
    rest.gcode("M400")
    assert fake.log_path is not None
    wait_for_log(fake.log_path, "M400")  # its "ok" can come before the fake's log is written
    ran = executed(fake.log_path)
    for expected in (
        "M104 S210",
        "M140 S60",
        "M141 S40",
        "G28 X0 Y0",
        "G0 X10 Y-5 F6000",
        "M220 S120",
        "M221 S95",
        "G1 E2 F300",
        "M400",
    ):
        assert expected in ran, (expected, ran[-30:])
    printer = rest.printer(history=True, exclude=["sd"])
    assert "sd" not in printer and printer["state"]["flags"]["ready"] is True
    assert printer["temperature"]["tool0"]["target"] == 210
    assert printer["temperature"]["history"], "no temperature history"
    assert set(rest.printer(exclude=["temperature", "sd"])) == {"state"}
    assert rest.tool()["tool0"]["target"] == 210 and rest.bed()["bed"]["target"] == 60
    rest.tool_target(0)
    rest.bed_target(0)
    rest.chamber_target(0)
    with pytest.raises(RuntimeError, match="409"):
        rest.tool_target({"tool3": 200})  # no such tool on this printer

    # A job: select, start, pause, restart (from the start), cancel.
    rest.select("part.gcode")
    assert rest.job_info()["job"]["file"]["name"] == "part.gcode"
    rest.start()
    wait_for(lambda: rest.state() == "Printing", what="printing")
    rest.pause()
    wait_for(lambda: rest.state() == "Paused", what="paused")
    rest.restart()
    wait_for(lambda: rest.state() == "Printing", what="restarted")
    rest.cancel()
    wait_for(lambda: rest.state().startswith("Operational"), what="cancelled")
    assert rest.job_info()["job"]["file"]["name"] == "part.gcode"
    ran = executed(fake.log_path)
    assert ran.count("G28") == 2  # the job twice: restarted from its start
    first, second = [i for i, line in enumerate(ran) if line == "G28"]
    assert "G0 Z10" in ran[first:second]  # after the first run's safe stop

    # Files: folders, copy, move, delete.
    rest.copy("part.gcode", "copy.gcode")
    httpx.post(
        f"{server.url}/api/files/local",
        headers={"X-Api-Key": KEY},
        data={"foldername": "parts"},
    ).raise_for_status()
    rest.move("copy.gcode", "parts")
    assert rest.files("parts")["children"][0]["path"] == "parts/copy.gcode"
    rest.delete("parts")
    assert [f["name"] for f in rest.files("local")["files"]] == ["part.gcode"]
