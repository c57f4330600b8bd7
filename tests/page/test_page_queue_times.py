"""The page in a real browser (headless Chromium) against a real server with two fake
printers: the queue in time (each queued job's estimate and its end, the printer's free
time counting its queue)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.support.page import Browser, TwoPrinters, needs_browser
from tests.support.server import gcode

pytestmark = [needs_browser, pytest.mark.timeout(120)]


def submit(two_printers: TwoPrinters, name: str, text: str) -> int:
    with two_printers.server.client() as client:
        answer = client.post("/v1/printers/left/jobs", files={"file": (name, text)})
        assert answer.status_code == 201, answer.text
        return int(answer.json()["id"])


def test_a_queued_row_shows_its_estimate_and_end_and_the_header_when_the_printer_is_free(
    browser: Browser, two_printers: TwoPrinters, tmp_path: Path
) -> None:
    submit(two_printers, "long.gcode", gcode(20000))  # some 80 s on the fake
    queued = submit(two_printers, "next.gcode", gcode(1000))
    browser.open(f"{two_printers.url}/printers/left")
    row = f'.queue-row[data-job="{queued}"] .queue-estimate'
    browser.wait(
        lambda: re.fullmatch(r"about \d+ (s|min) · ends ~\d\d?:\d\d( [AP]M)?", browser.text(row)),
        "the queued job's estimate and end",
    )
    browser.wait(
        lambda: re.fullmatch(
            r"free at \d\d?:\d\d( [AP]M)?", browser.text(".printer-head .free-at")
        ),
        "when the printer is free",
    )
    # The printer is free when the queued job ends (the header follows every progress, the
    # queue is listed again when that shows another minute).
    browser.wait(
        lambda: (
            browser.text(".printer-head .free-at")
            == f"free at {browser.text(row).rpartition('~')[2]}"
        ),
        "the same",
    )
    browser.screenshot(tmp_path / "queue-times.png")
    print(f"screenshot: {tmp_path / 'queue-times.png'}")

    # Held: the queued job has no start, so no end; how long it takes is still said.
    with two_printers.server.client() as client:
        assert client.post("/v1/printers/left/hold").status_code == 204
    browser.wait(lambda: re.fullmatch(r"about \d+ (s|min)", browser.text(row)), "no end when held")
    browser.wait(lambda: browser.text(".printer-head .free-at") == "", "no free time when held")
