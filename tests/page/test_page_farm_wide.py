"""The status page of a node in a farm, in headless Chromium: every node's printers (each
linking to its own node's page), the farm's queue kept fresh by its event stream, a file
sent to the farm from the page."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.farm import Farm, loadout, part, start_node, where_ran
from tests.support.page import Browser, needs_browser, rough
from tests.support.paths import ROOT
from tests.support.pg import needs_postgres

pytestmark = [pytest.mark.timeout(180), needs_browser, needs_postgres]
SCREENSHOTS = ROOT / "docs" / "screenshots"


def test_the_page_shows_every_node_and_sends_a_file_to_the_farm(
    farm: Farm, browser: Browser, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    two = loadout(tmp_path, "two", (1, "MK1-250", "PLA"), (2, "SDS-05", "PETG"))
    a = start_node(farm, "bench-a", {"a1": {"loadout": pla}, "a2": {"loadout": two}})
    b = start_node(farm, "bench-b", {"b1": {"loadout": pla, "tags": ["big"]}}, automatic=False)
    (done,) = farm.submit("bench-a", part("300"), "bracket.gcode", "tag=big").json()["jobs"]
    farm.wait(lambda: farm.jobs()[done]["state"] == "completed", what="the first job")
    # b1 is held now (its part is on the bed): the next job for it waits in the queue.
    (waiting,) = farm.submit("bench-a", part("301"), "lid.gcode", "printer=b1").json()["jobs"]

    browser.open(f"{b.server.url}/")
    browser.wait(lambda: browser.text("#farm-wide h2").startswith("The farm"), "the farm panel")
    assert "2 nodes" in browser.text("#farm-wide h2")
    assert browser.attributes("#farm-nodes .farm-node", "data-node") == ["bench-a", "bench-b"]
    # Each printer links to the page of the node that drives it.
    links = dict(
        zip(
            browser.attributes(".farm-printer", "data-printer"),
            browser.attributes(".farm-printer", "href"),
            strict=True,
        )
    )
    assert links["a1"] == f"{a.server.url}/printers/a1"
    assert links["b1"] == f"{b.server.url}/printers/b1"
    states = dict(
        zip(
            browser.attributes(".farm-printer", "data-printer"),
            browser.attributes(".farm-printer", "data-state"),
            strict=True,
        )
    )
    assert states == {"a1": "ready", "a2": "ready", "b1": "held"}
    assert "T1 SDS-05 PETG 0.5 mm" in browser.text('.farm-printer[data-printer="a2"]')
    assert browser.attributes(".farm-jobs tbody tr", "data-state")[:2] == ["queued", "completed"]
    assert "printer=b1" in browser.text(f'.farm-jobs tr[data-job="{waiting}"]')
    # Its planned time, once the node that received it planned it, and the queue's total.
    farm.wait(lambda: farm.jobs()[waiting]["estimated_time"] is not None, what="its estimate")
    planned = rough(farm.jobs()[waiting]["estimated_time"])
    browser.wait(
        lambda: browser.text(f'.farm-jobs tr[data-job="{waiting}"] td.estimate') == planned,
        "the page to show the job's estimate (from the farm's events)",
    )
    assert browser.text(".farm-queue-total") == f"1 queued · {planned}"

    # A file sent from the page: checked against the farm and queued; the page follows it.
    job = tmp_path / "clip.gcode"
    job.write_bytes(part("302"))
    browser.css('.farm-submit input[type="file"]').send_keys(str(job))
    browser.css('.farm-submit input[name="require"]').send_keys("material=pla")
    browser.click('.farm-submit button[type="submit"]')
    browser.wait(lambda: "queued as farm job" in browser.text(".farm-submit [role=status]"))
    sent = int(browser.text(".farm-submit [role=status]").split("farm job ")[1].split(" ")[0])
    browser.wait(
        lambda: (
            browser.attributes(f'.farm-jobs tr[data-job="{sent}"]', "data-state") == ["completed"]
        ),
        "the page to show the job completed (from the farm's events)",
    )
    assert where_ran(farm, "302") in ([("bench-a", "a1")], [("bench-a", "a2")])

    # A job cancelled as it streamed: the page offers its rest, on the printer it was on.
    long = farm.submit("bench-a", part("303", moves=2000), "long.gcode", "printer=a2")
    (cut,) = long.json()["jobs"]
    farm.wait(lambda: farm.jobs()[cut]["lines"] > 50, what="the long job to stream")
    with a.client() as client:
        assert client.delete(f"/v1/farm/jobs/{cut}").status_code == 200
    farm.wait(lambda: farm.jobs()[cut]["state"] == "cancelled", what="the cancel")
    button = f'.farm-jobs tr[data-job="{cut}"] button.resume'
    browser.wait(lambda: browser.text(button) == "Resume on a2", "the Resume button")
    browser.click(button)
    rest = browser.wait(
        lambda: next((j for j in farm.jobs().values() if j["resumes"] == cut), None),
        "the rest of the job queued",
    )
    assert rest["from_line"] == farm.jobs()[cut]["last_line"] + 1
    # Resumed: the page offers it no more (the farm would refuse a second rest).
    row = f'.farm-jobs tr[data-job="{cut}"]'
    browser.wait(lambda: browser.attributes(row, "data-state") == ["resumed"], "resumed")
    assert not browser.all(f"{row} button.resume")
    assert browser.text(f"{row} .resumed-as") == f"rest: job {rest['id']}"
    farm.wait(lambda: farm.jobs()[rest["id"]]["state"] == "completed", what="the rest")
    assert farm.jobs()[rest["id"]]["printer"] == "a2"
    SCREENSHOTS.mkdir(exist_ok=True)
    browser.screenshot(SCREENSHOTS / "farm-nodes-desktop.png", 1400, 900)
    browser.screenshot(SCREENSHOTS / "farm-nodes-phone.png", 400, 900)
