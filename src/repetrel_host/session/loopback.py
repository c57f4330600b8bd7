"""The pump against the simulated controller in memory, on simulated time.

No pty, no clock: a 20,000-line job runs in a second, deterministically, so
tests can try many seeds of line corruption and both flow modes. The framed
preview (``hyrel-send --dry-run --framed``) is the same exchange without faults.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.fakes.simulator import ControllerSimulator
from repetrel_host.protocol.dialect import Dialect
from repetrel_host.protocol.dialects import create_dialect
from repetrel_host.protocol.dialects.reprap import RepRapDialect
from repetrel_host.protocol.events import DialectFailed, ProbeKind
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.session.job import JobLine
from repetrel_host.session.pump import JobRun, Listener, Pump

# The smallest step of simulated time when nothing is scheduled.
_TICK = 0.0005
_STUCK_LIMIT = 10_000  # steps of simulated time that get nowhere


@dataclass
class LoopbackResult:
    executed: list[str]  # what the controller executed, the host's own lines left out
    acknowledged: list[int]  # indexes (from 0) of acknowledged commands, in order
    failure: DialectFailed | None
    seconds: float  # simulated time
    host: Dialect = field(repr=False)
    controller: ControllerSimulator = field(repr=False)
    run: JobRun = field(repr=False)


class _Recorder(Listener):
    def __init__(self, record: bool) -> None:
        self.record = record
        self.indexes: list[int] = []
        self.failure: DialectFailed | None = None

    def acknowledged(self, line: JobLine) -> None:
        if self.record:
            self.indexes.append(line.index - 1)

    def failed(self, failure: DialectFailed) -> None:
        self.failure = failure


def job_lines(commands: Iterable[str]) -> Iterator[JobLine]:
    """Commands as job lines, numbered from 1 (the first command is line 1)."""
    for index, command in enumerate(commands, start=1):
        yield JobLine(index, index, command, index, "job")


def run_loopback(
    commands: Sequence[str],
    flow: FlowControl | None = None,
    settings: ControllerSettings | None = None,
    *,
    line_number_limit: int | None = None,
    probe: ProbeKind | None = None,
    time_limit: float = 36_000.0,
    record: bool = True,
    dialect: Dialect | None = None,
    controller: ControllerSimulator | None = None,
) -> LoopbackResult:
    """Stream ``commands`` until confirmed, failed or ``time_limit``.

    ``record=False`` keeps no acknowledgements (for million-line soaks). ``probe``
    None lets the greeting find out how to probe, as a real connection does.
    """
    host = dialect or (
        RepRapDialect(flow, probe=probe)
        if line_number_limit is None
        else RepRapDialect(flow, line_number_limit=line_number_limit, probe=probe)
    )
    controller = controller or ControllerSimulator(settings)
    # Each line as it first went: (command, the host's own, its number).
    sends: list[tuple[str, bool, int | None]] = []
    if record:
        host.on_first_send = lambda command, _tag, own, number: sends.append((command, own, number))
    recorder = _Recorder(record)
    pump = Pump(host, recorder)
    run = JobRun(job_lines(commands))
    pump.begin(run)
    now = 0.0
    stuck = 0
    wire = bytearray(pump.start(now))  # written by the host, not yet taken by the controller
    while now < time_limit and not run.finished:
        pump.timeout(now)
        sent = pump.poke(now)
        wire += sent
        controller.receive_from(wire, now)
        controller.advance(now)
        received = controller.take_output(now)
        pump.receive(received, now)
        if sent or received:
            continue  # let each side answer at the same instant, as the real pump does
        upcoming = [t for t in (controller.next_wakeup(), pump.deadline) if t is not None]
        previous, now = now, max(min(upcoming), now + 1e-9) if upcoming else now + _TICK
        stuck = stuck + 1 if now - previous < 1e-6 else 0
        if stuck > _STUCK_LIMIT:
            raise AssertionError(f"no progress at t={now}: a deadline that nothing moves")
    executed = [c for c in controller.executed if not c.startswith("M110")]
    if record:
        assert controller.executed_numbers is not None
        executed = _callers_lines(controller.executed, controller.executed_numbers, sends)
    return LoopbackResult(executed, recorder.indexes, recorder.failure, now, host, controller, run)


def _callers_lines(
    executed: list[str], numbers: list[int | None], sends: list[tuple[str, bool, int | None]]
) -> list[str]:
    """What the controller ran (with each line's number), without the host's own lines: its
    M110s, and its probes (a numbered M105 runs), told apart from the caller's by their
    numbers. The controller runs lines in the order they first went (where they ran at
    all: a greeting given up, a job stopped); where it ran something that never went,
    that stays, for a test to see."""
    sent = [item for item in sends if not item[0].startswith("M110")]
    callers: list[str] = []
    position = 0
    for command, number in zip(executed, numbers, strict=True):
        if command.startswith("M110"):
            continue
        index = position
        while index < len(sent) and sent[index][::2] != (command, number):
            index += 1
        if index < len(sent):
            if not sent[index][1]:
                callers.append(command)
            position = index + 1
        else:
            callers.append(command)
    return callers


# Heavy random noise, as the property test in tests/protocol/test_loopback.py and
# bench/noise_loops.py draw it: jobs of these commands, each fault at one of these rates.
NOISE_COMMANDS = ("G1 X1 Y2 E3", "G28", "M105", "G4 P1", "G92 E0", "M400", "T1")
NOISE_RATES = (0.0, 0.01, 0.05, 0.15)
NOISE_FAULTS = ("corrupt", "garble", "drop_ok", "duplicate_ok", "spurious_resend")


def run_noisy_job(
    commands: Sequence[str],
    mode: FlowMode,
    rates: Sequence[float],
    marlin: tuple[bool, bool, bool],
    seed: int,
    rx_buffer: int,
    line_number_limit: int,
) -> LoopbackResult:
    """One job under heavy noise: ``rates`` for NOISE_FAULTS in order; ``marlin`` switches
    Marlin's flush_on_error, drop_duplicates and resend_without_ok."""
    corrupt, garble, drop_ok, duplicate_ok, spurious_resend = rates  # NOISE_FAULTS' order
    faults = Faults(
        corrupt=corrupt,
        garble=garble,
        drop_ok=drop_ok,
        duplicate_ok=duplicate_ok,
        spurious_resend=spurious_resend,
        flush_on_error=marlin[0],
        drop_duplicates=marlin[1],
        resend_without_ok=marlin[2],
        seed=seed,
    )
    settings = ControllerSettings(
        latency=0.001, rx_buffer=rx_buffer, bandwidth=20_000, faults=faults
    )
    return run_loopback(
        commands,
        FlowControl(mode, rx_buffer=rx_buffer),
        settings,
        line_number_limit=line_number_limit,
        time_limit=1200.0,
    )


def run_noise_case(case: int) -> tuple[list[str], LoopbackResult]:
    """Case ``case`` of ``bench/noise_loops.py``'s random jobs (its draws seeded by the
    number): the job's commands, and how it ran under :func:`run_noisy_job`."""
    rng = random.Random(case)
    commands = [rng.choice(NOISE_COMMANDS) for _ in range(rng.randint(1, 150))]
    mode = rng.choice(list(FlowMode))
    rates = [rng.choice(NOISE_RATES) for _ in NOISE_FAULTS]
    marlin = (rng.random() < 0.5, rng.random() < 0.5, rng.random() < 0.5)
    rx_buffer, limit = rng.randint(40, 256), rng.randint(5, 500)
    seed = rng.randint(0, 65536)
    return commands, run_noisy_job(commands, mode, rates, marlin, seed, rx_buffer, limit)


def wire_preview(
    commands: Iterable[str], flow: FlowControl | None = None, protocol: str = "reprap"
) -> Iterator[bytes]:
    """The bytes a clean exchange with a simulated controller puts on the wire, lazily.

    Used by ``hyrel-send --dry-run --framed``: the pump drives a simulated controller
    without faults, so the greeting, probes and any renumbering show (on Hyrel's link:
    the ping, the numbered lines and the M115 that confirms the end).
    """
    controller: ControllerSimulator
    if protocol == "hyrel":
        controller = HyrelControllerSimulator()
    else:
        controller = ControllerSimulator(ControllerSettings(banner=False))
    pump = Pump(create_dialect(protocol, flow))
    run = JobRun(job_lines(commands))
    pump.begin(run)
    now = 0.0
    sent = pump.start(now)
    while True:
        if sent:
            yield sent
        controller.receive(sent, now)
        controller.advance(now)
        received = controller.take_output(now)
        pump.receive(received, now)
        if run.finished:
            return
        sent = pump.poke(now)
        if not sent and not received:
            wakeup = controller.next_wakeup()  # a dwell still running
            if wakeup is None:
                return
            now = max(wakeup, now)
