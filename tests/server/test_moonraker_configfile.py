"""What Klipper's clients read before they offer a control: ``configfile``'s limits (Mainsail
refuses a target above a heater's ``max_temp``; KlipperScreen's panels and Mobileraker's
models fail without ``max_temp``, ``control``, ``filament_diameter``, ``max_accel``...) and
the machine's memory in every ``notify_proc_stat_update`` (KlipperScreen reads it each
second). A real server on the fake controller, asked as those clients ask."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from websockets.sync import client as ws_client

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import KEY, Server, server_config

pytestmark = pytest.mark.timeout(90)

# What Mobileraker's ConfigExtruder and ConfigHeaterBed require, and KlipperScreen's
# panels index (job_status, main_menu, temperature, limits).
EXTRUDER_KEYS = {
    "nozzle_diameter",
    "max_extrude_only_distance",
    "min_temp",
    "min_extrude_temp",
    "max_temp",
    "filament_diameter",
    "max_extrude_only_velocity",
    "max_extrude_only_accel",
    "control",
}
PRINTER_KEYS = {"kinematics", "max_velocity", "max_accel", "square_corner_velocity"}


def test_a_loadouts_heads_have_their_limits_and_a_head_without_one_marlins(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--protocol", "hyrel")
    config = server_config(
        tmp_path, hyrel={"port": fake.port, "loadout": "wiki-two-heads", "protocol": "hyrel"}
    )
    server = servers({}, "--config", str(config))
    with server.client() as http:
        server.wait_ready("hyrel")
        query = {"objects": {"configfile": None}}
        found = http.post("/printer/objects/query", json=query).json()["result"]["status"]
    settings, text = found["configfile"]["settings"], found["configfile"]["config"]
    # The MK1-250 (the loadout's first head) to 250 °C, as Hyrel names it; the SDS-05,
    # which the head library gives no limit, to Marlin's default maximum.
    assert settings["extruder"]["max_temp"] == 250.0
    assert settings["extruder1"]["max_temp"] == 275.0
    for name in ("extruder", "extruder1"):
        assert settings[name].keys() >= EXTRUDER_KEYS
        assert settings[name]["min_extrude_temp"] < settings[name]["max_temp"]
        # KlipperScreen reads the text form and parses it.
        assert float(text[name]["filament_diameter"]) == 1.75
        assert text[name]["control"] == "pid"
    printer = settings["printer"]
    assert printer.keys() >= PRINTER_KEYS
    assert printer["max_velocity"] > 0 and printer["max_accel"] > 0
    assert float(text["printer"]["max_accel"]) == printer["max_accel"]
    # The bed, as the controller's reports show it: Marlin's default maximum.
    assert settings["heater_bed"]["max_temp"] == 150.0
    assert settings["heater_bed"]["min_temp"] == 5.0


def test_each_proc_stat_update_carries_the_machines_memory(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    url = f"ws://127.0.0.1:{server.port}/websocket"
    updates: list[dict[str, object]] = []
    with ws_client.connect(url, additional_headers={"X-Api-Key": KEY}) as socket:
        deadline = time.monotonic() + 5
        while len(updates) < 2 and time.monotonic() < deadline:
            message = json.loads(socket.recv(timeout=5))
            if message.get("method") == "notify_proc_stat_update":
                updates.append(message["params"][0])
    assert len(updates) == 2
    for update in updates:
        memory = update["system_memory"]
        assert isinstance(memory, dict)
        assert memory["total"] >= memory["available"] > 0
        assert memory["used"] == memory["total"] - memory["available"]
