"""One-time links to the page (``hyrel-server link``, ``POST /v1/links``), for real (a
hyrel-server process, HTTP over loopback): the first browser that opens one in time gets an
app key of its own, once; a link used, expired or never made is refused, saying which; the
data folder keeps no link itself."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from tests.support.helpers import run_server_cli
from tests.support.server import KEY, Server

pytestmark = pytest.mark.timeout(120)


def link_command(data_dir: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run_server_cli("link", "--data-dir", str(data_dir), *args, timeout=30)


def made_token(server: Server, *args: str) -> str:
    made = link_command(server.data_dir, "--url", server.url, *args)
    assert made.returncode == 0, made.stderr
    url = made.stdout.strip()
    assert url.startswith(f"{server.url}/#token="), url
    return url.partition("#token=")[2]


def redeem(server: Server, token: str) -> httpx.Response:
    """As the page does with the link's token: no key, the token alone."""
    return httpx.post(f"{server.url}/v1/links/redeem", json={"token": token}, timeout=30)


@pytest.mark.slow
def test_a_link_made_beside_the_running_server_opens_the_page_once(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    made = link_command(server.data_dir, "--url", server.url, "--name", "hall screen")
    assert made.returncode == 0, made.stderr
    assert "giving the browser the app key 'hall screen'" in made.stderr
    token = made.stdout.strip().partition("#token=")[2]
    kept = server.data_dir / "links.json"
    assert token not in kept.read_text()  # its digest only
    assert stat.S_IMODE(kept.stat().st_mode) == 0o600

    opened = redeem(server, token)
    assert opened.status_code == 200, opened.text
    assert opened.json()["app_id"] == "hall screen"
    key = opened.json()["api_key"]
    assert key != KEY and len(key) >= 32
    with server.client(key) as browser:
        assert browser.get("/api/job").status_code == 200
        assert browser.get("/v1/printers").status_code == 200
    listed = run_server_cli("keys", "list", "--data-dir", str(server.data_dir), timeout=30)
    assert listed.stdout.startswith("hall screen\tadmin\t")

    again = redeem(server, token)
    assert again.status_code == 403
    assert again.json()["error"].startswith("this link was used already")
    unknown = redeem(server, "x" * 22)
    assert unknown.status_code == 403
    assert unknown.json()["error"].startswith("this link is not one the server made")
    assert redeem(server, "x" * 201).status_code == 400
    # Open to anyone, the route reads a few KB at most, as a login does.
    big = httpx.post(
        f"{server.url}/v1/links/redeem",
        content=b"{" + b" " * 100_000 + b"}",
        headers={"Content-Type": "application/json"},
        timeout=30,
    )
    assert big.status_code == 413

    # A new link for the same name replaces that name's key once it is opened.
    second = redeem(server, made_token(server, "--name", "hall screen"))
    assert second.status_code == 200
    with server.client(key) as browser:
        assert browser.get("/api/job").status_code == 403
    with server.client(second.json()["api_key"]) as browser:
        assert browser.get("/api/job").status_code == 200
    revoked = run_server_cli(
        "keys", "revoke", "hall screen", "--data-dir", str(server.data_dir), timeout=30
    )
    assert revoked.returncode == 0
    with server.client(second.json()["api_key"]) as browser:
        assert browser.get("/api/job").status_code == 403


@pytest.mark.slow
def test_a_link_expires_and_opens_for_one_of_many_at_once(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake"})
    short = made_token(server, "--for", "1s")
    time.sleep(1.2)
    expired = redeem(server, short)
    assert expired.status_code == 403
    assert expired.json()["error"].startswith("this link has expired")

    token = made_token(server)
    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(lambda _: redeem(server, token), range(8)))
    assert sorted(a.status_code for a in answers) == [200] + [403] * 7
    names = [a.json()["app_id"] for a in answers if a.status_code == 200]
    assert names[0].startswith("page link ")  # the default name: when it was made

    # Two links made in the same second: two names, two keys, neither replaces the other.
    first, second = (redeem(server, made_token(server)).json() for _ in range(2))
    assert first["app_id"] != second["app_id"]
    for opened in (first, second):
        with server.client(opened["api_key"]) as browser:
            assert browser.get("/api/job").status_code == 200


@pytest.mark.skipif(os.geteuid() != 0, reason="making a link as root needs root")
def test_a_link_made_as_root_leaves_its_files_to_the_servers_user(
    servers: Callable[..., Server],
) -> None:
    """``sudo hyrel-server link`` beside a service: the server's user can still open the
    links' files, as the data folder's owner it owns them."""
    server = servers({"demo": "fake"})
    nobody = 65534
    os.chown(server.data_dir, nobody, nobody)
    made_token(server)
    for name in ("links.json", "links.lock"):
        owner = (server.data_dir / name).stat()
        assert (owner.st_uid, owner.st_gid) == (nobody, nobody), name


def test_a_link_from_the_api_needs_the_key(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake"}, "--public-read")
    with server.client(key=None) as anonymous:
        assert anonymous.post("/v1/links", json={}).status_code == 403
    with server.client() as client:
        assert client.post("/v1/links", json={"seconds": 0}).status_code == 400
        assert client.post("/v1/links", json={"seconds": 90_000}).status_code == 400
        made = client.post("/v1/links", json={"app": "kiosk", "seconds": 60})
    assert made.status_code == 201, made.text
    answer = made.json()
    assert answer["app_id"] == "kiosk" and answer["expires"].endswith("+00:00")
    assert answer["url"].startswith(f"{server.url}/#token=")
    opened = redeem(server, answer["url"].partition("#token=")[2])
    assert opened.status_code == 200 and opened.json()["app_id"] == "kiosk"


def test_a_link_names_the_address_the_configuration_listens_on(
    servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"demo": "fake"})
    config = tmp_path / "server.toml"
    config.write_text(f'data_dir = "{server.data_dir}"\nbind = "0.0.0.0:9000"\n')
    made = run_server_cli("link", "--config", str(config), timeout=30)
    assert made.returncode == 0, made.stderr
    machine = socket.gethostname().split(".")[0]
    assert made.stdout.startswith(f"http://{machine}:9000/#token=")
    config.write_text(
        f'data_dir = "{server.data_dir}"\nnode_url = "https://printers.lab.example/"\n'
    )
    made = run_server_cli("link", "--config", str(config), timeout=30)
    assert made.stdout.startswith("https://printers.lab.example/#token=")
    assert redeem(server, made.stdout.strip().partition("#token=")[2]).status_code == 200


@pytest.mark.slow
def test_bad_link_commands_get_one_sentence(servers: Callable[..., Server], tmp_path: Path) -> None:
    nowhere = link_command(tmp_path / "nowhere")
    assert nowhere.returncode == 2
    assert nowhere.stderr == (
        f"hyrel-server: no hyrel-server has run on the data folder {tmp_path / 'nowhere'} "
        "(give its --data-dir)\n"
    )
    assert not (tmp_path / "nowhere").exists()
    server = servers({"demo": "fake"})
    for args, said in (
        (["--for", "10"], "--for 10: give a time with its unit, at most 24h (90s, 10m, 2h)"),
        (["--for", "25h"], "--for 25h: give a time with its unit"),
        (["--url", "printer.local"], "--url printer.local: give the page's address"),
        (["--name", " "], "--name: give a name of 1 to 200 characters"),
    ):
        result = link_command(server.data_dir, *args)
        assert result.returncode == 2, args
        assert said in result.stderr and "Traceback" not in result.stderr
        assert len(result.stderr.splitlines()) == 1
    assert "links.json" not in {path.name for path in server.data_dir.iterdir()}
