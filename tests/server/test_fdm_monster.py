"""FDM Monster, a farm manager, for real: version 2.1.1 from the npm registry, run headless
with Node, drives a printer of its Klipper type (Moonraker) through its own REST API as its
web page does: test the connection, add the printer, see it online with its temperatures, home it,
list and upload files, print, pause, resume, cancel, and print a file to its end. Once
against hyrel-server with the fake controller (the fake's log says what ran), once against
real Moonraker 0.11.0 on the fake Klippy (the reference).

FDM Monster's Moonraker client sends no key (its ``createClient`` ignores the printer's API
key), so both servers trust this machine's network. It is installed once into the user's
cache (``FDM_MONSTER_DIR`` names another install); the test is skipped, saying why, where
Node or npm is missing or the install fails. Its calls (``dist/services/moonraker/``):
``GET /api/version`` first, then a websocket with ``server.connection.identify`` and
``POST /printer/objects/subscribe?connection_id=``, ``GET /printer/objects/query`` every
15 s, and each with ``Content-Type: application/json`` and an empty body."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.server.test_moonraker_reference import reference  # noqa: F401 (a fixture)
from tests.support.helpers import MARLIN_SAFE_STOP, executed
from tests.support.paths import CACHE, install_once
from tests.support.server import KEY, Server, free_port, gcode, wait_for

pytestmark = pytest.mark.timeout(420)  # the first run installs FDM Monster (some 90 s)

VERSION = "2.1.1"
# The package asks for its web page's package at 2.4.2, which the registry does not hold;
# the API does not need the page, so the newest there is taken.
PACKAGE = {
    "name": "fdm-monster-for-tests",
    "private": True,
    "dependencies": {"@fdm-monster/server": VERSION},
    "overrides": {"@fdm-monster/client-next": "2.3.3"},
}
QUIET = ["--no-audit", "--no-fund", "--omit=dev", "--loglevel=error"]
KLIPPER = 1  # FDM Monster's printer type for Moonraker (PrinterTypesEnum)
LONG = gcode(20000)  # paused and cancelled
SHORT = gcode(50)  # printed to its end


def fdm_monster() -> Path:
    """FDM Monster's entry point: ``FDM_MONSTER_DIR``, else an install in the user's cache
    made once."""
    folder = Path(os.environ.get("FDM_MONSTER_DIR") or CACHE / f"fdm-monster-{VERSION}")
    entry = folder / "node_modules" / "@fdm-monster" / "server" / "dist" / "index.js"
    npm = shutil.which("npm")
    if not shutil.which("node") or not npm:
        pytest.skip("FDM Monster needs Node.js and npm, and this machine has not both")

    def package() -> None:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "package.json").write_text(json.dumps(PACKAGE, indent=2))

    # It asks for Node 22; it runs on 20 (better-sqlite3 12 builds for it).
    install = [npm, "install", "--engine-strict=false", *QUIET]
    install_once(folder, f"FDM Monster {VERSION}", install, first=package, cwd=folder, timeout=400)
    return entry


@dataclass
class Manager:
    """A running FDM Monster: a client of its API, and its log folder."""

    http: httpx.Client
    logs: Path

    def log(self) -> str:
        return "".join(path.read_text() for path in sorted(self.logs.glob("*.log")))


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[Manager]:
    """FDM Monster on a free port with a data folder of its own, set up as a person does on
    its first page (no login) with Klipper printers turned on; a client of its API."""
    entry = fdm_monster()
    port = free_port()
    data = tmp_path / "fdm-monster"
    environment = {
        **os.environ,
        "NODE_ENV": "production",
        "SERVER_PORT": str(port),
        "DATABASE_PATH": str(data),
        "MEDIA_PATH": str(data / "media"),
        "ENV_FILE": str(data / "none.env"),  # not a .env beside the package
        "OVERRIDE_LOGIN_REQUIRED": "false",
        "OVERRIDE_REGISTRATION_ENABLED": "false",
        "DISABLE_SWAGGER_OPENAPI": "true",
        # Its error reports go nowhere: a closed port of this machine.
        "SENTRY_CUSTOM_DSN": "http://none@127.0.0.1:9/0",
    }
    environment.pop("GITHUB_PAT", None)  # no update checks
    log = (tmp_path / "fdm-monster.log").open("w")
    process = subprocess.Popen(
        ["node", str(entry)], env=environment, stdout=log, stderr=log, stdin=subprocess.DEVNULL
    )
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}/api/v2", timeout=60)
    try:

        def up() -> bool:
            assert process.poll() is None, (tmp_path / "fdm-monster.log").read_text()
            try:
                return http.get("/auth/login-required").status_code == 200
            except httpx.TransportError:
                return False

        wait_for(up, timeout=60, what="FDM Monster")
        wizard = {"loginRequired": False, "registration": False}
        wizard |= {"rootUsername": "root", "rootPassword": "a-root-password"}
        assert http.post("/first-time-setup/complete", json=wizard).status_code == 200
        moonraker = http.put("/settings/experimental-moonraker-support", json={"enabled": True})
        assert moonraker.json()["server"]["experimentalMoonrakerSupport"] is True
        yield Manager(http, data / "media" / "logs")
    finally:
        http.close()
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()


class Checks:
    """What a person sees, one check at a time; each failure kept with why, and the run
    goes on where it can."""

    def __init__(self) -> None:
        self.failed: list[str] = []
        self.passed: list[str] = []

    def check(
        self, name: str, condition: Callable[[], Any], timeout: float = 20, needs: str = ""
    ) -> Any:
        if needs and needs not in self.passed:
            self.failed.append(f"{name}: not tried, as {needs!r} failed")
            return None
        last: list[str] = []

        def attempt() -> Any:
            try:
                return condition()
            except (AssertionError, KeyError, TypeError, ValueError, httpx.HTTPError) as exc:
                last[:] = [f"{type(exc).__name__}: {exc}"]
                return None

        try:
            found = wait_for(attempt, timeout, name)
        except AssertionError:
            self.failed.append(f"{name}: {last[0] if last else 'never true'}")
            return None
        self.passed.append(name)
        return found

    def once(self, name: str, action: Callable[[], Any]) -> Any:
        """A check that is not tried again (a click)."""
        return self.check(name, action, timeout=0.05)


def answered(response: httpx.Response) -> httpx.Response:
    assert response.status_code == 200, f"{response.status_code} {response.text[:300]}"
    return response


def drive(manager: Manager, url: str, ran: Callable[[], list[str]]) -> Checks:
    """FDM Monster's page's calls for a Klipper printer at ``url`` that holds ``cube.gcode``,
    as a person clicks through them; ``ran`` gives the lines the printer ran (the rest of
    the printer's own record is left to the caller)."""
    checks = Checks()
    fdm = manager.http
    login = {"printerURL": url, "printerType": KLIPPER, "apiKey": KEY}

    def tested() -> bool:
        answer = answered(fdm.post("/printer/test-connection", json=login)).json()
        assert not answer.get("failure"), answer
        return True

    def test_passed() -> bool:
        # Its outcome goes to the page over socket.io, and to the log
        # (test-printer-socket.store.js); the file log may lag the answer.
        log = manager.log().splitlines()
        errors = [line for line in log if " ERR] " in line][-1:]
        assert any("Test completed successfully" in line for line in log), errors
        return True

    if checks.once("the connection test is answered", tested):
        checks.check("the connection test passes", test_passed, timeout=5)
    printer = {**login, "name": "hyrel", "enabled": True}
    added = checks.check(
        "the printer is added (its connection checked)",
        lambda: answered(fdm.post("/printer", json=printer)).json(),
        timeout=5,
    )
    if added is None:  # as the page offers: save it anyway
        added = answered(fdm.post("/printer", params={"forceSave": "true"}, json=printer)).json()
    number = added["id"]

    def current() -> dict[str, Any]:
        events: dict[str, Any] = answered(fdm.get(f"/printer/{number}/socket")).json()
        return events

    def flags() -> dict[str, bool]:
        found: dict[str, bool] = current()["current"]["payload"]["state"]["flags"]
        return found

    def objects() -> dict[str, Any]:
        found: dict[str, Any] = current()["notify_status_update"]["payload"]
        return found

    online = "the printer shows online and ready"
    checks.check(online, lambda: flags()["operational"] and flags()["ready"])
    checks.check(
        "its temperatures show",
        lambda: all(
            isinstance(objects()[heater]["temperature"], (int, float))
            for heater in ("extruder", "heater_bed")
        ),
        needs=online,
    )

    def button(name: str, path: str, body: dict[str, Any] | None = None, **form: Any) -> bool:
        """A click, once: its answer is a check of its own."""
        return bool(checks.once(name, lambda: answered(fdm.post(path, json=body, **form))))

    def listed(name: str) -> bool:
        files = answered(fdm.get(f"/printer-files/{number}")).json()["files"]
        return name in [file["path"] for file in files]

    if button("home is answered", f"/printer/{number}/home", {"x": True, "y": True, "z": True}):
        checks.check("the printer homes", lambda: "G28 X Y Z" in ran(), 10)

    listing = "its files are listed"
    checks.check(listing, lambda: listed("cube.gcode"), timeout=5)
    files = {"file": ("long.gcode", LONG.encode(), "application/octet-stream")}
    upload = f"/printer-files/{number}/upload"
    if button("a file is uploaded", upload, data={"startPrint": "false"}, files=files):
        checks.check("it is listed", lambda: listed("long.gcode"), 5, needs=listing)

    def state() -> str:
        return str(objects()["print_stats"]["state"])

    printing = "it shows printing"
    job = f"/printer/{number}/job"
    # FDM Monster merges each status update into the objects it holds one level deep: an
    # update of print_stats' durations (they move while a job runs or waits, on Klipper
    # too) drops its state, and its flags read false until its next full query (every
    # 15 s). A flag of a running job is looked for over two such queries.
    polls = 35
    if button("a print is started", f"/printer-files/{number}/print", {"filePath": "long.gcode"}):
        checks.check(printing, lambda: flags()["printing"], polls, needs=online)
    if button("pause is answered", f"{job}/pause"):
        checks.check("it shows paused", lambda: flags()["paused"], polls, needs=printing)
    if button("resume is answered", f"{job}/resume"):
        checks.check("it shows printing again", lambda: flags()["printing"], polls, printing)
    if button("cancel is answered", f"{job}/cancel"):
        checks.check("it shows cancelled", lambda: state() == "cancelled", needs=printing)
    if button(
        "a second print is started", f"/printer-files/{number}/print", {"filePath": "cube.gcode"}
    ):
        checks.check("it ends, complete", lambda: state() == "complete", 30, needs=online)
    return checks


def verdict(checks: Checks) -> None:
    passed = "\n  ".join(checks.passed)
    failed = "\n  ".join(checks.failed)
    assert not checks.failed, f"passed:\n  {passed}\nfailed:\n  {failed}"


@pytest.mark.slow
def test_fdm_monster_drives_a_hyrel_printer_as_a_klipper_printer(
    manager: Manager,
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    tmp_path: Path,
) -> None:
    fake = bench("--move-time", "0.004")
    config = tmp_path / "server.toml"
    config.write_text(
        f'moonraker_trusted_clients = ["127.0.0.0/8"]\n[printers.bench]\nport = "{fake.port}"\n'
    )
    server = servers({}, "--config", str(config))
    server.wait_ready("bench")
    with server.client() as http:
        upload = http.post("/server/files/upload", files={"file": ("cube.gcode", SHORT)})
        assert upload.status_code == 201, upload.text
    checks = drive(manager, server.url, lambda: executed(fake.log_path))
    fake.request("status")
    ran = executed(fake.log_path)
    print("passed:", checks.passed, "\nfailed:", checks.failed)
    if "it shows cancelled" in checks.passed:  # the long file stopped part way, safely
        cancelled = ran.index("G28") + ran[ran.index("G28") :].index("M84")
        assert ran[cancelled - len(MARLIN_SAFE_STOP) + 1 : cancelled + 1] == MARLIN_SAFE_STOP
        assert 0 < cancelled < 20000
    if "it ends, complete" in checks.passed:  # then the short file ran whole
        last = len(ran) - 1 - ran[::-1].index("G28")
        assert ran[last : last + 51] == SHORT.splitlines()
    verdict(checks)


@pytest.mark.slow
def test_fdm_monster_drives_real_moonraker_the_reference(
    manager: Manager,
    reference: str,  # noqa: F811 (the fixture)
) -> None:
    upload = httpx.post(f"{reference}/server/files/upload", files={"file": ("cube.gcode", SHORT)})
    assert upload.status_code == 201, upload.text

    def ran() -> list[str]:
        store = httpx.get(f"{reference}/server/gcode_store").json()["result"]["gcode_store"]
        return [str(line["message"]) for line in store if line["type"] == "command"]

    checks = drive(manager, reference, ran)
    print("passed:", checks.passed, "\nfailed:", checks.failed)
    jobs = httpx.get(f"{reference}/server/history/list").json()["result"]["jobs"]
    assert [job["status"] for job in jobs][:1] == ["completed"]
    verdict(checks)
