"""Who may use the server, as OctoPrint decides it: a key on every request (reads too)
unless reads are opened on purpose, OctoPrint's login and its session cookie, app keys a
person grants on the page (Home Assistant's only way in, driven here by pyoctoprintapi, the
library its integration is built on), ``hyrel-server keys``, and names too long to store."""

from __future__ import annotations

import asyncio
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import httpx
import pytest
from pyoctoprintapi import OctoprintClient
from pyoctoprintapi.api import ApiError, UnauthorizedException

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed, run_server_cli
from tests.support.server import KEY, Server, gcode, wait_for

pytestmark = pytest.mark.timeout(120)


def keys_command(data_dir: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run_server_cli("keys", *args, "--data-dir", str(data_dir), timeout=30)


def approve(server: Server, app: str, allow: bool = True) -> None:
    """A person on the page: wait for ``app``'s request, then allow or deny it."""
    with server.client() as client:

        def pending() -> Any:
            found = [p for p in client.get("/v1/appkeys").json()["pending"] if p["app_id"] == app]
            return found[0] if found else None

        request = wait_for(pending, what=f"{app}'s request")
        answer = client.post(f"/v1/appkeys/requests/{request['user_token']}", json={"allow": allow})
        assert answer.status_code == 204, answer.text


@pytest.mark.slow
def test_every_request_needs_a_key_unless_reads_are_opened(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    reads = ["/api/version", "/api/settings", "/api/files", "/api/job", "/api/printer"]
    reads += ["/v1/printers", "/v1/files", "/v1/appkeys", "/downloads/files/local/a.gcode"]
    with server.client(key=None) as anonymous, server.client("wrong") as wrong:
        for path in reads:
            for client in (anonymous, wrong):
                answer = client.get(path)
                assert answer.status_code == 403, path
                assert "API key" in answer.json()["error"]
        # What an app needs before it has a key, and the page that asks for one, are open.
        assert anonymous.get("/plugin/appkeys/probe").status_code == 204
        assert anonymous.get("/printers/demo/plugin/appkeys/probe").status_code == 204
        assert anonymous.get("/").status_code == 200
    with server.client() as client:
        assert client.get("/api/version").json()["text"].startswith("OctoPrint")
        # The key in the query (an image's or an event stream's URL) and as a bearer token.
    assert httpx.get(f"{server.url}/api/job?apikey={KEY}").status_code == 200
    bearer = {"Authorization": f"Bearer {KEY}"}
    assert httpx.get(f"{server.url}/api/job", headers=bearer).status_code == 200
    server.stop()

    opened = servers({"demo": "fake"}, "--public-read")
    with opened.client(key=None) as anonymous:
        assert anonymous.get("/api/version").status_code == 200
        assert anonymous.get("/api/currentuser").json()["groups"] == ["guests"]
        refused = anonymous.post("/api/printer/command", json={"command": "M105"})
        assert refused.status_code == 403  # changes still need the key
        # The app keys and the requests waiting are a user's, as on OctoPrint: a request's
        # user_token decides it.
        assert anonymous.get("/v1/appkeys").status_code == 403
        assert anonymous.get("/api/plugin/appkeys").status_code == 403
        assert (
            anonymous.post(
                "/api/plugin/appkeys", json={"command": "generate", "app": "x"}
            ).status_code
            == 403
        )


def test_a_passive_login_with_the_key_gives_the_owner_a_session_and_a_cookie(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    with server.client() as keyed:
        login = keyed.post("/api/login", json={"passive": True})
        assert login.status_code == 200, login.text
        user = login.json()
        # A farm manager takes "_api" or "guests" for "not logged in".
        assert user["name"] == "admin" and "admins" in user["groups"]
        assert len(user["session"]) >= 16 and "PRINT" in user["permissions"]
        cookies = dict(login.cookies)
    with httpx.Client(base_url=server.url, cookies=cookies, timeout=30) as browser:
        assert browser.get("/api/currentuser").json()["name"] == "admin"
        assert browser.get("/api/job").status_code == 200
        # A change by cookie alone needs the CSRF token (as OctoPrint asks): a page on
        # another site cannot make one.
        command = {"command": "M105"}
        assert browser.post("/api/printer/command", json=command).status_code == 403
        token = {"X-CSRF-Token": cookies["hyrel_csrf"]}
        wait_for(lambda: browser.get("/api/job").json()["state"] == "Operational", what="ready")
        sent = browser.post("/api/printer/command", json=command, headers=token)
        assert sent.status_code == 204, sent.text
        assert browser.post("/api/logout", headers=token).json()["groups"] == ["guests"]
    with httpx.Client(base_url=server.url, cookies=cookies, timeout=30) as after:
        assert after.get("/api/job").status_code == 403  # the session is gone
    with server.client(key=None) as anonymous:
        guest = anonymous.post("/api/login", json={"passive": True})
        assert guest.status_code == 200 and guest.json()["name"] is None
        password = anonymous.post("/api/login", json={"user": "admin", "pass": "x"})
        assert password.status_code == 403
        assert anonymous.post("/api/login", json={}).status_code == 400


def test_a_job_keeps_who_submitted_it(servers: Callable[..., Server]) -> None:
    server = servers({"demo": "fake"})
    job = {"file": ("part.gcode", gcode(3).encode())}
    with server.client() as keyed:
        uploaded = keyed.post("/api/files/local", data={"print": "true"}, files=job)
        assert uploaded.status_code == 201, uploaded.text
        assert uploaded.json()["job"]["user"] == "admin"
        submitted = keyed.post("/v1/printers/demo/jobs", files=job)
        assert submitted.status_code == 201 and submitted.json()["user"] == "admin"
        wait_for(lambda: keyed.get("/api/job").json()["progress"]["completion"] == 100.0)
        assert keyed.get("/api/job").json()["job"]["user"] == "admin"


@pytest.mark.slow
def test_home_assistant_sets_up_with_a_key_granted_on_the_page(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.02", "--heat-rate", "50")
    second = bench()
    server = servers({"p1": fake.port, "p2": second.port})
    job = tmp_path / "part.gcode"
    job.write_text(gcode(400))

    async def home_assistant() -> None:
        async with aiohttp.ClientSession() as session:
            octoprint = OctoprintClient("127.0.0.1", session, server.port, False, "/")
            # Its config flow: ask for a key, a person allows it on the page.
            approving = threading.Thread(target=approve, args=(server, "Home Assistant"))
            approving.start()
            key = await octoprint.request_app_key("Home Assistant", "admin", 30)
            approving.join()
            octoprint.set_api_key(key)
            # Its unique id: the discovery UUID, stable and one per printer.
            discovery = await octoprint.get_discovery_info()
            assert discovery is not None and len(discovery.upnp_uuid) == 36
            again = await octoprint.get_discovery_info()
            assert again is not None and again.upnp_uuid == discovery.upnp_uuid
            other = OctoprintClient("127.0.0.1", session, server.port, False, "/printers/p2/")
            other.set_api_key(key)
            other_discovery = await other.get_discovery_info()
            assert other_discovery is not None
            assert other_discovery.upnp_uuid != discovery.upnp_uuid
            assert (await octoprint.get_server_info()).version.startswith("1.11")
            assert (await octoprint.get_tracking_info()) is not None
            # Its coordinator: the printer and the job, its heater controls.
            await wait_ready(octoprint)
            await octoprint.set_tool_temperature("tool0", 60)
            await octoprint.set_bed_temperature(45)
            targets = fake.request("status")["temperatures"]
            assert targets["T"][1] == 60 and targets["B"][1] == 45
            printer = await octoprint.get_printer_info()
            assert {t.name for t in printer.temperatures} >= {"tool0", "bed"}
            await octoprint.turn_tool_off("tool0")
            await octoprint.turn_bed_off()
            await other.set_tool_temperature("tool0", 30)  # the second printer's own
            assert second.request("status")["temperatures"]["T"][1] == 30
            assert fake.request("status")["temperatures"]["T"][1] == 0

            form = aiohttp.FormData({"print": "true"})
            form.add_field("file", job.read_bytes(), filename=job.name)
            upload = await session.post(
                f"{server.url}/api/files/local", data=form, headers={"X-Api-Key": key}
            )
            assert upload.status == 201, await upload.text()
            await until(octoprint, lambda j: j.state == "Printing")
            during = await octoprint.get_job_info()
            assert during.job.file.name == "part.gcode"
            # Its estimate, from the file's moves (it has no slicer's comment): while it runs,
            # what it ran and has left, the time left beside it.
            await until(
                octoprint,
                lambda j: (
                    j.state == "Printing"
                    and j.job.estimated_print_time is not None
                    and j.progress.print_time_left is not None
                ),
            )
            await until(octoprint, lambda j: (j.progress.completion or 0) > 5)
            await octoprint.pause_job()
            await until(octoprint, lambda j: j.state == "Paused")
            await octoprint.resume_job()
            await until(octoprint, lambda j: j.state == "Printing")
            await octoprint.cancel_job()
            await until(octoprint, lambda j: j.state.startswith("Operational"))
            after = await octoprint.get_job_info()
            assert after.job.file.name == "part.gcode"  # kept after the job, as OctoPrint

            # A key revoked on the command line is refused at once.
            listed = keys_command(server.data_dir, "list")
            assert listed.returncode == 0 and "Home Assistant" in listed.stdout, listed
            revoked = keys_command(server.data_dir, "revoke", "Home Assistant")
            assert revoked.returncode == 0, revoked
            with pytest.raises(UnauthorizedException):
                await octoprint.get_job_info()
            # A request a person denies is answered as OctoPrint does.
            denying = threading.Thread(target=approve, args=(server, "Stranger", False))
            denying.start()
            with pytest.raises(ApiError, match="denied"):
                await octoprint.request_app_key("Stranger", "admin", 30)
            denying.join()

    asyncio.run(home_assistant())
    ran = executed(fake.log_path)
    assert ran[-4:] == ["G91", "G0 Z10", "G90", "M84"]  # the cancel's safe stop, last
    assert keys_command(server.data_dir, "revoke", "Nobody").returncode == 2


async def wait_ready(octoprint: OctoprintClient) -> None:
    await until(octoprint, lambda job: job.state == "Operational")


async def until(octoprint: OctoprintClient, condition: Callable[[Any], bool]) -> None:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if condition(await octoprint.get_job_info()):
            return
        await asyncio.sleep(0.1)
    raise AssertionError("timed out waiting for the job's state")


@pytest.mark.slow
def test_an_app_key_request_not_polled_expires_and_a_key_can_be_revoked_on_the_api(
    servers: Callable[..., Server],
) -> None:
    server = servers({"demo": "fake"})
    with server.client(key=None) as app, server.client() as person:
        asked = app.post("/plugin/appkeys/request", json={"app": "Slicer"})
        assert asked.status_code == 201
        token = asked.json()["app_token"]
        assert asked.headers["Location"].endswith(f"/plugin/appkeys/request/{token}")
        assert app.get(f"/plugin/appkeys/request/{token}").status_code == 202
        time.sleep(6)  # OctoPrint drops a request its app stopped polling after 5 s
        assert app.get(f"/plugin/appkeys/request/{token}").status_code == 404
        assert person.get("/v1/appkeys").json()["pending"] == []
        assert app.post("/plugin/appkeys/request", json={}).status_code == 400
        # Generated by a user, listed, revoked through OctoPrint's plugin API.
        made = person.post("/api/plugin/appkeys", json={"command": "generate", "app": "Cura"})
        key = made.json()["api_key"]
        assert httpx.get(f"{server.url}/api/job", headers={"X-Api-Key": key}).status_code == 200
        listed = person.get("/api/plugin/appkeys").json()["keys"]
        assert [k["app_id"] for k in listed] == ["Cura"] and "api_key" not in listed[0]
        revoke = person.post("/api/plugin/appkeys", json={"command": "revoke", "app": "Cura"})
        assert revoke.status_code == 204
        assert httpx.get(f"{server.url}/api/job", headers={"X-Api-Key": key}).status_code == 403
    keys = (server.data_dir / "appkeys.json").stat()
    assert keys.st_mode & 0o077 == 0  # private, as the server's own key


@pytest.mark.slow
def test_names_too_long_for_the_filesystem_are_shortened_or_refused_never_a_500(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench("--move-time", "0.02")
    server = servers({"demo": fake.port})
    with server.client() as client:
        wait_for(lambda: client.get("/api/job").json()["state"] == "Operational", what="ready")
        long = "x" * 796 + ".gcode"
        answer = client.post("/api/files/local", files={"file": (long, b"G28\n")})
        assert answer.status_code == 201, answer.text
        stored = answer.json()["files"]["local"]["name"]
        assert len(stored) <= 200 and stored.endswith(".gcode")
        assert "shortened" in answer.json()["note"]
        # A second upload of a name a job uses gets a "-2" name that fits too.
        name = "y" * 243 + ".gcode"
        first = client.post(
            "/api/files/local", files={"file": (name, gcode(300).encode())}, data={"print": "true"}
        )
        assert first.status_code == 201, first.text
        wait_for(lambda: client.get("/api/job").json()["state"] == "Printing", what="printing")
        second = client.post("/api/files/local", files={"file": (name, b"G28\n")})
        assert second.status_code == 201, second.text
        assert second.json()["files"]["local"]["name"].endswith("-2.gcode")
        for path in ("/api/files/local/" + "z" * 300, "/downloads/files/local/" + "z" * 300):
            refused = client.get(path)
            assert refused.status_code == 400 and "too long" in refused.json()["error"], path
        folder = client.post("/api/files/local", data={"foldername": "f" * 300})
        assert folder.status_code == 400
        assert client.post("/api/job", json={"command": "cancel"}).status_code == 204
