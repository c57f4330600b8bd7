"""What the page's tests share: headless Chromium driven by Selenium (Debian's chromium and
chromium-driver), a real hyrel-server with two fake printers on ptys, and a screenshot of
each test kept when it fails (in ``test-screenshots/`` at the repository's root).

Its fixtures (``browser``, ``two_printers``) are every test's (``tests/conftest.py`` loads this
module as a plugin); a test module imports the rest: ``from tests.support.page import Browser,
TwoPrinters, needs_browser``.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.paths import ROOT
from tests.support.server import CAMERA, KEY, Server

__all__ = [
    "CAMERA",
    "KEY",
    "TwoPrinters",
    "browser",
    "chromium",
    "needs_browser",
    "two_printers",
]

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
SCREENSHOTS = ROOT / "test-screenshots"
needs_browser = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="needs Debian's chromium and chromium-driver (.ci/run installs them)",
)
WAIT = 30.0  # seconds a page's change may take before the test fails


@dataclass
class TwoPrinters:
    """A server with printers ``left`` (a camera, two hotends) and ``right`` (one hotend),
    each a fake controller on a pty whose executed log tells what ran."""

    server: Server
    fakes: dict[str, BuiltInFake]
    url: str

    def executed(self, printer: str) -> list[str]:
        """What ``printer``'s fake ran but the host's probes (M105 lines: the page's tests
        never send one themselves)."""
        log = self.fakes[printer].log_path
        assert log is not None
        return [line for line in log.read_text().splitlines() if line and line != "M105"]


@pytest.fixture
def two_printers(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> TwoPrinters:
    fakes = {
        "left": bench("--move-time", "0.004", "--heat-rate", "40", "--extruders", "2"),
        "right": bench("--move-time", "0.004", "--heat-rate", "40"),
    }
    config = tmp_path / "server.toml"
    config.write_text(
        '[printers.left]\nport = "{}"\ncamera = {}\n[printers.right]\nport = "{}"\n'
        "[presets.PLA]\nhead = 205\nbed = 60\n[presets.PETG]\nhead = 235\nbed = 80\n".format(
            fakes["left"].port, json.dumps(CAMERA), fakes["right"].port
        )
    )
    server = servers({}, "--config", str(config))
    return TwoPrinters(server, fakes, server.url)


class Browser:
    """A Chromium page with helpers: ``open(path)`` with the key given, ``css(selector)``,
    ``wait(condition)``."""

    def __init__(self, driver: Any) -> None:
        from selenium.webdriver.support.ui import WebDriverWait

        self.driver = driver
        self.waiter = WebDriverWait(driver, WAIT)

    def open(self, url: str, key: str | None = KEY) -> None:
        """Load ``url`` with the API key kept in the browser (as after typing it once)."""
        self.driver.get(url.split("/", 3)[0] + "//" + url.split("/", 3)[2] + "/static/style.css")
        script = "localStorage.clear();"
        if key is not None:
            script += f"localStorage.setItem('hyrel-api-key', {json.dumps(key)});"
        self.driver.execute_script(script)
        self.driver.get(url)

    def css(self, selector: str) -> Any:
        from selenium.webdriver.common.by import By

        return self.driver.find_element(By.CSS_SELECTOR, selector)

    def all(self, selector: str) -> list[Any]:
        from selenium.webdriver.common.by import By

        return list(self.driver.find_elements(By.CSS_SELECTOR, selector))

    def text(self, selector: str) -> str:
        """The text of the first element ``selector`` finds ("" when none): read in the
        page at once (the page redraws often: a found element may be gone a moment later)."""
        return str(
            self.driver.execute_script(
                "const e = document.querySelector(arguments[0]); return e ? e.innerText : ''",
                selector,
            )
        ).strip()

    def texts(self, selector: str) -> list[str]:
        """The text of every element ``selector`` finds, read at once."""
        found: list[str] = self.driver.execute_script(
            "return [...document.querySelectorAll(arguments[0])].map(e => e.innerText.trim())",
            selector,
        )
        return found

    def attributes(self, selector: str, name: str) -> list[str | None]:
        """Attribute ``name`` of every element ``selector`` finds, read at once."""
        found: list[str | None] = self.driver.execute_script(
            "return [...document.querySelectorAll(arguments[0])]"
            ".map(e => e.getAttribute(arguments[1]))",
            selector,
            name,
        )
        return found

    def click(self, selector: str) -> None:
        """Click the element ``selector`` finds (again, should a redraw replace it)."""
        from selenium.common.exceptions import StaleElementReferenceException

        for _ in range(20):
            try:
                self.css(selector).click()
                return
            except StaleElementReferenceException:
                time.sleep(0.05)
        raise AssertionError(f"{selector} kept being replaced")

    def wait(self, condition: Callable[[], Any], message: str = "") -> Any:
        return self.waiter.until(lambda _: condition(), message)

    def keep_screenshot(self, name: str) -> None:
        """The page as it is, and the browser's console, kept in test-screenshots/."""
        SCREENSHOTS.mkdir(exist_ok=True)
        shot = SCREENSHOTS / f"{name}.png"
        try:
            self.driver.save_screenshot(str(shot))
            console = "\n".join(str(entry) for entry in self.driver.get_log("browser"))
            (SCREENSHOTS / f"{name}.console.txt").write_text(console)
        except Exception as exc:  # an alert open, a browser gone: the test's error stands
            print(f"no screenshot: {exc}")
            return
        print(f"screenshot kept: {shot}")

    def screenshot(self, path: Path, width: int = 1400, height: int = 1000) -> None:
        """The page at ``width``, as tall as it is (``height`` at least, 3000 px at most),
        as PNG."""
        self.driver.set_window_size(width, height)
        time.sleep(0.3)  # the layout follows the new width
        full = self.driver.execute_script("return document.documentElement.scrollHeight")
        self.driver.set_window_size(width, min(max(height, int(full)), 3000))
        time.sleep(0.3)
        self.driver.save_screenshot(str(path))


@pytest.fixture
def browser() -> Iterator[Browser]:
    """Headless Chromium (1400 x 1000); its screenshot is kept when the test fails."""
    driver = chromium()
    try:
        yield Browser(driver)  # a failed test's screenshot is taken as it fails (conftest.py)
    finally:
        driver.quit()


def chromium(locale: str | None = None) -> Any:
    """A headless Chromium driven by Selenium (1400 x 1000, its console kept), in
    ``locale`` ("de-DE": its dates, times and numbers) if given: quit it."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--window-size=1400,1000",
        "--hide-scrollbars",
    ):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    if locale is not None:
        driver.execute_cdp_cmd("Emulation.setLocaleOverride", {"locale": locale})
    return driver


def preview_png(size: int = 96) -> bytes:
    """A slicer-like preview: a shaded cylinder on a plate (Pillow draws it)."""
    import io

    from PIL import Image, ImageDraw

    image = Image.new("RGBA", (size, size), (0, 0, 0, 0))
    draw = ImageDraw.Draw(image)
    draw.ellipse((size * 0.08, size * 0.7, size * 0.92, size * 0.95), fill=(190, 196, 205, 255))
    for row in range(int(size * 0.25), int(size * 0.8)):
        shade = 120 + (row * 90) // size
        draw.line((size * 0.25, row, size * 0.75, row), fill=(30, shade // 2 + 40, shade, 255))
    draw.ellipse((size * 0.25, size * 0.17, size * 0.75, size * 0.33), fill=(90, 170, 240, 255))
    out = io.BytesIO()
    image.save(out, "PNG")
    return out.getvalue()


def rough(seconds: float) -> str:
    """An estimate as the page writes it (api.js's ``duration(s, {rough: true})``): "about
    40 s", "about 38 min", "about 2 h 05 min"."""
    import math

    half_up = lambda x: math.floor(x + 0.5)  # noqa: E731 (JavaScript's Math.round)
    s = max(0, half_up(seconds))
    if s < 60:
        return f"about {s} s"
    minutes = half_up(s / 60)
    if minutes < 60:
        return f"about {minutes} min"
    return f"about {minutes // 60} h {minutes % 60:02d} min"


def part_gcode(layers: int = 8, moves: int = 120, thumbnail: bool = True) -> str:
    """A sliced part as PrusaSlicer writes one: an embedded preview, layer marks (Z, and
    Hyrel's M790 for the layer snapshots), circles of extruding moves, a time estimate."""
    import base64
    import math

    text = "; generated by PrusaSlicer 2.8.1 on 2026-12-03 at 08:00:00 UTC\n"
    if thumbnail:
        data = base64.b64encode(preview_png()).decode()
        lines = [f"; {data[i : i + 78]}" for i in range(0, len(data), 78)]
        text += f";\n; thumbnail begin 96x96 {len(data)}\n" + "\n".join(lines)
        text += "\n; thumbnail end\n;\n"
    text += "M83\nG28\n"
    e = 0.05
    for layer in range(layers):
        z = round(0.2 * (layer + 1), 2)
        text += f";LAYER_CHANGE\n;Z:{z}\nG1 Z{z} F600\nM790\n"
        radius = 20 - layer * 1.2
        for step in range(moves + 1):
            angle = 2 * math.pi * step / moves
            x, y = 100 + radius * math.cos(angle), 100 + radius * math.sin(angle)
            extrude = f" E{e}" if step else ""
            text += f"G1 X{x:.3f} Y{y:.3f}{extrude} F1800\n"
    seconds = layers * moves // 10
    text += f"; filament used [mm] = {layers * moves * e:.2f}\n"
    text += f"; estimated printing time (normal mode) = {seconds // 60}m {seconds % 60}s\n"
    return text
