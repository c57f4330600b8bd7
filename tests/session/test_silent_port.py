"""A port that does not answer is no silence: where, at once; each greeting that goes again,
as it goes; then one sentence naming the port, the baud rate and the likely causes. Real
processes on a bare pseudo-terminal that never answers (nothing reads its other end)."""

from __future__ import annotations

import asyncio
import os
import pty
import subprocess
import sys
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import repetrel_host as rh
from repetrel_host.protocol.dialects import hyrel, reprap_greeting
from tests.support.server import Server

CAUSES = ("the wrong port", "the wrong baud rate", "the board still booting")


@pytest.fixture
def silent_port() -> Iterator[str]:
    """A serial port whose controller never says a word."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def timed_stderr(*args: str) -> tuple[list[tuple[float, str]], float, int, str]:
    """Run hyrel-send; its stderr lines with the seconds each came at, when it ended, its
    exit code and its stdout."""
    environment = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    started = time.monotonic()
    process = subprocess.Popen(
        [sys.executable, "-m", "repetrel_host.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        env=environment,
    )
    assert process.stderr is not None and process.stdout is not None
    lines = [(time.monotonic() - started, line.rstrip("\n")) for line in process.stderr]
    code = process.wait(timeout=30)
    return lines, time.monotonic() - started, code, process.stdout.read()


def assert_told_as_it_went(
    lines: list[tuple[float, str]], ended: float, port: str, hello_timeout: float
) -> str:
    """connecting..., each retry, the sentence, in that order and each when it happened;
    the sentence is returned."""
    assert "Traceback" not in "\n".join(text for _, text in lines)
    texts = [text for _, text in lines]
    assert texts[:3] == [
        f"connecting to {port} at 115200 baud...",
        "no answer yet: greeting again, 2 of 3",
        "no answer yet: greeting again, 3 of 3",
    ], texts
    assert len(texts) == 4, texts
    (connecting, _), (first_retry, _), (second_retry, _) = lines[:3]
    # At once, before the first greeting could time out; each retry a timeout later, as it
    # goes, not all at the end.
    margin = hello_timeout / 2
    assert connecting < first_retry - margin
    assert first_retry < second_retry - margin
    assert second_retry < ended - margin
    return texts[3]


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_hyrel_send_says_where_it_connects_each_retry_and_why_it_gave_up(
    tmp_path: Path, silent_port: str
) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    lines, ended, code, stdout = timed_stderr(str(job), "--port", silent_port)
    sentence = assert_told_as_it_went(lines, ended, silent_port, reprap_greeting.HELLO_TIMEOUT)
    assert code == 3 and stdout == ""
    assert sentence == (
        f"link failure: {silent_port} at 115200 baud: no answer to M110 (line numbering "
        "reset), sent 3 times in 9 s; likely the wrong port, the wrong baud rate, or the "
        "board still booting"
    )


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_on_hyrels_link_too(tmp_path: Path, silent_port: str) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    lines, ended, code, _ = timed_stderr(str(job), "--port", silent_port, "--protocol", "hyrel")
    sentence = assert_told_as_it_went(lines, ended, silent_port, hyrel.HELLO_TIMEOUT)
    assert code == 3
    assert sentence.startswith(
        f"link failure: {silent_port} at 115200 baud: no answer to Hyrel's ping (0x07), "
        "sent 3 times in 9 s; likely"
    )
    assert all(cause in sentence for cause in CAUSES) and "Hyrel's own link" in sentence


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_console_says_it_as_well(silent_port: str) -> None:
    lines, ended, code, _ = timed_stderr("--console", "--port", silent_port)
    sentence = assert_told_as_it_went(lines, ended, silent_port, reprap_greeting.HELLO_TIMEOUT)
    assert code == 3
    assert sentence.startswith(f"link failure: {silent_port} at 115200 baud: no answer")
    assert all(cause in sentence for cause in CAUSES)


@pytest.mark.timeout(30)
@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_the_python_api_hears_each_retry_before_connect_returns(
    silent_port: str, protocol: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The same greeting, on a shorter clock: the test needs the order, not the seconds.
    module = reprap_greeting if protocol == "reprap" else hyrel
    monkeypatch.setattr(module, "HELLO_TIMEOUT", 0.3)
    heard: list[object] = []

    async def scenario() -> None:
        with pytest.raises(rh.LinkError) as failure:
            await rh.connect(silent_port, protocol=protocol, reconnect=False, on_event=heard.append)
        heard.append(failure.value)

    asyncio.run(scenario())
    retries = [event for event in heard if isinstance(event, rh.NoAnswerYet)]
    assert [(r.port, r.baud, r.attempt, r.attempts) for r in retries] == [
        (silent_port, 115200, 2, 3),
        (silent_port, 115200, 3, 3),
    ]
    assert retries[0].text == "no answer yet: greeting again, 2 of 3"
    assert 0.3 <= retries[0].waited < retries[1].waited
    error = heard[-1]  # after every retry
    assert isinstance(error, rh.LinkError)
    assert str(error).startswith(f"{silent_port} at 115200 baud: no answer to ")
    assert all(cause in str(error) for cause in CAUSES)


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_servers_printer_log_tells_each_retry(
    silent_port: str, servers: Callable[..., Server]
) -> None:
    server = servers({"mute": silent_port})
    prefix = "repetrel_host.server: printer mute:"
    expected = [
        f"INFO {prefix} connecting to {silent_port}",
        f"INFO {prefix} {silent_port} at 115200 baud: no answer yet: greeting again, 2 of 3",
        f"INFO {prefix} {silent_port} at 115200 baud: no answer yet: greeting again, 3 of 3",
        f"WARNING {prefix} {silent_port} at 115200 baud: no answer to M110 (line numbering "
        "reset), sent 3 times in 9 s; likely the wrong port, the wrong baud rate, or the "
        "board still booting (trying again)",
    ]

    def told() -> list[str]:
        return [line for line in server.stderr.read_text().splitlines() if prefix in line]

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and len(told()) < len(expected):
        time.sleep(0.2)
    assert told()[: len(expected)] == expected
