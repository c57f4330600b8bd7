"""A closed session has let go of its port: whoever opens it next (a connect after
OctoPrint's disconnect or Moonraker's restart, another program) finds it free at once. A
serial transport closes its file in the background, after what it still holds is written;
closing waits for that."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
import serial

import repetrel_host as rh
from repetrel_host.fakes.fake_controller import BuiltInFake

pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize("protocol", ["reprap", "hyrel"])
def test_a_closed_session_leaves_its_port_free_for_the_next_program(
    tmp_path: Path, protocol: str
) -> None:
    async def scenario(port: str) -> None:
        for _ in range(3):
            printer = await rh.connect(port, protocol=protocol, reconnect=False)
            await printer.command("M105")
            await printer.close()
            serial.Serial(port, 115200, exclusive=True).close()  # no "port is busy"

    with BuiltInFake(tmp_path / "executed.log", ["--protocol", protocol]) as fake:
        asyncio.run(scenario(fake.port))
