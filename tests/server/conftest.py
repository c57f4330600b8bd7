"""What the server's tests share beyond tests/support/server.py's fixtures."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.server import Server


@pytest.fixture
def printer(
    bench: Callable[..., BuiltInFake], servers: Callable[..., Server]
) -> tuple[Server, BuiltInFake]:
    """A server with one printer, ``bench``, on the fake controller, ready (a test file
    may make its own ``printer`` instead)."""
    fake = bench()
    server = servers({"bench": fake.port})
    server.wait_ready("bench")
    return server, fake
