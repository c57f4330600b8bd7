"""The printer page's job and camera panels in a real browser: a layered job drawn as it
prints, paused, resumed and cancelled from the page (the fake controller's log says what
ran), the resume offer queued from the page, the layer shown marked as printed, printing
or when the job starts it; the layer snapshots, a snapshot taken now, a time-lapse made by
ffmpeg, and the plain sentence where ffmpeg is missing."""

from __future__ import annotations

import re
import shutil
import sys
import time
from collections.abc import Callable
from itertools import pairwise
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.support.helpers import MARLIN_SAFE_STOP
from tests.support.page import CAMERA, Browser, TwoPrinters, needs_browser, part_gcode
from tests.support.server import Server, camera_config, wait_for

pytestmark = [needs_browser, pytest.mark.timeout(120)]
# Marlin's safe stop on printer left: each of its two hotends off by its index.
SAFE_STOP = [
    command
    for marlin in MARLIN_SAFE_STOP
    for command in (["M104 T0 S0", "M104 T1 S0"] if marlin == "M104 S0" else [marlin])
]


def sent(lines: list[str]) -> list[str]:
    """The commands of ``lines`` that reach the controller: no comments, no host codes."""
    return [line for line in lines if line and not line.startswith((";", "M790", "M791"))]


def printer(client: httpx.Client, name: str = "left") -> dict[str, Any]:
    return dict(client.get(f"/v1/printers/{name}").json())


def job_record(client: httpx.Client, job_id: int) -> dict[str, Any]:
    return dict(client.get(f"/v1/jobs/{job_id}").json())


def drawn(browser: Browser) -> dict[str, int]:
    """What the layer view drew: its layer, its moves, those acknowledged (read at once)."""
    found = browser.driver.execute_script(
        "const c = document.querySelector('#panel-job canvas.layer-canvas');"
        "return c ? [c.dataset.layer, c.dataset.moves, c.dataset.acked] : [0, 0, 0]"
    )
    return dict(zip(("layer", "moves", "acked"), map(int, found), strict=True))


def percent(browser: Browser) -> float:
    return float(browser.text("#panel-job .job-percent").split()[0] or 0)


def buttons(browser: Browser) -> dict[str, tuple[bool, str]]:
    """Pause, Resume and Cancel: whether each is enabled, and its hover text."""
    found = browser.driver.execute_script(
        "return ['pause', 'resume', 'cancel'].map((name) => {"
        "  const b = document.getElementById('job-' + name);"
        "  return [name, !b.disabled, b.getAttribute('title') || ''] })"
    )
    return {name: (enabled, title) for name, enabled, title in found}


def confirm_cancel(browser: Browser, accept: bool) -> str:
    """Click Cancel, and answer the confirmation it asks; its text."""
    from selenium.webdriver.support import expected_conditions

    browser.click("#job-cancel")
    alert = browser.waiter.until(expected_conditions.alert_is_present())
    text = str(alert.text)
    if accept:
        alert.accept()
    else:
        alert.dismiss()
    return text


def test_the_job_panel_draws_the_layer_and_pauses_resumes_cancels_and_resumes_it(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    text = part_gcode(layers=12, moves=500, thumbnail=False)
    lines = text.splitlines()
    client = two_printers.server.client()
    wait_for(lambda: printer(client)["state"] == "ready", what="printer left ready")
    job = client.post("/v1/printers/left/jobs", files={"file": ("part.gcode", text)}).json()
    browser.open(f"{two_printers.url}/printers/left")
    browser.wait(lambda: browser.text("#panel-job .job-file") == "part.gcode", "the job shown")
    browser.wait(lambda: drawn(browser)["moves"] > 0, "the layer view draws")

    # The view follows the print: the acknowledged moves grow, the layer advances.
    seen = [drawn(browser)]
    first_percent = percent(browser)

    def grew() -> bool:
        return any(a["layer"] == b["layer"] and b["acked"] > a["acked"] for a, b in pairwise(seen))

    deadline = time.monotonic() + 60
    while not (grew() and seen[-1]["layer"] > seen[0]["layer"]):
        assert time.monotonic() < deadline, seen
        time.sleep(0.1)
        seen.append(drawn(browser))
    assert percent(browser) > first_percent
    facts = browser.text("#panel-job .job-facts").replace(",", "")  # 6,026: the browser's
    assert f"of {job['total_lines']}" in facts and "of 12" in facts
    assert job["total_lines"] == len(sent(lines))
    layer = client.get(f"/v1/files/part.gcode/layers/{seen[-1]['layer']}").json()
    assert seen[-1]["moves"] == len(layer["moves"]) == 501  # the travel to the ring, its moves

    # Pause from the page: the controller stops at the acknowledged line.
    assert buttons(browser)["pause"] == (True, "")
    browser.click("#job-pause")
    browser.wait(lambda: browser.text(".printer-head .badge") == "paused", "the badge: paused")
    browser.wait(lambda: browser.text("#panel-job .job-state") == "paused", "the job: paused")
    state = buttons(browser)
    assert not state["pause"][0] and state["pause"][1] == "the job is paused already"
    assert state["resume"] == (True, "") and state["cancel"] == (True, "")
    paused = printer(client)["job"]
    assert paused["state"] == "paused"
    said = {
        "estimate": "(planned, at this printer's pace)",
        "plan": "(planned)",
        "slicer": "(slicer's estimate)",
        "linear": "(at the rate so far)",
    }
    # Waited for: the plan may land as the job pauses (3 s in), its event a moment later.
    browser.wait(
        lambda: (
            said[printer(client)["job"]["time_left_from"]] in browser.text("#panel-job .job-facts")
        ),
        "the time left, and how it was found",
    )
    assert two_printers.executed("left")[-1] == lines[paused["last_line"] - 1]
    # The view shows exactly the acknowledged moves of the layer being printed.
    moves = client.get(f"/v1/files/part.gcode/layers/{paused['layer']}").json()["moves"]
    acked = sum(1 for move in moves if move[0] <= paused["last_line"])
    browser.wait(
        lambda: drawn(browser) == {"layer": paused["layer"], "moves": len(moves), "acked": acked},
        f"layer {paused['layer']} drawn with {acked} moves acknowledged",
    )
    ran = len(two_printers.executed("left"))
    time.sleep(0.5)
    assert len(two_printers.executed("left")) == ran  # nothing runs while paused
    # Each layer's moves were asked for once (the next one ahead), not at each progress
    # (its times are asked again, without the moves).
    asked = browser.driver.execute_script(
        "return performance.getEntriesByType('resource').map((e) => e.name)"
        ".filter((name) => name.includes('/layers/') && !name.includes('moves=false'))"
    )
    assert len(asked) == len(set(asked)) <= paused["layer"] + 1, asked

    browser.click("#job-resume")
    browser.wait(lambda: browser.text(".printer-head .badge") == "printing", "printing again")
    browser.wait(lambda: buttons(browser)["pause"][0], "Pause enabled again")
    assert not buttons(browser)["resume"][0] and buttons(browser)["resume"][1]
    wait_for(lambda: len(two_printers.executed("left")) > ran, what="the job runs on")

    # Cancel asks first: dismissed, nothing happens.
    question = confirm_cancel(browser, accept=False)
    assert question == "Cancel job {} (part.gcode)? The safe stop runs first.".format(job["id"])
    ran = len(two_printers.executed("left"))
    wait_for(lambda: len(two_printers.executed("left")) > ran + 20, what="the job goes on")
    now = printer(client)
    assert now["state"] == "printing" and now["job"]["id"] == job["id"]
    assert two_printers.executed("left")[-8:] != SAFE_STOP
    # Accepted: the job is cancelled, and the safe stop ran last.
    confirm_cancel(browser, accept=True)
    wait_for(lambda: job_record(client, job["id"])["state"] == "cancelled", what="cancelled")
    wait_for(lambda: two_printers.executed("left")[-8:] == SAFE_STOP, what="the safe stop")
    browser.wait(lambda: browser.text("#panel-job .job-state") == "cancelled", "shown cancelled")
    assert not any(enabled for enabled, _ in buttons(browser).values())
    assert all(title for _, title in buttons(browser).values())

    # The resume offer: the command hyrel-send runs, and a button that queues the same.
    offer = client.get(f"/v1/jobs/{job['id']}/resume").json()
    browser.wait(lambda: "--from-layer" in browser.text(".job-resume-offer code"), "the offer")
    assert browser.text(".job-resume-offer code") == offer["layer_command"]
    assert offer["layer_command"].endswith(f"--from-layer {offer['from_layer']}")
    queue = browser.css("#job-queue-resumed")
    assert queue.text == f"Queue the resumed job (from layer {offer['from_layer']})"
    # The view shows the layer where it stopped, its moves acknowledged up to the stop.
    layer = client.get(f"/v1/files/part.gcode/layers/{offer['from_layer']}").json()
    acked = sum(1 for move in layer["moves"] if move[0] < offer["from_line"])
    browser.wait(
        lambda: drawn(browser)["layer"] == offer["from_layer"] and drawn(browser)["acked"] == acked,
        "the stopped layer drawn",
    )
    queue.click()
    browser.wait(lambda: "Queued as job" in browser.text(".job-resume-offer"), "queued")
    resumed_id = int(re.findall(r"Queued as job (\d+)", browser.text(".job-resume-offer"))[0])
    resumed = job_record(client, resumed_id)
    assert resumed["state"] == "queued" and resumed["from_line"] == layer["first_line"]
    assert lines[layer["first_line"] - 1] == ";LAYER_CHANGE"
    assert not queue.is_enabled()  # queued once
    if printer(client)["held"]:
        assert client.post("/v1/printers/left/release").status_code == 204
    browser.wait(
        lambda: "resumed from line" in browser.text("#panel-job .job-facts"), "the resumed job"
    )
    wait_for(lambda: job_record(client, resumed_id)["state"] == "completed", what="resumed job")
    ran = two_printers.executed("left")
    after_stop = ran[len(ran) - ran[::-1].index("M84") :]
    expected = sent(lines[layer["first_line"] - 1 :])
    assert after_stop[-len(expected) :] == expected  # from the layer's start to the end
    browser.wait(lambda: browser.text("#panel-job .job-state") == "completed", "completed")
    browser.wait(lambda: drawn(browser)["acked"] == drawn(browser)["moves"] > 0, "all drawn done")
    assert not browser.all(".job-resume-offer:not([hidden])")


def show_layer(browser: Browser, number: int) -> None:
    """Move the layer slider to ``number``, as a person drags it."""
    browser.driver.execute_script(
        "const s = document.querySelector('#panel-job .layer-slider');"
        "s.value = arguments[0]; s.dispatchEvent(new Event('input'));",
        number,
    )


def marks(browser: Browser) -> tuple[int, int, str, str]:
    """Read at once: the job's layer as the panel says it ("Layer 3 of 12"), the layer
    drawn, and the mark under the view (its words, and which it is: printed, printing,
    ahead)."""
    found = browser.driver.execute_script(
        "const facts = document.querySelector('#panel-job .job-facts').innerText;"
        "const m = /Layer\\s+(\\d+) of/.exec(facts);"
        "const mark = document.querySelector('#panel-job .layer-mark');"
        "return [m ? Number(m[1]) : 0,"
        " Number(document.querySelector('#panel-job canvas.layer-canvas').dataset.layer),"
        " mark.hidden ? '' : mark.innerText.trim(), mark.hidden ? '' : mark.dataset.mark]"
    )
    return int(found[0]), int(found[1]), str(found[2]), str(found[3])


def test_the_layer_shown_is_marked_printed_printing_or_when_the_running_job_prints_it(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    client = two_printers.server.client()
    wait_for(lambda: printer(client)["state"] == "ready", what="printer left ready")
    part = ("part.gcode", part_gcode(layers=12, moves=500, thumbnail=False))
    job = client.post("/v1/printers/left/jobs", files={"file": part}).json()
    browser.open(f"{two_printers.url}/printers/left")
    browser.wait(lambda: drawn(browser)["moves"] > 0, "the layer view draws")
    mark = "#panel-job .layer-mark"
    # The view follows the print: the layer it prints is marked as printing, never as
    # printed, from one layer to the next (once the view drew the job's layer).
    browser.wait(lambda: browser.text(mark).startswith("printing now"), "marked now")
    seen: list[tuple[int, int, str, str]] = []
    while len({layer for layer, drawn_layer, _, _ in seen if layer == drawn_layer}) < 3:
        seen.append(marks(browser))
        assert len(seen) < 2000, seen[-5:]
        time.sleep(0.02)
    followed = [(words, which) for layer, shown, words, which in seen if layer == shown]
    assert all(
        which == "printing" and words.startswith("printing now") for words, which in followed
    ), followed
    assert browser.all(".layer-mark.now")
    browser.wait(lambda: browser.text(mark).startswith("printing now · done ~"), "its end")
    running = wait_for(lambda: (j := printer(client)["job"]) and j["layer"] >= 2 and j)
    later = running["layer"] + 4
    assert later <= 12, running

    show_layer(browser, later)  # a layer still to print: when it starts, and in how long
    browser.wait(lambda: drawn(browser)["layer"] == later, f"layer {later} drawn")
    browser.wait(lambda: browser.text(mark).startswith("starts ~"), "marked later")
    found = re.fullmatch(r"starts ~.+ \(in about (\d+) (s|min)\)", browser.text(mark))
    assert found, browser.text(mark)
    seconds = int(found[1]) * (60 if found[2] == "min" else 1)
    times = client.get(f"/v1/files/part.gcode/layers/{later}?printer=left&moves=false").json()
    assert 0 < seconds <= printer(client)["job"]["time_left"] + 60  # within the job's end
    assert abs(seconds - times["starts_in"]) <= 60  # the server's, as roughly as shown
    assert not browser.all(".layer-mark.now")

    show_layer(browser, 1)  # a layer printed already
    browser.wait(lambda: browser.text(mark) == "printed", "marked printed")
    assert browser.all(".layer-mark.done") and not browser.all(".layer-mark.now")
    client.delete(f"/v1/jobs/{job['id']}")
    ended = ("cancelled", "completed")
    wait_for(lambda: job_record(client, job["id"])["state"] in ended, what="the job's end")
    browser.wait(lambda: not browser.all(f"{mark}:not([hidden])"), "no mark once it ended")


def layer_thumbs(browser: Browser) -> list[str]:
    return [str(name) for name in browser.attributes(".camera-strip .camera-thumb", "data-file")]


def image_loaded(browser: Browser, selector: str) -> bool:
    return bool(
        browser.driver.execute_script(
            "const i = document.querySelector(arguments[0]);"
            "return Boolean(i && i.complete && i.naturalWidth > 0);",
            selector,
        )
    )


def test_the_camera_panel_shows_layer_snapshots_takes_one_and_makes_a_time_lapse(
    browser: Browser, two_printers: TwoPrinters
) -> None:
    client = two_printers.server.client()
    wait_for(lambda: printer(client)["state"] == "ready", what="printer left ready")
    browser.open(f"{two_printers.url}/printers/right")
    browser.wait(lambda: browser.text("#panel-camera .camera-absent"), "no camera on right")
    sentence = "No camera: add camera = ... to this printer's settings."
    assert browser.text("#panel-camera .panel-body") == sentence

    browser.open(f"{two_printers.url}/printers/left")
    browser.wait(lambda: browser.all("#camera-snapshot"), "the camera panel")
    no_job = "no job: upload a file in Files below and print it"
    browser.wait(lambda: browser.text("#panel-job .empty") == no_job, "no job yet")
    assert browser.text(".camera-strip") == "None yet: a job takes one at each layer (M790)."
    part = ("part.gcode", part_gcode(layers=4, moves=100))
    job_id = client.post("/v1/printers/left/jobs", files={"file": part}).json()["id"]
    wait_for(lambda: job_record(client, job_id)["state"] == "completed", what="the job")

    def layer_shots() -> list[str]:
        # A layer's snapshot is skipped while the last one is still being taken (a busy
        # machine): the strip shows what the server kept.
        shots = [s["file"] for s in client.get("/v1/printers/left/snapshots").json()]
        return sorted(f for f in shots if f"-job{job_id}-layer" in f)

    wait_for(lambda: len(layer_shots()) >= 2, what="the layer snapshots")
    browser.wait(lambda: layer_thumbs(browser) == layer_shots(), "the strip of layer snapshots")
    kept = layer_shots()
    assert browser.text("#panel-camera h3") == f"Layer snapshots of job {job_id}"
    browser.wait(lambda: image_loaded(browser, ".camera-thumb:last-child img"), "thumbs shown")

    # Snapshot now: a new one, shown as the latest.
    latest = browser.css(".camera-image").get_attribute("data-file")
    assert latest == kept[-1]
    assert browser.css("#camera-snapshot").is_enabled()
    browser.css("#camera-snapshot").click()
    browser.wait(lambda: browser.css(".camera-image").get_attribute("data-file") != latest, "new")
    now = browser.css(".camera-image").get_attribute("data-file")
    assert "-job" not in now
    assert client.get("/v1/printers/left/snapshots").json()[0]["file"] == now
    browser.wait(lambda: image_loaded(browser, ".camera-image"), "the new snapshot shown")
    assert layer_thumbs(browser) == kept  # not a layer's

    # A layer snapshot clicked is shown large, until "Show the latest".
    browser.all(".camera-thumb")[1].click()
    browser.wait(lambda: browser.css(".camera-image").get_attribute("data-file") == kept[1])
    assert browser.text(".camera-caption").startswith(f"layer 2 of job {job_id} · ")
    browser.css(".camera-latest").click()
    browser.wait(lambda: browser.css(".camera-image").get_attribute("data-file") == now)

    # A time-lapse of the job's layer snapshots, played by the page.
    make = browser.css("#camera-timelapse")
    assert make.text == f"Make time-lapse of job {job_id}" and make.is_enabled()
    assert not browser.all(".camera-missing:not([hidden])")
    make.click()
    browser.wait(lambda: browser.all("video.camera-video"), "the video shown")
    videos = client.get("/v1/printers/left/timelapses").json()["videos"]
    assert [v["file"] for v in videos] == [f"timelapse-job{job_id}.mp4"]
    video = browser.css("video.camera-video")
    assert video.get_attribute("controls") is not None
    assert f"timelapse-job{job_id}.mp4?apikey=" in video.get_attribute("src")
    browser.wait(
        lambda: browser.driver.execute_script("return arguments[0].readyState", video) >= 1,
        "the browser reads the video",
    )
    assert browser.driver.execute_script("return arguments[0].duration", video) > 0


def test_without_ffmpeg_the_camera_panel_says_so_and_makes_no_time_lapse(
    browser: Browser,
    bench: Callable[..., Any],
    servers: Callable[..., Server],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The server inherits this PATH: Python's folder, without ffmpeg.
    python_only = str(Path(sys.executable).parent)
    assert shutil.which("ffmpeg", path=python_only) is None
    monkeypatch.setenv("PATH", python_only)
    fake = bench("--move-time", "0.004")
    server = servers({}, "--config", str(camera_config(tmp_path, {"left": fake.port}, left=CAMERA)))
    client = server.client()
    wait_for(lambda: printer(client)["state"] == "ready", what="printer left ready")
    job_id = client.post(
        "/v1/printers/left/jobs", files={"file": ("part.gcode", part_gcode(layers=3, moves=50))}
    ).json()["id"]
    wait_for(lambda: job_record(client, job_id)["state"] == "completed", what="the job")
    missing = client.get("/v1/printers/left/timelapses").json()["missing"]
    assert missing and "ffmpeg is not installed" in missing

    browser.open(f"{server.url}/printers/left")
    # The camera skips a layer while it still takes the last one (a busy machine): the
    # strip shows each snapshot the server kept.
    snapshots = client.get("/v1/printers/left/snapshots").json()
    kept = sum(f"-job{job_id}-layer" in s["file"] for s in snapshots)
    assert kept >= 1
    browser.wait(lambda: len(browser.all(".camera-thumb")) >= kept, "the layer snapshots")
    browser.wait(lambda: browser.text(".camera-missing") == missing, "the sentence")
    make = browser.css("#camera-timelapse")
    assert not make.is_enabled() and make.get_attribute("title") == missing
    assert not browser.all("video")
    # The job panel, opened after the job, shows it as the last one, drawn whole.
    assert browser.text("#panel-job .job-state") == "completed"
    assert browser.text("#panel-job .job-title") == "No job is running. The last one:"
    browser.wait(lambda: drawn(browser) == {"layer": 3, "moves": 51, "acked": 51}, "layer 3 done")
    assert client.post("/v1/printers/left/timelapses", json={"job": job_id}).status_code == 501
