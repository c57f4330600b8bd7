"""Live status as Klipper's (issue 50), for real: a hyrel-server process on the fake
controller, a websocket client (moonraker-api) and plain HTTP. An idle printer's
subscription hears Klipper's cadence (its clock moves: the toolhead's
estimated_print_time, the eventtime); G-code over ``printer.gcode.script`` answers as
Klipper does (M105 in ``heaters.py``'s words, no ``ok``); and a target set is read back
by the time the call returns, on every face that reads it (Moonraker's objects,
OctoPrint's ``/api/printer``, ``/v1``), on the RepRap link and Hyrel's."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.server.test_moonraker import Heard, client, connected, until
from tests.support.server import KEY, Server, gcode, server_config, wait_for

pytestmark = pytest.mark.timeout(90)

# Klipper's M105 answer (klippy/extras/heaters.py, _get_temp): by G-code id, sorted.
KLIPPERS_M105 = re.compile(r"^B:\d+\.\d /\d+\.\d T0:\d+\.\d /\d+\.\d T1:\d+\.\d /\d+\.\d$")


@pytest.fixture(params=["reprap", "hyrel"])
def printer(
    request: pytest.FixtureRequest,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
) -> Server:
    """A server on a two-hotend fake controller of each link."""
    fake = bench("--extruders", "2", "--protocol", request.param)
    settings = {"port": fake.port, "protocol": request.param}
    server = servers({}, "--config", str(server_config(tmp_path, bench=settings)))
    server.wait_ready("bench")
    with server.client() as http:  # its first report came: the heaters are read
        wait_for(lambda: http.get("/v1/printers/bench").json()["temperatures"], what="a report")
    return server


@pytest.mark.slow
def test_an_idle_printers_subscription_hears_klippers_clock_four_times_a_second(
    printer: Server,
) -> None:
    heard = Heard()

    async def run() -> None:
        async with connected(client(printer, heard)) as moonraker:
            first = await moonraker.call_method(
                "printer.objects.subscribe",
                objects={"toolhead": None, "extruder": ["target"], "print_stats": ["state"]},
            )
            await asyncio.sleep(3)
        updates = [d for m, d in heard.notifications if m == "notify_status_update"]
        assert len(updates) >= 8, updates
        times = [first["eventtime"], *(eventtime for _, eventtime in updates)]
        assert times == sorted(times) and len(set(times)) == len(times)
        clock = [s["toolhead"]["estimated_print_time"] for s, _ in updates]
        assert clock == sorted(clock) and clock[-1] - clock[0] > 1.5
        assert clock[0] > first["status"]["toolhead"]["estimated_print_time"]
        # Only what changed: the idle extruder's target and print_stats never come again.
        assert not any("extruder" in s or "print_stats" in s for s, _ in updates)

    asyncio.run(run())


@pytest.mark.slow
def test_gcode_answers_as_klipper_does_no_ok_and_m105_in_its_words(printer: Server) -> None:
    heard = Heard()

    async def run() -> None:
        async with connected(client(printer, heard)) as moonraker:
            assert await moonraker.call_method("printer.gcode.script", script="M104 S0") == "ok"
            assert await moonraker.call_method("printer.gcode.script", script="M105") == "ok"
            await until(lambda: responses(heard), "M105's answer")
            await asyncio.sleep(0.3)  # anything said late comes too
        said = responses(heard)
        assert len(said) == 1 and KLIPPERS_M105.match(said[0]), said

    asyncio.run(run())
    with printer.client() as http:  # and the console's store keeps the same
        store = http.get("/server/gcode_store").json()["result"]["gcode_store"]
    kept = [e["message"] for e in store if e["type"] == "response"]
    assert len(kept) == 1 and KLIPPERS_M105.match(kept[0]), kept


def responses(heard: Heard) -> list[str]:
    return [d[0] for m, d in heard.notifications if m == "notify_gcode_response"]


@pytest.mark.slow
def test_a_target_reads_back_as_the_call_returns_on_every_face(printer: Server) -> None:
    heard = Heard()

    async def run() -> None:
        async with connected(client(printer, heard)) as moonraker:
            script = "M104 S205\nM140 S55"
            assert await moonraker.call_method("printer.gcode.script", script=script) == "ok"
            found = await moonraker.call_method(
                "printer.objects.query", objects={"extruder": ["target"], "heater_bed": None}
            )
            assert found["status"]["extruder"]["target"] == 205
            assert found["status"]["heater_bed"]["target"] == 55
            # The second hotend by Klipper's name: its own address (T1), the first kept.
            script = "SET_HEATER_TEMPERATURE HEATER=extruder1 TARGET=150"
            assert await moonraker.call_method("printer.gcode.script", script=script) == "ok"
            found = await moonraker.call_method(
                "printer.objects.query", objects={"extruder": ["target"], "extruder1": ["target"]}
            )
            assert found["status"] == {"extruder": {"target": 205}, "extruder1": {"target": 150}}
            # Klipper's own command, over HTTP: the same.
            async with httpx.AsyncClient(base_url=printer.url, headers={"X-Api-Key": KEY}) as http:
                set_it = {"script": "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=0"}
                assert (await http.post("/printer/gcode/script", json=set_it)).status_code == 200
                query = await http.get("/printer/objects/query?extruder=target")
                assert query.json()["result"]["status"]["extruder"]["target"] == 0

    asyncio.run(run())
    with printer.client() as http:
        # OctoPrint's face: the target it set, read back at once.
        tool = http.post("/api/printer/tool", json={"command": "target", "targets": {"tool0": 190}})
        assert tool.status_code == 204, tool.text
        bed = http.post("/api/printer/bed", json={"command": "target", "target": 45})
        assert bed.status_code == 204, bed.text
        temperature = http.get("/api/printer").json()["temperature"]
        assert temperature["tool0"]["target"] == 190 and temperature["bed"]["target"] == 45
        # /v1: a command's target in the printer's temperatures as its answer comes.
        done = http.post("/v1/printers/bench/command", json={"command": "M140 S0"})
        assert done.status_code == 200, done.text
        readings = http.get("/v1/printers/bench").json()["temperatures"]
        assert readings["B"]["target"] == 0


@pytest.mark.slow
def test_homed_axes_and_factors_read_back_as_the_commands_ran(
    printer: Server, request: pytest.FixtureRequest
) -> None:
    """``toolhead.homed_axes`` (what enables a client's jog buttons) and ``gcode_move``'s
    factors come from the commands the controller ran: a homing names its axes (Marlin's
    bare G28 homes all three; Hyrel's homes only what it names), motors off forgets them,
    Marlin's M220/M221 set the factors (Hyrel's M221 is a head's flow set-up)."""
    hyrel = request.node.callspec.params["printer"] == "hyrel"
    wanted = {"objects": {"toolhead": ["homed_axes"], "gcode_move": None}}

    def script(http: httpx.Client, line: str) -> dict[str, object]:
        answer = http.post("/printer/gcode/script", json={"script": line})
        assert answer.status_code == 200, answer.text
        status: dict[str, object] = http.post("/printer/objects/query", json=wanted).json()[
            "result"
        ]["status"]
        return status

    def homed(status: dict[str, object]) -> object:
        return status["toolhead"]["homed_axes"]  # type: ignore[index]

    with printer.client() as http:
        first = http.post("/printer/objects/query", json=wanted).json()["result"]["status"]
        assert homed(first) == ""
        assert homed(script(http, "G28 X0 Y0")) == "xy"
        assert homed(script(http, "G28 Z0")) == "xyz"
        assert homed(script(http, "M84 S120")) == "xyz"  # Marlin's idle timeout only
        assert homed(script(http, "M18 X")) == "yz"
        assert homed(script(http, "M84")) == ""
        # A job starts from nothing homed; on the RepRap link its own G28 is read as it
        # runs (its ok says it ran), on Hyrel's not (its ack says only that it arrived).
        assert homed(script(http, "G28 X0 Y0")) == "xy"
        assert http.post("/v1/files", files={"file": ("j.gcode", gcode(50))}).status_code == 201
        assert http.post("/printer/print/start", params={"filename": "j.gcode"}).status_code == 200
        wait_for(
            lambda: (
                http.get("/printer/objects/query?print_stats=state").json()["result"]["status"][
                    "print_stats"
                ]["state"]
                == "complete"
            ),
            what="the job's end",
        )
        after_job = http.post("/printer/objects/query", json=wanted).json()["result"]["status"]
        assert homed(after_job) == ("" if hyrel else "xyz")
        if not hyrel:
            assert homed(script(http, "M84")) == ""
            assert homed(script(http, "G28")) == "xyz"
            moved = script(http, "M220 S150")["gcode_move"]
            assert moved["speed_factor"] == 1.5  # type: ignore[index]
            moved = script(http, "M221 S95")["gcode_move"]
            assert moved["extrude_factor"] == 0.95  # type: ignore[index]
