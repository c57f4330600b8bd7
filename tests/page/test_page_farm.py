"""The page in a real browser (headless Chromium) against a real server with two fake
printers: the farm view, the terminal, the Access panel, and honest state (offline since
when and why; reconnecting after a restart)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import pytest
from selenium.webdriver.common.keys import Keys

from tests.support.page import KEY, Browser, TwoPrinters, chromium, needs_browser, part_gcode
from tests.support.server import gcode

pytestmark = [needs_browser, pytest.mark.timeout(120)]


def submit(two_printers: TwoPrinters, printer: str, name: str, text: str) -> int:
    with two_printers.server.client() as client:
        answer = client.post(f"/v1/printers/{printer}/jobs", files={"file": (name, text)})
        assert answer.status_code == 201, answer.text
        return int(answer.json()["id"])


def test_the_farm_view_shows_each_printer_live_filters_and_releases(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    browser.open(f"{two_printers.url}/")
    browser.wait(lambda: len(browser.all(".tile")) == 2, "two tiles")
    browser.wait(lambda: browser.text("[data-printer=right] .badge") == "ready", "right ready")
    assert browser.text("#link") == "live"
    temps = "[data-printer=right] .temps"
    browser.wait(lambda: re.search(r"bed 2\d°", browser.text(temps)), "the bed's temperature")
    # A job with the slicer's preview: the tile shows it, with its progress.
    submit(two_printers, "left", "cylinder.gcode", part_gcode(layers=12, moves=150))
    tile = "[data-printer=left]"
    browser.wait(lambda: browser.text(f"{tile} .badge") == "printing", "left printing")
    browser.wait(lambda: "layer" in browser.text(f"{tile} .numbers"), "its layer")
    # The time it has left (the plan's) and the clock time the printer is free again.
    browser.wait(
        lambda: re.search(r"left · free at \d", browser.text(f"{tile} .numbers")),
        "its time left and when it is free",
    )
    assert browser.text(f"{tile} .file") == "cylinder.gcode"
    browser.wait(
        lambda: (
            browser.driver.execute_script(
                "const i = document.querySelector('[data-printer=left] img.thumb');"
                "return i && i.complete && i.naturalWidth"
            )
            == 96
        ),
        "the thumbnail loaded",
    )
    assert "%" in browser.text(f"{tile} .numbers")
    # Filters: printing shows the printing one; idle the other.
    browser.click("[data-filter=printing]")
    assert browser.attributes(".tile", "data-printer") == ["left"]
    browser.click("[data-filter=idle]")
    assert browser.attributes(".tile", "data-printer") == ["right"]
    browser.click("[data-filter=all]")
    # The job ends: the queue is held, the tile says so and its Release works.
    browser.wait(lambda: "bed not cleared" in browser.text(f"{tile} .badge"), "held")
    browser.click("[data-filter=held]")
    assert browser.attributes(".tile", "data-printer") == ["left"]
    assert "2" not in browser.text("[data-filter=held] .count")
    browser.click(f"{tile} .held button")
    browser.wait(lambda: not browser.all(".tile"), "no held printer left")
    with two_printers.server.client() as client:
        assert client.get("/v1/printers/left").json()["held"] is False
    # The choices are kept in the browser.
    browser.driver.refresh()
    browser.wait(lambda: browser.all("[data-filter=held].on"), "the filter kept")


def test_a_lost_printer_says_offline_since_when_and_why(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    browser.open(f"{two_printers.url}/")
    browser.wait(lambda: browser.text("[data-printer=right] .badge") == "ready", "right ready")
    two_printers.fakes["right"].stop()
    badge = "[data-printer=right] .badge"
    browser.wait(lambda: browser.text(badge).startswith("offline since"), "offline")
    assert re.fullmatch(r"offline since \d\d:\d\d( [AP]M)?", browser.text(badge))
    browser.wait(lambda: browser.text("[data-printer=right] .reason"), "the reason")
    browser.click("[data-filter=offline]")
    assert browser.attributes(".tile", "data-printer") == ["right"]
    # The printer's own page says it too, and refuses its commands with the reason.
    browser.driver.get(f"{two_printers.url}/printers/right")
    browser.wait(lambda: browser.text(".printer-head .badge").startswith("offline since"))
    # (The panels load after the head line: the terminal's button may not be there yet.)
    browser.wait(lambda: browser.attributes("#terminal-send", "disabled") == [""], "disabled")
    assert "offline" in str(browser.attributes("#terminal-send", "title")[0])


def test_the_page_reconnects_by_itself_after_the_server_restarts(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    browser.open(f"{two_printers.url}/printers/left")
    browser.wait(lambda: browser.text("#link") == "live", "live")
    browser.wait(lambda: browser.text(".printer-head .badge") == "ready", "ready")
    assert two_printers.server.stop() == 0
    browser.wait(lambda: browser.text("#link") == "reconnecting…", "reconnecting")
    assert "reconnecting" in browser.css("#link").get_attribute("class")
    two_printers.server.start()
    browser.wait(lambda: browser.text("#link") == "live", "live again")
    browser.wait(lambda: browser.text(".printer-head .badge") == "ready", "ready again")
    # What happened meanwhile shows without a reload: a job queued while it was away.
    submit(two_printers, "left", "after.gcode", gcode(50))
    browser.wait(lambda: "after.gcode" in browser.text("#panel-queue"), "the new job")


def test_the_terminal_sends_recalls_shows_the_wire_and_says_why_not(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    browser.open(f"{two_printers.url}/printers/right")
    browser.wait(lambda: browser.text(".printer-head .badge") == "ready", "ready")
    # The wire is followed from when the page's socket joins (its first lines: polls).
    browser.wait(lambda: browser.all("#panel-terminal .line.wire"), "the wire followed")
    field = browser.css("#terminal-input")
    field.send_keys("M115", Keys.ENTER)
    output = "#panel-terminal .terminal-output"
    browser.wait(lambda: "FIRMWARE_NAME" in browser.text(f"{output} .reply"), "M115's reply")
    field.send_keys("G1 X12 F3000", Keys.ENTER)
    browser.wait(lambda: "G1 X12 F3000" in two_printers.executed("right"), "the move executed")
    # The up arrow brings back what was typed, newest first.
    field.send_keys(Keys.ARROW_UP)
    assert field.get_attribute("value") == "G1 X12 F3000"
    field.send_keys(Keys.ARROW_UP)
    assert field.get_attribute("value") == "M115"
    # The wire: what went and came, the polls hidden unless asked for.
    sent = re.compile(r"^Send: (N\d+ )?G1 X12 F3000(\*\d+)?$", re.MULTILINE)
    browser.wait(lambda: sent.search(browser.text(output)), "the wire")
    polls = "#panel-terminal .line.wire[data-poll=true]"
    browser.wait(lambda: browser.all(polls), "a poll on the wire")
    assert not any(line.is_displayed() for line in browser.all(polls))
    browser.css("#terminal-polls").click()
    assert any(line.is_displayed() for line in browser.all(polls))
    # While a job streams, Send waits and says why, in words.
    job = submit(two_printers, "right", "long.gcode", gcode(3000))
    send = browser.css("#terminal-send")
    browser.wait(lambda: send.get_attribute("disabled") is not None, "send disabled")
    assert send.get_attribute("title") == "a job is streaming: pause it first"
    assert "Commands wait: a job is streaming" in browser.text("#panel-terminal .terminal-why")
    with two_printers.server.client() as client:
        assert client.delete(f"/v1/jobs/{job}").status_code in (200, 202)
    browser.wait(lambda: send.get_attribute("disabled") is None, "send again")


def test_access_is_asked_for_allowed_and_revoked_on_the_page(
    browser: Browser, two_printers: TwoPrinters, tmp_path: Path
) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    browser.open(f"{two_printers.url}/")
    browser.wait(lambda: browser.text("#link") == "live", "live")
    second = chromium()
    try:
        other = Browser(second)
        other.open(f"{two_printers.url}/", key=None)
        WebDriverWait(second, 30).until(lambda _: other.css("#ask-access").is_displayed())
        assert "API key" in other.text("#notice")
        assert not other.all(".tile")
        other.css("#ask-access").click()
        requests = "#access-panel #requests"
        browser.wait(lambda: "asks for access" in browser.text(requests), "the request")
        browser.css(f"{requests} button.primary").click()
        other.wait(lambda: len(other.all(".tile")) == 2, "the other browser's tiles")
        granted = second.execute_script("return localStorage.getItem('hyrel-api-key')")
        assert granted and granted != KEY
        assert httpx.get(f"{two_printers.url}/api/job?apikey={granted}").is_success
        keys = "#access-panel #appkeys"
        browser.wait(lambda: "Status page" in browser.text(keys), "the key listed")
        browser.css(f"{keys} button.danger").click()
        browser.driver.switch_to.alert.accept()
        browser.wait(lambda: "Status page" not in browser.text(keys), "revoked")
        assert httpx.get(f"{two_printers.url}/api/job?apikey={granted}").status_code == 403
        time.sleep(0.2)
    finally:
        second.quit()
