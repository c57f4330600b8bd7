"""A hyrel-server process for tests, its fake printers and the waits the tests share."""

from __future__ import annotations

import contextlib
import functools
import json
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.paths import SUPPORT

KEY = "test-key"

pytestmark = pytest.mark.timeout(120)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class Server:
    """A hyrel-server process on a free port."""

    def __init__(self, data_dir: Path, printers: dict[str, str], *args: str) -> None:
        self.data_dir = data_dir
        self.printers = printers
        self.args = list(args)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.process: subprocess.Popen[str] | None = None
        self.stderr = data_dir.parent / f"server-{self.port}.log"

    def start(self) -> Server:
        command = [sys.executable, "-m", "repetrel_host.server.main"]
        command += ["--data-dir", str(self.data_dir), "--bind", f"127.0.0.1:{self.port}"]
        for name, port in self.printers.items():
            command += ["--printer", f"{name}={port}"]
        with self.stderr.open("a") as log:
            self.process = subprocess.Popen(
                [*command, *self.args], stdout=log, stderr=log, stdin=subprocess.DEVNULL, text=True
            )
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            assert self.process.poll() is None, self.stderr.read_text()
            try:
                httpx.get(f"{self.url}/api/version", timeout=1)
                return self
            except httpx.TransportError:
                time.sleep(0.1)
        raise AssertionError(f"the server did not start: {self.stderr.read_text()}")

    def wait_ready(self, *names: str) -> Server:
        """Once each printer ``names`` is connected and ready."""
        with self.client() as http:

            def ready(name: str) -> bool:
                return bool(http.get(f"/v1/printers/{name}").json()["state"] == "ready")

            for name in names:
                wait_for(functools.partial(ready, name), what=f"printer {name} ready")
        return self

    def client(self, key: str | None = KEY) -> httpx.Client:
        headers = {"X-Api-Key": key} if key is not None else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=30)

    def stop(self, signum: int = signal.SIGTERM) -> int:
        assert self.process is not None
        if self.process.poll() is None:
            self.process.send_signal(signum)
        return self.process.wait(timeout=60)


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Callable[..., BuiltInFake]]:
    """Fake controllers started by the test: ``bench(*fake_args)``."""
    fakes: list[BuiltInFake] = []

    def start(*args: str) -> BuiltInFake:
        fake = BuiltInFake(tmp_path / f"executed-{len(fakes)}.log", args, control=True)
        fakes.append(fake)
        fake.start()
        return fake

    yield start
    for fake in fakes:
        fake.stop()


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[Callable[..., Server]]:
    started: list[Server] = []

    def start(printers: dict[str, str], *args: str, key: bool = True) -> Server:
        server = Server(tmp_path / "data", printers, *(["--api-key", KEY] if key else []), *args)
        started.append(server.start())
        return server

    yield start
    for server in started:
        if server.process is not None and server.process.poll() is None:
            server.stop(signal.SIGKILL)


def gcode(count: int, *, start: int = 0) -> str:
    return "G28\n" + "".join(f"G1 X{(start + i) % 200} F3000\n" for i in range(count))


def commands_of(text: str) -> list[str]:
    return [line for line in text.splitlines() if line]


def past_paces(server: Server, *paces: float, printer: str = "bench") -> None:
    """Past jobs of ``printer`` that ran at ``paces`` (as the server records them), written
    into its store beside it."""
    with contextlib.closing(sqlite3.connect(server.data_dir / "jobs.sqlite")) as db:
        for number, pace in enumerate(paces, 1):
            db.execute(
                "INSERT INTO jobs (printer, name, file, state, position, submitted, "
                "started, ended, pace) VALUES (?, ?, 'files/old.gcode', "
                "'completed', 0, 1, 2, ?, ?)",
                (printer, f"old{number}.gcode", 2 + number, pace),
            )
        db.commit()


def wait_for(condition: Callable[[], Any], timeout: float = 30, what: str = "") -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = condition()
        if result:
            return result
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what or condition}")


def job_state(client: httpx.Client, job_id: int) -> dict[str, Any]:
    answer: dict[str, Any] = client.get(f"/v1/jobs/{job_id}").json()
    return answer


# --- as a slicer uses it -----------------------------------------------------------------


CAMERA = f"{sys.executable} {SUPPORT / 'fake_camera.py'}"


def camera_config(tmp_path: Path, printers: dict[str, str], **cameras: str) -> Path:
    """A server TOML file with ``printers``, each with its camera command, if any."""
    config = tmp_path / "server.toml"
    text = ""
    for name, port in printers.items():
        text += f'[printers.{name}]\nport = "{port}"\n'
        if name in cameras:
            text += f"camera = {json.dumps(cameras[name])}\n"
    config.write_text(text)
    return config


def server_config(tmp_path: Path, **printers: dict[str, object]) -> Path:
    """A server TOML file with a ``[printers.NAME]`` table of settings for each printer."""
    config = tmp_path / "server.toml"
    text = ""
    for name, settings in printers.items():
        text += f"[printers.{name}]\n"
        text += "".join(f"{key} = {json.dumps(value)}\n" for key, value in settings.items())
    config.write_text(text)
    return config


# A data folder made before jobs kept their M773 report: the table without its column.


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[int]:
    """An MQTT broker process on a free port: Debian's mosquitto, else amqtt's broker."""
    port = free_port()
    if shutil.which("mosquitto"):
        command = ["mosquitto", "-p", str(port)]
    else:
        config = tmp_path / "amqtt.yaml"
        config.write_text(
            f"listeners:\n  default:\n    type: tcp\n    bind: 127.0.0.1:{port}\n"
            "plugins:\n  amqtt.plugins.authentication.AnonymousAuthPlugin:\n"
            "    allow_anonymous: true\n"
        )
        command = [str(Path(sys.executable).parent / "amqtt"), "-c", str(config)]
    process = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL
    )
    try:
        wait_for(lambda: accepts(port), 15, "the MQTT broker")
        yield port
    finally:
        process.terminate()
        process.wait(timeout=10)


def accepts(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0
