"""The page and one-time links in a real browser (headless Chromium) against a real server:
a link gives a browser a key of its own and leaves its address at once; a spent link says
so, and a new link opened in the page takes its place; a key in the address is not taken,
and the page says why; the Access panel makes links for other screens."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from tests.support.helpers import run_server_cli
from tests.support.page import KEY, Browser, chromium, needs_browser
from tests.support.server import Server

pytestmark = [needs_browser, pytest.mark.timeout(120)]

KEY_STORAGE = "return localStorage.getItem('hyrel-api-key')"


def link(server: Server) -> str:
    made = run_server_cli(
        *("link", "--data-dir", str(server.data_dir), "--url", server.url), timeout=30
    )
    assert made.returncode == 0, made.stderr
    return made.stdout.strip()


def test_a_one_time_link_gives_the_browser_a_key_once_and_leaves_no_token_behind(
    browser: Browser, servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"demo": "fake"})
    url = link(server)
    browser.open(url, key=None)
    browser.wait(lambda: browser.text("#link") == "live", "live with the link's key")
    browser.wait(lambda: browser.all(".tile"), "the printer's tile")
    assert browser.driver.current_url == f"{server.url}/"  # no token in the address
    assert "This browser has a key of its own now" in browser.text("#notice")
    assert browser.css("#key-form").get_attribute("hidden") is not None
    kept = browser.driver.execute_script(KEY_STORAGE)
    assert kept and kept != KEY
    assert httpx.get(f"{server.url}/api/job", headers={"X-Api-Key": kept}).is_success
    browser.screenshot(tmp_path / "link-opened.png", 1000, 500)
    # Reloaded, the page keeps its key and asks for nothing.
    browser.driver.refresh()
    browser.wait(lambda: browser.text("#link") == "live", "live after a reload")
    assert browser.driver.execute_script(KEY_STORAGE) == kept

    second = chromium()
    try:
        other = Browser(second)
        other.open(url, key=None)  # the same link, spent
        other.wait(lambda: "used already" in other.text("#notice"), "the spent link's sentence")
        other.wait(lambda: other.text("#link") == "no key", "no key")
        # The stream's "no key" leaves the link's sentence, which says more.
        assert other.text("#notice").startswith("This link was used already")
        assert other.css("#key-form").is_displayed() and not other.all(".tile")
        assert second.current_url == f"{server.url}/"
        assert second.execute_script(KEY_STORAGE) is None
        other.screenshot(tmp_path / "link-spent.png", 1000, 500)
        # A new link opened in this page, open already: only the address's hash changes.
        second.get(link(server))
        other.wait(lambda: other.text("#link") == "live", "live with the new link's key")
        assert second.current_url == f"{server.url}/"
        assert second.execute_script(KEY_STORAGE) not in (None, kept)
    finally:
        second.quit()


def test_a_key_in_the_address_is_not_taken_and_the_page_says_why(
    browser: Browser, servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"demo": "fake"})
    browser.open(f"{server.url}/printers/demo?apikey={KEY}", key=None)
    browser.wait(lambda: browser.text("#link") == "no key", "no key")
    assert browser.text("#notice").startswith("A key in the page's address is not taken")
    assert browser.driver.current_url == f"{server.url}/printers/demo"
    assert browser.driver.execute_script(KEY_STORAGE) is None
    assert browser.css("#key-form").is_displayed()
    browser.screenshot(tmp_path / "key-in-address.png", 1000, 500)
    # With a key typed once, the address's key is still dropped, and said so.
    browser.open(f"{server.url}/?apikey=something", key=KEY)
    browser.wait(lambda: browser.text("#link") == "live", "live with the kept key")
    assert browser.driver.current_url == f"{server.url}/"
    assert browser.text("#notice").startswith("A key in the page's address is not taken")


def test_the_access_panel_makes_a_link_for_another_screen(
    browser: Browser, servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"demo": "fake"})
    browser.open(f"{server.url}/")
    browser.wait(lambda: browser.text("#link") == "live", "live")
    browser.wait(lambda: browser.all("#make-link"), "the Access panel")
    browser.click("#make-link")
    field = "#one-time-link input"
    browser.wait(lambda: browser.all(field), "the link")
    url = browser.css(field).get_attribute("value")
    assert url.startswith(f"{server.url}/#token=")
    assert "once, until" in browser.text("#one-time-link")
    browser.screenshot(tmp_path / "access-link.png", 1000, 1000)
    second = chromium()
    try:
        other = Browser(second)
        other.open(url, key=None)
        other.wait(lambda: other.all(".tile"), "the other screen's tile")
        granted = second.execute_script(KEY_STORAGE)
        assert granted and granted != KEY
    finally:
        second.quit()
    keys = "#access-panel #appkeys"
    browser.wait(lambda: "page link" in browser.text(keys), "its key listed")
