"""Klipper's commands on Moonraker's face, as Klipper's clients send them, read back from
the fake controller's own log and heaters: ``M104 T<n>`` is Klipper's extruder n (a Hyrel
head by its address), ``SDCARD_RESET_FILE`` clears a print that ended, an extended command
the server does not do is answered in Klipper's words and reaches no controller, and a
cancel with no job is ok."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed
from tests.support.server import Server, gcode, server_config, wait_for

pytestmark = pytest.mark.timeout(90)


def v4_loadout(tmp_path: Path) -> Path:
    """Two heads on Repetrel v4 addressing: tools T0 and T1, addresses T11 and T12 (so a
    head's address is not its tool number)."""
    path = tmp_path / "two-heads-v4.toml"
    path.write_text(
        'machine = "hydra-16a-v4"\n'
        '[[heads]]\nslot = 1\nhead = "MK1-250"\n'
        '[[heads]]\nslot = 2\nhead = "SDS-05"\n'
    )
    return path


def script(http: httpx.Client, line: str) -> httpx.Response:
    return http.post("/printer/gcode/script", json={"script": line})


def targets(fake: BuiltInFake) -> dict[str, float]:
    return {name: float(t) for name, (_, t) in fake.request("status")["temperatures"].items()}


def responses(http: httpx.Client) -> list[str]:
    store = http.get("/server/gcode_store").json()["result"]["gcode_store"]
    return [item["message"] for item in store if item["type"] == "response"]


def print_stats(http: httpx.Client) -> dict[str, Any]:
    query = http.get("/printer/objects/query", params={"print_stats": "state,filename"})
    stats: dict[str, Any] = query.json()["result"]["status"]["print_stats"]
    return stats


@pytest.mark.parametrize(
    ("protocol", "first", "second"),
    [("hyrel", "T11", "T12"), ("reprap", "T0", "T1")],
)
def test_klippers_m104_t_is_its_extruder_set_by_the_heads_own_command(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
    protocol: str,
    first: str,
    second: str,
) -> None:
    """KlipperScreen and Home Assistant send ``M104 T<index> S..``: Klipper's extruder
    index, as SET_HEATER_TEMPERATURE names it. On Hyrel's link the head's address; on the
    RepRap link its tool."""
    fake = bench("--protocol", protocol, "--extruders", "2")
    settings = {"port": fake.port, "loadout": str(v4_loadout(tmp_path)), "protocol": protocol}
    server = servers({}, "--config", str(server_config(tmp_path, two=settings)))
    with server.client() as http:
        server.wait_ready("two")
        for line in ("M104 T1 S190", "M104 S185", "m109 t1 s60", "M104 T7 S0"):
            assert script(http, line).status_code == 200, line
        missing = script(http, "M104 T7 S200")
        assert missing.status_code == 400
        assert missing.json()["error"]["message"] == "Extruder not configured"
        assert "!! Extruder not configured" in responses(http)
    fake.request("status")
    ran = executed(fake.log_path)
    sent = [line for line in ran if line.startswith(("M104", "M109"))]
    assert sent == [f"M104 {second} S190", f"M104 {first} S185", f"M109 {second} S60"]
    if protocol == "reprap":  # the fake's hotends by their tool (T0 reads as T)
        assert targets(fake)["T"] == 185 and targets(fake)["T1"] == 60


@pytest.mark.slow
def test_sdcard_reset_file_clears_a_print_that_ended_and_not_one_running(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    """Mainsail's, Fluidd's and KlipperScreen's "clear" after a print: print_stats back to
    standby with no file, the controller not asked; refused while a print runs."""
    fake = bench("--move-time", "0.002")
    server = servers({"bench": fake.port})
    with server.client() as http:
        server.wait_ready("bench")
        upload = http.post("/server/files/upload", files={"file": ("long.gcode", gcode(20000))})
        assert upload.status_code == 201
        assert http.post("/printer/print/start", params={"filename": "long.gcode"}).is_success
        wait_for(lambda: print_stats(http)["state"] == "printing", what="printing")
        busy = script(http, "SDCARD_RESET_FILE")
        assert busy.status_code == 400
        message = "SDCARD_RESET_FILE cannot be run while printing: cancel the print first"
        assert busy.json()["error"]["message"] == message
        assert print_stats(http)["state"] == "printing"
        assert script(http, "CANCEL_PRINT").status_code == 200
        wait_for(lambda: print_stats(http)["state"] == "cancelled", what="cancelled")
        assert print_stats(http)["filename"] == "long.gcode"
        assert script(http, "sdcard_reset_file").status_code == 200
        assert print_stats(http) == {"state": "standby", "filename": ""}
    assert not [line for line in executed(fake.log_path) if "SDCARD" in line.upper()]


@pytest.mark.slow
def test_an_extended_command_the_server_does_not_do_is_unknown_as_in_klipper(
    printer: tuple[Server, BuiltInFake],
) -> None:
    """Klipper answers a command it lacks with ok and a response saying so
    (klippy/gcode.py), so a babystep or a limit does not look done; G-code, Hyrel's own
    M-codes too, goes to the controller."""
    server, fake = printer
    with server.client() as http:
        for line in ("FOOBAR", "SET_GCODE_OFFSET Z_ADJUST=0.05 MOVE=1", "M220 S150", "M221 S95"):
            answer = script(http, line)
            assert answer.status_code == 200 and answer.json()["result"] == "ok", line
        said = responses(http)
        assert '// Unknown command:"FOOBAR"' in said
        assert '// Unknown command:"SET_GCODE_OFFSET"' in said
        assert script(http, "HELP").status_code == 200
        helped = responses(http)[len(said) :]
        assert helped[0] == "// Available extended commands:"
        assert any(line.startswith("// SDCARD_RESET_FILE: ") for line in helped)
        listed = http.get("/printer/gcode/help").json()["result"]
        assert "SDCARD_RESET_FILE" in listed and "FOOBAR" not in listed
        # Klipper's gcode object, which Mainsail's console completes commands from.
        query = {"objects": {"gcode": ["commands"]}}
        found = http.post("/printer/objects/query", json=query).json()["result"]["status"]
        commands = found["gcode"]["commands"]
        assert commands["SDCARD_RESET_FILE"] == {"help": listed["SDCARD_RESET_FILE"]}
        assert commands.keys() == listed.keys()
    fake.request("status")
    ran = executed(fake.log_path)
    assert "M220 S150" in ran and "M221 S95" in ran
    assert not [line for line in ran if "FOOBAR" in line or "SET_GCODE_OFFSET" in line]


def test_a_cancel_with_no_job_is_ok_as_in_klipper(printer: tuple[Server, BuiltInFake]) -> None:
    """Fluidd cancels at a job's end too: Klipper says ``action:cancel`` and answers ok
    (klippy/extras/pause_resume.py), with no job to cancel."""
    server, _ = printer
    with server.client() as http:
        answer = http.post("/printer/print/cancel")
        assert answer.status_code == 200 and answer.json()["result"] == "ok"
        assert script(http, "CANCEL_PRINT").status_code == 200
        assert responses(http).count("// action:cancel") == 2
        assert print_stats(http)["state"] == "standby"
