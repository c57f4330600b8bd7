"""Host protocol against the simulated controller in memory, on simulated time.

No pty, no clock: a 20,000-line job runs in a second, deterministically, so
tests can try many seeds of line corruption and both flow modes.
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import dataclass, field

from repetrel_host.protocol.host import (
    Event,
    Failed,
    FlowControl,
    HostProtocol,
    LineAcknowledged,
)
from repetrel_host.testing.simulator import ControllerSettings, ControllerSimulator

# The smallest step of simulated time when nothing is scheduled.
_TICK = 0.0005


@dataclass
class LoopbackResult:
    executed: list[str]  # what the controller executed, host M110 lines left out
    acknowledged: list[int]  # tags of acknowledged lines, in order
    events: list[Event] = field(repr=False)
    failure: Failed | None
    seconds: float  # simulated time
    host: HostProtocol = field(repr=False)
    controller: ControllerSimulator = field(repr=False)


def corrupt_lines(data: bytes, rate: float, rng: random.Random) -> bytes:
    """Change one byte (never the newline) in each line with probability ``rate``."""
    if rate <= 0 or not data:
        return data
    lines = data.split(b"\n")
    for i, line in enumerate(lines):
        if line and rng.random() < rate:
            position = rng.randrange(len(line))
            replacement = (line[position] + rng.randrange(1, 255)) % 256
            if replacement == 0x0A:
                replacement = 0x0B
            lines[i] = line[:position] + bytes([replacement]) + line[position + 1 :]
    return b"\n".join(lines)


def run_loopback(
    commands: Sequence[str],
    flow: FlowControl | None = None,
    settings: ControllerSettings | None = None,
    *,
    corruption: float = 0.0,
    seed: int = 0,
    line_number_limit: int | None = None,
    time_limit: float = 3600.0,
) -> LoopbackResult:
    """Stream ``commands`` (tagged with their index) until done, failed or ``time_limit``."""
    rng = random.Random(seed)
    host = (
        HostProtocol(flow)
        if line_number_limit is None
        else HostProtocol(flow, line_number_limit=line_number_limit)
    )
    controller = ControllerSimulator(settings)
    events: list[Event] = []
    acknowledged: list[int] = []
    now = 0.0
    host.start(now)
    fed = 0
    while now < time_limit:
        while host.wants_lines and fed < len(commands):
            host.send(commands[fed], fed)
            fed += 1
        controller.receive(corrupt_lines(host.data_to_send(now), corruption, rng), now)
        controller.advance(now)
        host.receive_data(controller.take_output(now), now)
        host.handle_timeout(now)
        while (event := host.next_event()) is not None:
            events.append(event)
            if isinstance(event, LineAcknowledged) and isinstance(event.tag, int):
                acknowledged.append(event.tag)
        if host.failure is not None or (fed == len(commands) and host.is_done):
            break
        upcoming = [t for t in (controller.next_wakeup(), host.next_deadline()) if t is not None]
        now = max(min(upcoming), now + 1e-9) if upcoming else now + _TICK
    executed = [c for c in controller.executed if not c.startswith("M110")]
    return LoopbackResult(executed, acknowledged, events, host.failure, now, host, controller)
