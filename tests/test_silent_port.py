"""A port that does not answer is no silence: where, at once; each greeting that goes again,
as it goes; then one sentence naming the port, the baud rate and the likely causes. Real
processes on a bare pseudo-terminal that never answers (nothing reads its other end)."""

from __future__ import annotations

import asyncio
import os
import pty
import tty
from collections.abc import Iterator

import pytest

import repetrel_host as rh
from repetrel_host.protocol.dialects import hyrel, reprap

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


@pytest.mark.timeout(30)
@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_the_python_api_hears_each_retry_before_connect_returns(
    silent_port: str, protocol: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The same greeting, on a shorter clock: the test needs the order, not the seconds.
    module = reprap if protocol == "reprap" else hyrel
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
