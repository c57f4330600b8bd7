"""Home Assistant without the cloud (issue 22, item 7): a real hyrel-server process, a
real broker (mosquitto), the fake controller. Home Assistant's discovery configs are read
back from the broker; each config's value_template is rendered with Jinja (as Home
Assistant renders it) against what its state_topic really carries; its buttons, pressed as
Home Assistant presses them (their payload on their command topic), pause, resume and
cancel a real job. And MQTT's order: a job's last progress and its end before "ready"."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import aiomqtt
import httpx
import jinja2
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.session.events import State
from tests.support.helpers import CONE, MARLIN_SAFE_STOP, executed, job_commands
from tests.support.server import (
    KEY,
    Server,
    gcode,
    wait_for,
)

pytestmark = pytest.mark.timeout(180)

Messages = list[tuple[str, bytes]]


async def collect(port: int, topics: list[str], until: Callable[[Messages], bool]) -> Messages:
    """(topic, payload) of what arrives on ``topics`` (retained ones first) until ``until``."""
    messages: Messages = []
    async with aiomqtt.Client("127.0.0.1", port) as client:
        for topic in topics:
            await client.subscribe(topic, qos=1)
        async with asyncio.timeout(60):
            async for message in client.messages:
                assert isinstance(message.payload, bytes)
                messages.append((str(message.topic), message.payload))
                if until(messages):
                    return messages
    return messages


async def retained(port: int, topic: str) -> dict[str, bytes]:
    """Every retained message under ``topic`` now: those the broker sends as one
    subscribes, before a marker published after subscribing."""
    marker = "test/marker"
    found: dict[str, bytes] = {}
    async with aiomqtt.Client("127.0.0.1", port) as client:
        await client.subscribe(topic, qos=1)
        await client.subscribe(marker, qos=1)
        await client.publish(marker, b"end", qos=1)
        async with asyncio.timeout(10):
            async for message in client.messages:
                if str(message.topic) == marker:
                    return found
                assert isinstance(message.payload, bytes)
                found[str(message.topic)] = message.payload
    return found


def render(config: dict[str, Any], payload: bytes) -> str:
    """The config's value_template on ``payload``, as Home Assistant renders it
    (``value`` the payload, ``value_json`` its JSON)."""
    template = jinja2.Template(config["value_template"])
    value = payload.decode()
    return template.render(value=value, value_json=json.loads(value))


def configs_of(found: dict[str, bytes], prefix: str = "homeassistant") -> dict[str, Any]:
    """The discovery configs among retained messages, by their unique_id."""
    configs = [json.loads(p) for t, p in found.items() if t.startswith(f"{prefix}/") and p]
    return {config["unique_id"]: config for config in configs}


def start(
    servers: Callable[..., Server], fake: BuiltInFake, broker: int, tmp_path: Path, *extra: str
) -> Server:
    config = tmp_path / "server.toml"
    config.write_text(f'[printers.bench]\nport = "{fake.port}"\n')
    mqtt = ["--mqtt", f"127.0.0.1:{broker}", "--mqtt-commands", *extra]
    server = servers({}, "--config", str(config), *mqtt)
    with server.client() as client:
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "ready")
    return server


@pytest.mark.slow
def test_each_printer_is_a_home_assistant_device_whose_sensors_read_real_messages(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], broker: int, tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.0005", "--chamber")
    server = start(servers, fake, broker, tmp_path)
    with server.client() as client:
        settings = client.get("/api/settings").json()
        uuid = settings["plugins"]["discovery"]["upnpUuid"]
        job = client.post(
            "/v1/printers/bench/jobs", files={"file": ("cone.gcode", CONE.read_bytes())}
        )
        assert job.status_code == 201, job.text
        wait_for(lambda: client.get("/v1/printers/bench").json()["state"] == "printing")

    async def scenario() -> None:
        node = f"hyrel_{uuid}"
        # The chamber's sensors too, once the printer reported one (C:).
        expected = ["state", "progress", "time_left", "print_end", "file"]
        expected += ["pause", "resume", "cancel"]
        expected += [
            f"{h}_{w}" for h in ("hotend", "bed", "chamber") for w in ("temperature", "target")
        ]

        def keys(found: dict[str, bytes]) -> list[str]:
            return sorted(unique_id.removeprefix(f"{node}_") for unique_id in configs_of(found))

        found = await retained(broker, "#")
        async with asyncio.timeout(30):
            # Every sensor's config, and the states they read (the job's first progress, the
            # temperatures).
            def missing() -> bool:
                read = {c["state_topic"] for c in configs_of(found).values() if "state_topic" in c}
                return not set(expected) <= set(keys(found)) or not read <= set(found)

            while missing():
                await asyncio.sleep(0.2)
                found = await retained(broker, "#")
        assert keys(found) == sorted(expected)
        configs = configs_of(found)
        for topic, payload in found.items():
            if topic.startswith("homeassistant/"):
                component, node_id, object_id, last = topic.split("/")[1:]
                config = json.loads(payload)
                assert (node_id, last) == (node, "config")
                assert config["unique_id"] == f"{node}_{object_id}"
                assert component == ("button" if "command_topic" in config else "sensor")
                # One device per printer, available while the server says it is online.
                assert config["device"]["identifiers"] == [node]
                assert config["device"]["name"] == "bench"
                assert config["availability_topic"] == "hyrel/server/online"
                assert found["hyrel/server/online"].decode() == config["payload_available"]
        # Every sensor's template reads what its state topic really carries, mid-job.
        for config in configs.values():
            if "state_topic" not in config:
                continue
            value = render(config, found[config["state_topic"]])
            key = config["unique_id"].removeprefix(f"{node}_")
            if key == "state":
                assert value == "printing" and value in config["options"]
                assert config["options"] == [state.value for state in State]
            elif key == "file":
                assert value == "cone.gcode"
            elif key == "progress":
                assert 0 <= float(value) <= 100 and config["unit_of_measurement"] == "%"
            elif key == "time_left":  # the plan's (13m 58s for the whole cone, heat included)
                assert 0 <= int(value) <= 840 and config["device_class"] == "duration"
            elif key == "print_end":  # when, in Home Assistant's timestamp form
                ends = datetime.fromisoformat(value)
                assert ends.tzinfo is not None and config["device_class"] == "timestamp"
                assert abs(ends.timestamp() - time.time()) <= 840 + 60
            elif key == "hotend_target":
                assert float(value) == 200.0 and config["unit_of_measurement"] == "°C"
            else:  # the temperatures, the other targets
                assert float(value) >= 0.0 and config["device_class"] == "temperature"
        # The buttons, pressed as Home Assistant presses them.
        buttons = {c["payload_press"]: c for c in configs.values() if "command_topic" in c}
        assert set(buttons) == {"pause", "resume", "cancel"}
        async with aiomqtt.Client("127.0.0.1", broker) as home_assistant:

            async def press(action: str) -> None:
                button = buttons[action]
                await home_assistant.publish(button["command_topic"], button["payload_press"])

            await press("pause")
            await until_state(server, "paused")
            ran = len(executed(fake.log_path))
            await asyncio.sleep(0.5)
            assert len(executed(fake.log_path)) == ran  # held: the fake runs nothing more
            await press("resume")
            await until_state(server, "printing")
            await press("cancel")
            await until_state(server, "ready")

    asyncio.run(scenario())
    with server.client() as client:
        assert client.get("/v1/jobs/1").json()["state"] == "cancelled"
    fake.request("status")  # the log is complete
    ran = executed(fake.log_path)
    assert ran[-len(MARLIN_SAFE_STOP) :] == MARLIN_SAFE_STOP
    cone = job_commands(CONE)
    job = ran[: -len(MARLIN_SAFE_STOP)]
    assert job == cone[: len(job)]  # each line once, in order, up to the cancel


async def until_state(server: Server, state: str) -> None:
    async with httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as client:
        async with asyncio.timeout(30):
            while (await client.get("/v1/printers/bench")).json()["state"] != state:
                await asyncio.sleep(0.05)


def test_a_jobs_last_progress_and_its_end_go_out_before_the_printer_is_ready(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server], broker: int, tmp_path: Path
) -> None:
    fake = bench("--move-time", "0.001")
    server = start(servers, fake, broker, tmp_path)

    async def scenario() -> Messages:
        async def upload() -> None:
            await asyncio.sleep(0.5)  # subscribed by then
            async with httpx.AsyncClient(base_url=server.url, headers={"X-Api-Key": KEY}) as web:
                files = {"file": ("part.gcode", gcode(600))}
                assert (await web.post("/v1/printers/bench/jobs", files=files)).status_code == 201

        def ready_after_the_job(messages: Messages) -> bool:
            ended = [i for i, (t, p) in enumerate(messages) if t == "hyrel/bench/job" and
                     json.loads(p)["job"]["state"] == "completed"]  # fmt: skip
            return bool(ended) and any(
                t == "hyrel/bench/state" and json.loads(p)["state"] == "ready"
                for t, p in messages[ended[0] :]
            )

        uploading = asyncio.create_task(upload())
        seen = await collect(broker, ["hyrel/bench/#"], ready_after_the_job)
        await uploading
        return seen

    seen = [(topic, json.loads(payload)) for topic, payload in asyncio.run(scenario())]
    printing = next(i for i, (t, p) in enumerate(seen) if t.endswith("/state") and
                    p["state"] == "printing")  # fmt: skip
    after = seen[printing:]
    kinds = [(t.rsplit("/", 1)[1], p) for t, p in after]
    last_progress = max(i for i, (kind, _) in enumerate(kinds) if kind == "progress")
    completed = next(i for i, (k, p) in enumerate(kinds) if k == "job" and
                     p["job"]["state"] == "completed")  # fmt: skip
    ready = next(i for i, (k, p) in enumerate(kinds) if k == "state" and p["state"] == "ready")
    assert last_progress < completed < ready  # never "ready" at 99 %
    final = kinds[last_progress][1]
    assert final["lines"] == 601 and final["completion"] == 100.0 and final["time_left"] == 0


@pytest.mark.parametrize(
    ("options", "toml", "prefix"),
    [
        (["--mqtt-discovery-prefix", "ha"], "", "ha"),
        ([], 'mqtt_discovery_prefix = "ha"\n', "ha"),
        (["--no-mqtt-discovery"], "", None),
    ],
    ids=["option", "toml", "off"],
)
def test_the_discovery_prefix_is_chosen_or_discovery_turned_off(
    bench: Callable[..., BuiltInFake],
    servers: Callable[..., Server],
    broker: int,
    tmp_path: Path,
    options: list[str],
    toml: str,
    prefix: str | None,
) -> None:
    fake = bench()
    config = tmp_path / "server.toml"
    config.write_text(f'{toml}[printers.bench]\nport = "{fake.port}"\n')
    mqtt = ["--mqtt", f"127.0.0.1:{broker}", *options]
    servers({}, "--config", str(config), *mqtt)

    async def scenario() -> dict[str, bytes]:
        await collect(broker, ["hyrel/bench/state"], lambda messages: True)  # it went out
        return await retained(broker, "#")

    found = asyncio.run(scenario())
    assert not configs_of(found, "homeassistant")
    if prefix is not None:  # without --mqtt-commands: no buttons
        configs = configs_of(found, prefix).values()  # the printer's 5, each heater's 2
        assert len(configs) == 9 and not any("command_topic" in c for c in configs)
    else:
        assert [t for t in found if t.endswith("/config")] == []
