"""The page writes every time one way, in the browser's locale: the printer's "since", the
job's end, a queued job's end and the temperature chart's axis all read 12-hour in en-US
and 24-hour in de-DE; and the job panel shows the server's own figures (the time left, the
end, the whole job's time), none of its own making."""

from __future__ import annotations

import re
from datetime import datetime
from typing import Any

import httpx
import pytest

from tests.support.page import Browser, TwoPrinters, chromium, needs_browser, part_gcode, rough
from tests.support.server import wait_for

pytestmark = [needs_browser, pytest.mark.timeout(120)]
# A clock time as each locale writes it (another day's has its date before it).
CLOCK = {
    "en-US": r"(\d\d?:\d\d)(:\d\d)?\s([AP]M)",
    "de-DE": r"(\d\d:\d\d)(:\d\d)?",
}


def printer(client: httpx.Client) -> dict[str, Any]:
    return dict(client.get("/v1/printers/left").json())


def fact(browser: Browser, label: str) -> str:
    """The job panel's fact ``label`` ("Ends"), read at once ("" when it is not shown)."""
    return str(
        browser.driver.execute_script(
            "const dt = [...document.querySelectorAll('#panel-job .job-facts dt')]"
            ".find(e => e.innerText.trim() === arguments[0]);"
            "return dt ? dt.nextElementSibling.innerText.trim() : ''",
            label,
        )
    )


def axis(browser: Browser) -> list[str]:
    """The temperature chart's time axis, as uPlot wrote its ticks, once it charts a few
    seconds (one sample spans no time: its axis would be years wide)."""
    found = browser.driver.execute_script(
        "const u = (document.querySelector('.temps-chart') || {}).uplot;"
        "return u && u.data[0].length >= 3 && u.axes[0]._values ? u.axes[0]._values : []"
    )
    return [str(value) for value in found]


def seconds_of(duration: str) -> int:
    """ "4 min 10 s" -> 250 (the page's exact durations)."""
    units = {"h": 3600, "min": 60, "s": 1}
    return sum(int(n) * units[unit] for n, unit in re.findall(r"(\d+) (h|min|s)\b", duration))


def minutes_apart(shown: str, iso: str, locale: str) -> float:
    """How far the clock time ``shown`` (today, as ``locale`` writes it) is from ``iso``."""
    found = re.search(CLOCK[locale], shown)
    assert found, shown
    text = found[1] + (f" {found[3]}" if locale == "en-US" else "")
    parsed = datetime.strptime(text, "%I:%M %p" if locale == "en-US" else "%H:%M")
    when = datetime.fromisoformat(iso).astimezone()
    return abs((when.hour * 60 + when.minute) - (parsed.hour * 60 + parsed.minute))


@pytest.mark.parametrize("locale", ["en-US", "de-DE"])
def test_clock_times_and_the_chart_axis_follow_the_browser_locale(
    locale: str, two_printers: TwoPrinters
) -> None:
    clock = re.compile(rf"(.+ )?{CLOCK[locale]}")
    client = two_printers.server.client()
    wait_for(lambda: printer(client)["state"] == "ready", what="printer left ready")
    part = part_gcode(layers=12, moves=500, thumbnail=False)
    client.post("/v1/printers/left/jobs", files={"file": ("part.gcode", part)})
    queued = client.post("/v1/printers/left/jobs", files={"file": ("next.gcode", part)}).json()
    driver = chromium(locale)
    try:
        browser = Browser(driver)
        browser.open(f"{two_printers.url}/printers/left")
        browser.wait(lambda: fact(browser, "Ends"), "the job's end")
        browser.wait(lambda: len(axis(browser)) >= 2, "the chart's time axis")
        browser.wait(lambda: "ends ~" in browser.text(".queue-estimate"), "the queued job's end")

        since = browser.text(".printer-head .since")
        assert since.startswith("since ") and clock.fullmatch(since.removeprefix("since ")), since
        assert clock.fullmatch(fact(browser, "Ends")), fact(browser, "Ends")
        ticks = axis(browser)
        assert all(clock.fullmatch(tick) for tick in ticks), ticks
        assert len(set(ticks)) == len(ticks), ticks  # a tick a second at most
        row = browser.text(f'.queue-row[data-job="{queued["id"]}"] .queue-estimate')
        assert clock.fullmatch(row.split("ends ~")[1]), row
        if locale == "de-DE":
            assert not re.search(r"[AP]M", since + fact(browser, "Ends") + "".join(axis(browser)))

        # The figures are the server's: its end, its time left, its whole job's time.
        job = printer(client)["job"]
        assert minutes_apart(fact(browser, "Ends"), job["ends"], locale) <= 1
        browser.wait(
            lambda: (
                abs(seconds_of(fact(browser, "Time left")) - printer(client)["job"]["time_left"])
                <= 2
            ),
            "the server's time left",
        )
        browser.wait(
            lambda: (
                (whole := printer(client)["job"]["estimated_time"]) is not None
                and fact(browser, "Elapsed").endswith(f"of {rough(whole)}")
            ),
            "the server's whole job",
        )
    finally:
        driver.quit()
