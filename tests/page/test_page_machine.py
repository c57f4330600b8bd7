"""The printer page's machine panels in a real browser: the temperatures (a live chart of
every heater, targets set by hand or from a preset) and the controls (jog, home, fan,
extrude), checked against what the fake controller executed."""

from __future__ import annotations

import re
import time
from typing import Any

import pytest

from tests.support.page import TwoPrinters, needs_browser
from tests.support.server import gcode

pytestmark = [needs_browser, pytest.mark.timeout(120)]

CHART = """
const plot = document.querySelector('#panel-temperatures .temps-chart');
const u = plot && plot.uplot;
return u ? {labels: u.series.map((s) => s.label || ''), data: u.data} : null;
"""


def chart(browser: Any) -> dict[str, Any] | None:
    """What the temperature chart draws: its series' labels and its data columns."""
    return browser.driver.execute_script(CHART)  # type: ignore[no-any-return]


def series(browser: Any, label: str) -> list[float | None]:
    drawn = chart(browser)
    if drawn is None or label not in drawn["labels"]:
        return []
    return list(drawn["data"][drawn["labels"].index(label)])


def times(browser: Any) -> list[float]:
    """The chart's x column: when each report was taken (seconds since the epoch)."""
    drawn = chart(browser)
    return list(drawn["data"][0]) if drawn else []


def ready(browser: Any, two_printers: TwoPrinters) -> None:
    browser.open(f"{two_printers.url}/printers/left")
    browser.wait(lambda: "ready" in browser.text(".printer-head .badge"), "left is not ready")


def executed_after(two_printers: TwoPrinters, command: str, count: int = 1) -> bool:
    return two_printers.executed("left").count(command) >= count


def around(two_printers: TwoPrinters, command: str) -> list[str]:
    """The commands the fake executed before, at and after ``command`` ([] until all ran)."""
    log = two_printers.executed("left")
    at = log.index(command) if command in log else -1
    return log[at - 1 : at + 2] if at > 0 and at + 1 < len(log) else []


def test_a_target_set_on_the_page_heats_and_is_charted(browser, two_printers: TwoPrinters) -> None:
    ready(browser, two_printers)
    row = "#panel-temperatures tr[data-sensor=T0]"
    browser.wait(lambda: browser.all(f"{row} button.set"), "no row for T0")
    browser.wait(lambda: browser.css(f"{row} button.set").is_enabled(), "Set stays disabled")
    assert browser.text(f"{row} .target") == "off"

    browser.css(f"{row} input").send_keys("200")
    browser.css(f"{row} button.set").click()
    browser.wait(lambda: executed_after(two_printers, "M104 T0 S200"), "M104 T0 S200 never ran")
    browser.wait(lambda: "200" in browser.text(f"{row} .target"), "the table misses the target")
    # The next report carries the target: the chart's dashed T0 line is at 200.
    browser.wait(lambda: 200 in series(browser, "T0 target"), "the chart draws no T0 target")
    assert all(value in (None, 200) for value in series(browser, "T0 target"))
    assert not any(series(browser, "T1 target")), "T1 was not set: it has no target line"
    browser.wait(lambda: max(v or 0 for v in series(browser, "T0")) > 30, "T0 does not heat")

    # A preset for the bed: PLA's bed is 60 °C.
    bed = "#panel-temperatures tr[data-sensor=B]"
    assert browser.css(f"{bed} button[data-preset=PLA]").text == "PLA 60°"
    browser.css(f"{bed} button[data-preset=PLA]").click()
    browser.wait(
        lambda: executed_after(two_printers, "M140 S60"), "the PLA preset did not set the bed"
    )
    browser.wait(lambda: "60" in browser.text(f"{bed} .target"), "the bed's target is not shown")
    browser.wait(lambda: 60 in series(browser, "bed target"), "the chart draws no bed target")
    assert "M104 T0 S205" not in two_printers.executed("left"), "the bed's preset set a head"


def test_b_the_chart_shows_the_history_from_before_the_page(
    browser, two_printers: TwoPrinters
) -> None:
    with two_printers.server.client() as client:
        wait = time.monotonic() + 30
        while client.get("/v1/printers/left").json()["state"] != "ready":
            assert time.monotonic() < wait, "left never got ready"
            time.sleep(0.2)
        time.sleep(3)  # reports every 2 s: at least one before the page opens
        history = client.get("/v1/printers/left/temperatures").json()["samples"]
    assert history, "the server kept no report"
    opened = time.time()
    browser.open(f"{two_printers.url}/printers/left")

    browser.wait(lambda: series(browser, "T0"), "no chart")
    drawn = times(browser)
    assert drawn[0] < opened, "the chart starts at the page's load: no history"
    assert drawn[0] <= history[0]["time"] + 0.01
    assert series(browser, "T0")[0] is not None and series(browser, "bed")[0] is not None
    # and it goes on live from the event stream
    browser.wait(lambda: len(times(browser)) > len(drawn), "no live report was added")
    assert times(browser)[-1] > opened


def test_c_jog_and_home_z_with_a_confirmation(browser, two_printers: TwoPrinters) -> None:
    ready(browser, two_printers)
    panel = "#panel-control"
    browser.wait(lambda: browser.css(f"{panel} .jog-xplus").is_enabled(), "jog stays disabled")
    browser.css(f"{panel} .segmented input[value='1'] + span").click()
    browser.css(f"{panel} .segmented input[value='10'] + span").click()
    browser.css(f"{panel} .jog-xplus").click()
    browser.wait(lambda: around(two_printers, "G1 X10 F3000"), "the jog did not end with G90")
    assert around(two_printers, "G1 X10 F3000") == ["G91", "G1 X10 F3000", "G90"]
    browser.wait(lambda: "G90" in browser.text(f"{panel} .control-status"), "no reply shown")
    assert "ok" in browser.text(f"{panel} .control-status")

    browser.css(f"{panel} .home-z").click()
    alert = browser.wait(lambda: _alert(browser), "Home Z asked nothing")
    assert "Home Z" in alert.text
    alert.accept()
    browser.wait(lambda: executed_after(two_printers, "G28 Z"), "G28 Z did not run")

    browser.css(f"{panel} .home-z").click()
    browser.wait(lambda: _alert(browser), "Home Z asked nothing").dismiss()
    browser.css(f"{panel} .motors-off").click()  # sent after whatever went before
    browser.wait(lambda: executed_after(two_printers, "M84"), "M84 did not run")
    assert two_printers.executed("left").count("G28 Z") == 1, "a dismissed Home Z was sent"

    # Z jogs at 600 mm/min, down with a minus.
    browser.css(f"{panel} .jog-zminus").click()
    browser.wait(lambda: executed_after(two_printers, "G1 Z-10 F600"), "Z- did not run")


def _alert(browser: Any) -> Any:
    from selenium.common.exceptions import NoAlertPresentException

    try:
        alert = browser.driver.switch_to.alert
        alert.text  # noqa: B018 (raises when there is none)
        return alert
    except NoAlertPresentException:
        return None


def test_d_the_controls_wait_while_a_job_streams(browser, two_printers: TwoPrinters) -> None:
    ready(browser, two_printers)
    jog = "#panel-control .jog-yplus"
    set_t0 = "#panel-temperatures tr[data-sensor=T0] button.set"
    browser.wait(lambda: browser.css(jog).is_enabled(), "jog stays disabled")
    browser.wait(lambda: browser.all(set_t0), "no row for T0")
    with two_printers.server.client() as client:
        answer = client.post("/v1/printers/left/jobs", files={"file": ("long.gcode", gcode(3000))})
        assert answer.status_code == 201, answer.text
        job = answer.json()["id"]
        try:
            browser.wait(lambda: not browser.css(jog).is_enabled(), "jog stays enabled")
            assert "pause it first" in (browser.css(jog).get_attribute("title") or "")
            assert not browser.css(set_t0).is_enabled()
            assert "pause it first" in (browser.css(set_t0).get_attribute("title") or "")
            assert not browser.css("#panel-control .home-z").is_enabled()

            assert client.post("/v1/printers/left/pause").status_code == 204
            browser.wait(lambda: browser.css(jog).is_enabled(), "jog stays disabled when paused")
            assert not browser.css(jog).get_attribute("title")
            browser.css("#panel-control .segmented input[value='100'] + span").click()
            browser.css(jog).click()
            browser.wait(lambda: around(two_printers, "G1 Y100 F3000"), "a paused jog did not run")
            assert around(two_printers, "G1 Y100 F3000") == ["G91", "G1 Y100 F3000", "G90"]
            assert client.get(f"/v1/jobs/{job}").json()["state"] == "paused"
            # The terminal shows the jog on the wire, among the job's lines.
            terminal = "#panel-terminal .terminal-output"
            browser.wait(
                lambda: re.search(r"Send: (N\d+ )?G1 Y100 F3000", browser.text(terminal)),
                "the jog in the terminal",
            )
        finally:
            client.delete(f"/v1/jobs/{job}")
        browser.wait(lambda: "ready" in browser.text(".printer-head .badge"), "no end")
        browser.wait(lambda: browser.css(jog).is_enabled(), "jog stays disabled after the job")
