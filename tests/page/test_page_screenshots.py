"""The screenshots in docs/: the farm view and a printer mid-print, at a desk's width and a
phone's, taken by the suite from a real server with four printers (one printing with its
slicer's preview, one paused, one idle, one whose port is gone)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.page import Browser, needs_browser, part_gcode
from tests.support.paths import ROOT
from tests.support.server import CAMERA, Server, wait_for

pytestmark = [needs_browser, pytest.mark.timeout(180)]
DOCS = ROOT / "docs" / "screenshots"
PHONE = 412  # px: a common phone's CSS width


def test_screenshots_of_the_farm_and_a_printer_mid_print(
    browser: Browser,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
) -> None:
    fakes = {
        name: bench("--move-time", "0.05", "--heat-rate", "30", "--extruders", "2")
        for name in ("hydra-1", "hydra-2", "hydra-3")
    }
    config = tmp_path / "server.toml"
    text = "".join(f'[printers.{name}]\nport = "{fake.port}"\n' for name, fake in fakes.items())
    text += f"camera = {json.dumps(CAMERA)}\n"  # hydra-3's
    text += '[printers.hydra-4]\nport = "/dev/ttyUSB7"\n'  # not plugged in
    config.write_text(text)
    server = servers({}, "--config", str(config))
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/hydra-1").json()["state"] == "ready")
        for name, heat in (("hydra-1", (215, 60)), ("hydra-2", (240, 80)), ("hydra-3", (0, 0))):
            wait_for(
                lambda name=name: client.get(f"/v1/printers/{name}").json()["state"] == "ready"
            )
            client.post(f"/v1/printers/{name}/command", json={"command": f"M104 T0 S{heat[0]}"})
            client.post(f"/v1/printers/{name}/command", json={"command": f"M140 S{heat[1]}"})
        part = part_gcode(layers=40, moves=160)
        for name, file in (("hydra-1", "bracket.gcode"), ("hydra-2", "housing.gcode")):
            answer = client.post(f"/v1/printers/{name}/jobs", files={"file": (file, part)})
            assert answer.status_code == 201, answer.text
        wait_for(lambda: client.get("/v1/printers/hydra-2").json()["state"] == "printing")
        wait_for(
            lambda: (client.get("/v1/printers/hydra-2").json()["job"] or {}).get("layer", 0) >= 2
        )
        assert client.post("/v1/printers/hydra-2/pause").status_code == 204
        # hydra-3 has printed something before: its history, and a held queue.
        done = client.post(
            "/v1/printers/hydra-3/jobs", files={"file": ("clip.gcode", part_gcode(3, 20))}
        ).json()
        wait_for(lambda: client.get(f"/v1/jobs/{done['id']}").json()["state"] == "completed", 60)

    DOCS.mkdir(parents=True, exist_ok=True)
    browser.open(f"{server.url}/")
    browser.wait(lambda: len(browser.all(".tile")) == 4, "four tiles")
    browser.wait(lambda: browser.text("[data-printer=hydra-2] .badge") == "paused", "paused")
    browser.wait(lambda: browser.text("[data-printer=hydra-4] .badge").startswith("offline"))
    browser.wait(
        lambda: browser.driver.execute_script(
            "return [...document.querySelectorAll('img.thumb')].every(i => i.naturalWidth > 0)"
            " && document.querySelectorAll('img.thumb').length == 2"
        ),
        "both previews",
    )
    browser.screenshot(DOCS / "farm-desktop.png", 1400, 700)
    browser.screenshot(DOCS / "farm-phone.png", PHONE, 900)

    browser.driver.set_window_size(1400, 1000)
    browser.driver.get(f"{server.url}/printers/hydra-1")
    browser.wait(lambda: browser.text(".printer-head .badge") == "printing", "printing")
    browser.wait(lambda: "Layer" in browser.text("#panel-job"), "the job panel")
    browser.wait(
        lambda: int(browser.css("#panel-job canvas").get_attribute("data-acked") or 0) > 20,
        "the layer view drawing what was acknowledged",
    )
    browser.wait(
        lambda: browser.text("#panel-job .layer-mark").startswith("printing now"),
        "the layer's mark: when the job is done with it",
    )
    browser.wait(lambda: browser.all("#panel-files img"), "the files' previews")
    browser.wait(lambda: browser.all("#panel-temperatures canvas"), "the chart")
    browser.screenshot(DOCS / "printer-desktop.png", 1400, 1000)
    browser.screenshot(DOCS / "printer-phone.png", PHONE, 900)
    for name in ("farm-desktop", "farm-phone", "printer-desktop", "printer-phone"):
        assert (DOCS / f"{name}.png").stat().st_size > 20_000, name  # a page, not a blank
