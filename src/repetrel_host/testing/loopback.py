"""Host protocol against the simulated controller in memory, on simulated time.

No pty, no clock: a 20,000-line job runs in a second, deterministically, so
tests can try many seeds of line corruption and both flow modes.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from repetrel_host.protocol.host import (
    Event,
    Failed,
    FlowControl,
    HostProtocol,
    LineAcknowledged,
)
from repetrel_host.testing.simulator import ControllerSettings, ControllerSimulator, Overflow

# The smallest step of simulated time when nothing is scheduled.
_TICK = 0.0005
_STUCK_LIMIT = 10_000  # steps of simulated time that get nowhere


@dataclass
class LoopbackResult:
    executed: list[str]  # what the controller executed, host M110 lines left out
    acknowledged: list[int]  # tags of acknowledged lines, in order
    events: list[Event] = field(repr=False)
    failure: Failed | None
    seconds: float  # simulated time
    host: HostProtocol = field(repr=False)
    controller: ControllerSimulator = field(repr=False)


def run_loopback(
    commands: Sequence[str],
    flow: FlowControl | None = None,
    settings: ControllerSettings | None = None,
    *,
    line_number_limit: int | None = None,
    time_limit: float = 36_000.0,
    record: bool = True,
) -> LoopbackResult:
    """Stream ``commands`` (tagged with their index) until confirmed, failed or ``time_limit``.

    ``record=False`` keeps no events and no acknowledgements (for million-line soaks).
    """
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
    stuck = 0
    wire = bytearray()  # written by the host, not yet taken by a controller that pushes back
    block = controller.settings.overflow is Overflow.BLOCK
    while now < time_limit:
        host.handle_timeout(now)
        while host.wants_lines and fed < len(commands):
            host.send(commands[fed], fed)
            fed += 1
        if fed == len(commands):
            host.request_sync()
        sent = host.data_to_send(now)
        wire += sent
        taken = min(len(wire), controller.room()) if block else len(wire)
        controller.receive(bytes(wire[:taken]), now)
        del wire[:taken]
        controller.advance(now)
        received = controller.take_output(now)
        host.receive_data(received, now)
        while (event := host.next_event()) is not None:
            if not record:  # long soaks: keep only what the verdict needs
                continue
            events.append(event)
            if isinstance(event, LineAcknowledged) and isinstance(event.tag, int):
                acknowledged.append(event.tag)
        if host.failure is not None or (fed == len(commands) and host.is_done):
            break
        if sent or received:
            continue  # let each side answer at the same instant, as the real pump does
        upcoming = [t for t in (controller.next_wakeup(), host.next_deadline()) if t is not None]
        previous, now = now, max(min(upcoming), now + 1e-9) if upcoming else now + _TICK
        stuck = stuck + 1 if now - previous < 1e-6 else 0
        if stuck > _STUCK_LIMIT:
            raise AssertionError(f"no progress at t={now}: a deadline that nothing moves")
    executed = [c for c in controller.executed if not c.startswith("M110")]
    return LoopbackResult(executed, acknowledged, events, host.failure, now, host, controller)


def wire_preview(commands: Iterable[str], flow: FlowControl | None = None) -> Iterator[bytes]:
    """The bytes a clean exchange with a Marlin-style controller puts on the wire, lazily.

    Used by ``hyrel-send --dry-run --framed``: the host core drives a simulated
    controller without faults, so the greeting, pings and any renumbering show.
    """
    host = HostProtocol(flow)
    controller = ControllerSimulator(ControllerSettings(banner=False))
    clock = [0.0]
    host.start(0.0)

    def exchange() -> Iterator[bytes]:
        while True:
            now = clock[0]
            sent = host.data_to_send(now)
            if sent:
                yield sent
            controller.receive(sent, now)
            controller.advance(now)
            received = controller.take_output(now)
            host.receive_data(received, now)
            if not sent and not received:
                wakeup = controller.next_wakeup()  # a dwell still running
                if wakeup is None:
                    return
                clock[0] = max(wakeup, now)

    for command in commands:
        host.send(command)
        yield from exchange()
    host.request_sync()
    yield from exchange()
