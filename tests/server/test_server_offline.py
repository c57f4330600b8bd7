"""A lost printer says since when and why (``since`` and ``reason`` in
``/v1/printers/NAME``): the time stays that of the loss however often the server tries the
port again, the reason is the session's sentence, and both move on once it is back. A real
server on a fake whose pty disappears for a while (its ``link_drop``)."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import Server, wait_for

pytestmark = pytest.mark.timeout(90)


@pytest.mark.slow
def test_an_unplugged_printer_says_since_when_and_why(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> None:
    fake = bench()
    server = servers({"bench": fake.port})
    with server.client() as client:

        def printer() -> dict:
            return client.get("/v1/printers/bench").json()

        ready = wait_for(lambda: printer() if printer()["state"] == "ready" else None)
        dropped_at = time.time()
        assert fake.request("link_drop 4")["ok"]
        offline = wait_for(lambda: printer() if printer()["state"] != "ready" else None)
        assert offline["since"] >= ready["since"] and offline["since"] >= dropped_at - 1
        seen = []
        while time.time() < dropped_at + 3:  # the server tries the port again meanwhile
            seen.append(printer())
            time.sleep(0.2)
        offline_states = [p for p in seen if p["state"] in ("disconnected", "connecting")]
        assert offline_states, seen
        assert {p["since"] for p in offline_states} == {offline["since"]}
        assert all(p["reason"] for p in offline_states)
        assert any("port" in p["reason"] for p in offline_states)
        back = wait_for(lambda: printer() if printer()["state"] == "ready" else None, 30)
        assert back["since"] > offline["since"]
