"""A farm for tests: nodes (hyrel-server processes) sharing one PostgreSQL queue."""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import executed
from tests.support.server import KEY, Server

LEASE = 3.0  # seconds: short, so that a lost node is found within a test


def loadout(tmp: Path, name: str, *heads: tuple[int, str, str]) -> Path:
    """A hydra-16a loadout of (slot, head, material) heads."""
    text = 'machine = "hydra-16a"\n' + "".join(
        f'[[heads]]\nslot = {slot}\nhead = "{head}"\nmaterial = "{material}"\nnozzle = 0.5\n'
        for slot, head, material in heads
    )
    path = tmp / f"{name}.toml"
    path.write_text(text)
    return path


def part(job: str, moves: int = 30, tool: int = 0, unique: bool = False) -> bytes:
    """A job whose moves name it (Y is its number): the executed logs tell where it ran
    (``unique``: each move's X its own, so the logs tell which lines ran)."""
    number = int(job)
    xs = [f"{i * 0.1:.1f}" if unique else str(i % 100) for i in range(moves)]
    lines = [f"T{tool}", "G28"] + [f"G1 X{x} Y{number} F6000" for x in xs]
    return ("\n".join(lines) + "\n").encode()


@dataclass
class Node:
    name: str
    server: Server
    fakes: dict[str, BuiltInFake]
    config: Path

    def client(self) -> httpx.Client:
        return self.server.client()

    def ran(self, printer: str) -> list[str]:
        log = self.fakes[printer].log_path
        assert log is not None
        return executed(log) if log.exists() else []


@dataclass
class Farm:
    url: str
    tmp: Path
    nodes: dict[str, Node] = field(default_factory=dict)

    def submit(self, node: str, job: bytes, name: str, *requires: str, **form: Any) -> Any:
        with self.nodes[node].client() as client:
            answer = client.post(
                "/v1/farm/jobs",
                data={"require": list(requires), **{k: str(v) for k, v in form.items()}},
                files={"file": (name, job, "application/octet-stream")},
            )
        return answer

    def view(self, node: str | None = None) -> dict[str, Any]:
        """The farm as ``node`` (else the first node running) shows it."""
        alive = [n for n, v in self.nodes.items() if v.server.process.poll() is None]  # type: ignore[union-attr]
        with self.nodes[node or alive[0]].client() as client:
            answer: dict[str, Any] = client.get("/v1/farm").json()
        return answer

    def jobs(self, node: str | None = None) -> dict[int, dict[str, Any]]:
        return {job["id"]: job for job in self.view(node)["jobs"]}

    def wait(self, condition: Callable[[], Any], timeout: float = 60, what: str = "") -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                found = condition()
            except (httpx.TransportError, KeyError):
                found = None
            if found:
                return found
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what or condition}: {self.jobs()}")


@pytest.fixture
def farm(farm_db: str, tmp_path: Path) -> Iterator[Farm]:
    made = Farm(farm_db, tmp_path)
    fakes: list[BuiltInFake] = []
    yield made
    for node in made.nodes.values():
        if node.server.process is not None and node.server.process.poll() is None:
            node.server.stop(signal.SIGKILL)
        fakes += node.fakes.values()
    for fake in fakes:
        fake.stop()


def start_node(
    farm: Farm,
    name: str,
    printers: dict[str, dict[str, Any]],
    fake_args: tuple[str, ...] = ("--move-time", "0.002"),
    farm_url: str | None = None,
    automatic: bool = True,
) -> Node:
    """A node of the farm: its printers on fake controllers (``printers``: name: settings
    such as loadout and tags), its own data folder, a short lease."""
    tmp = farm.tmp
    existing = farm.nodes.get(name)
    fakes = existing.fakes if existing else {}
    lines = [
        f'farm = "{farm_url or farm.url}"',
        f'node_name = "{name}"',
        f"farm_lease = {LEASE}",
        f"automatic_transition = {str(automatic).lower()}",
    ]
    for printer, settings in printers.items():
        if printer not in fakes:
            log = tmp / f"executed-{name}-{printer}.log"
            fakes[printer] = BuiltInFake(log, fake_args, control=True)
            fakes[printer].start()
        lines.append(f"[printers.{printer}]")
        lines.append(f'port = "{fakes[printer].port}"')
        for key, value in settings.items():
            lines.append(f"{key} = {json.dumps(str(value) if isinstance(value, Path) else value)}")
    config = tmp / f"{name}.toml"
    config.write_text("\n".join(lines) + "\n")
    server = Server(tmp / f"data-{name}", {}, "--api-key", KEY, "--config", str(config))
    if existing is not None:
        server.port, server.url = existing.server.port, existing.server.url
        server.args = existing.server.args
    server.start()
    node = farm.nodes[name] = Node(name, server, fakes, config)
    farm.wait(
        lambda: any(n["name"] == name and not n["lost"] for n in farm_view_nodes(node)),
        what=f"node {name} to join",
    )
    return node


def farm_view_nodes(node: Node) -> list[dict[str, Any]]:
    with node.client() as client:
        answer = client.get("/v1/farm")
    nodes: list[dict[str, Any]] = answer.json()["nodes"] if answer.status_code == 200 else []
    return nodes


def where_ran(farm: Farm, job_mark: str) -> list[tuple[str, str]]:
    """(node, printer) whose fake executed the job marked ``Y<mark>``."""
    return [
        (node.name, printer)
        for node in farm.nodes.values()
        for printer in node.fakes
        if any(line.endswith(f" Y{job_mark} F6000") for line in node.ran(printer))
    ]


# --- the tests ----------------------------------------------------------------------------
