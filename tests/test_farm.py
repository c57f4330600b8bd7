"""A farm for real: hyrel-server processes sharing one queue in a real PostgreSQL, each
with fake controllers on ptys whose executed logs tell which printer ran what."""

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

from repetrel_host.testing.fake_controller import BuiltInFake
from tests.helpers import executed
from tests.pg import needs_postgres
from tests.test_server import KEY, Server

pytestmark = [pytest.mark.timeout(180), needs_postgres]

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


def part(job: str, moves: int = 30, tool: int = 0) -> bytes:
    """A job whose moves name it (Y is its number): the executed logs tell where it ran."""
    number = int(job)
    lines = [f"T{tool}", "G28"] + [f"G1 X{i % 100} Y{number} F6000" for i in range(moves)]
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
        with self.nodes[node or next(iter(self.nodes))].client() as client:
            answer: dict[str, Any] = client.get("/v1/farm").json()
        return answer

    def jobs(self) -> dict[int, dict[str, Any]]:
        return {job["id"]: job for job in self.view()["jobs"]}

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
        "automatic_transition = true",
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


def test_jobs_go_to_the_printers_that_match_their_needs_each_exactly_once(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    abs_ = loadout(tmp_path, "abs", (1, "MK1-250", "ABS"))
    start_node(farm, "alpha", {"p1": {"loadout": pla}})
    start_node(farm, "beta", {"a1": {"loadout": abs_, "tags": ["enclosed"]}})
    ids = {}
    for number, material in ((101, "PLA"), (102, "ABS"), (103, "PLA"), (104, "ABS")):
        name, material = f"part{number}.gcode", f"material={material}"
        answer = farm.submit("alpha", part(str(number)), name, material)
        assert answer.status_code == 201, answer.text
        ids[number] = answer.json()["jobs"][0]
    farm.wait(
        lambda: all(farm.jobs()[i]["state"] == "completed" for i in ids.values()),
        what="every job to complete",
    )
    assert where_ran(farm, "101") == [("alpha", "p1")]
    assert where_ran(farm, "103") == [("alpha", "p1")]
    assert where_ran(farm, "102") == [("beta", "a1")]
    assert where_ran(farm, "104") == [("beta", "a1")]
    jobs = farm.jobs()
    for number, job_id in ids.items():
        job = jobs[job_id]
        expected = ("alpha", "p1") if number in (101, 103) else ("beta", "a1")
        assert (job["node_name"], job["printer"]) == expected
        assert job["lines"] == 32 and job["last_line"] == 32
        # Exactly once: the job's 30 moves, each once, on that printer's fake.
        node, printer = expected
        moves = [line for line in farm.nodes[node].ran(printer) if f" Y{number} " in line]
        assert len(moves) == 30
    view = farm.view("beta")
    printers = {p["name"]: p for p in view["printers"]}
    assert printers["a1"]["capabilities"]["materials"] == ["ABS"]
    assert printers["a1"]["capabilities"]["tags"] == ["enclosed"]
    assert printers["p1"]["url"].endswith("/printers/p1")


def test_a_job_no_printer_can_print_is_refused_saying_what_is_missing(
    farm: Farm, tmp_path: Path
) -> None:
    pla = loadout(tmp_path, "pla", (1, "MK1-250", "PLA"))
    start_node(farm, "alpha", {"p1": {"loadout": pla}})
    answer = farm.submit("alpha", part("201"), "part.gcode", "material=PETG")
    assert answer.status_code == 400
    error = answer.json()["error"]
    assert "no printer of the farm can print part.gcode" in error
    assert "p1 on alpha: no material PETG" in error
    # A tool the printer has no head on: the lint says so.
    answer = farm.submit("alpha", part("202", tool=3), "t3.gcode")
    assert answer.status_code == 400
    assert "T3 selects yoke 1, slot 4, which has no head loaded" in answer.json()["error"]
    answer = farm.submit("alpha", part("203"), "x.gcode", "colour=red")
    assert answer.status_code == 400
    assert "'colour' is not something a printer has" in answer.json()["error"]
    assert farm.jobs() == {}
