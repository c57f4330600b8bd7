"""Soak: a million lines under noise, exactly once? And what does each lost ok cost?

    python bench/soak.py                      # 1,000,000 lines, both flow modes, in memory
    python bench/soak.py --lines 100000 --engine pty
    python bench/soak.py --rx-buffer 4096 --max-lines 96   # a USB link's window
    python bench/soak.py --protocol hyrel     # Hyrel's own link (its noise: see below)

The job is the cone slicer file repeated to ``--lines``. The noise is issue 4's: 2 %
of lines corrupted on the way in, 1 % of replies garbled, 1 % of oks dropped, 1 %
duplicated, 0.5 % spurious resend requests, on a link with ``--latency`` each way.

On Hyrel's own link (``--protocol hyrel``; its 8 KB buffer, the window its 2 KB headroom)
the noise is what that link can survive: 2 % of ACK bytes lost, 1 % of replies garbled
(ACKs, answers and notices among them). A line corrupted on its way has no resend there:
the job stops, naming it (tests/protocol/test_hyrel_dialect.py); it is no part of a soak.

- ``memory`` runs the host core against the simulated controller on simulated time:
  the stall figure is exact and the run is deterministic (same seed, same numbers).
- ``pty`` runs ``hyrel-send`` against ``hyrel-fake-controller`` as real processes.

Printed per flow mode: lines, resend requests, stalls recovered by a probe, faults
injected, time clean and noisy, the mean stall per lost or garbled ok ((noisy - clean)
/ (dropped oks + garbled replies)), the errors the controller answered on the clean link
per 10,000 lines (a healthy link draws none), CPU seconds, and the verdict: the
controller's executed log equals the job, nothing lost, nothing repeated, order kept.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.protocol.dialects.hyrel import HyrelDialect
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.session.job import Job
from repetrel_host.session.loopback import run_loopback
from repetrel_host.session.planning import DEFAULT_WINDOWS

ROOT = Path(__file__).resolve().parent.parent
CONE = ROOT / "tests" / "data" / "cone-prusaslicer.gcode"
NOISE = "corrupt=0.02 garble=0.01 drop_ok=0.01 duplicate_ok=0.01 spurious_resend=0.005"
HYREL_NOISE = "drop_ok=0.02 garble=0.01"
HYREL_RX_BUFFER = 8192


def job_commands(lines: int) -> list[str]:
    cone = [line.command for line in Job(CONE).lines()]
    return list(itertools.islice(itertools.cycle(cone), lines))


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime + children.ru_utime + children.ru_stime


def memory_run(
    commands: list[str],
    mode: FlowMode,
    latency: float,
    faults: str,
    window: tuple[int, int],
    protocol: str,
) -> dict[str, object]:
    rx_buffer, max_lines = window
    flow = FlowControl(mode, rx_buffer=rx_buffer, max_lines=max_lines)
    started = cpu_seconds()
    if protocol == "hyrel":
        settings = ControllerSettings(
            latency=latency, faults=Faults.parse(faults), rx_buffer=HYREL_RX_BUFFER, banner=False
        )
        result = run_loopback(
            commands,
            record=False,
            dialect=HyrelDialect(flow),
            controller=HyrelControllerSimulator(settings),
        )
        executed = [c for c in result.executed if c != "M115"]  # the host's syncs
    else:
        settings = ControllerSettings(
            latency=latency, faults=Faults.parse(faults), rx_buffer=rx_buffer
        )
        result = run_loopback(commands, flow, settings, record=False)
        executed = [c for c in result.executed if c != "M105"]  # the host's probes
    stats, counts = result.host.stats, result.controller.counts
    return {
        "seconds": result.seconds,
        "errors": result.controller.link.errors,
        "exact": result.failure is None and executed == commands,
        "failure": result.failure.reason if result.failure else "",
        "resends": stats.resend_requests,
        "stalls": stats.stalls_recovered,
        "lost_oks": counts.dropped_oks + counts.garbled_replies,
        "faults": counts.corrupted_lines
        + counts.garbled_replies
        + counts.dropped_oks
        + counts.duplicated_oks
        + counts.spurious_resends,
        "cpu": cpu_seconds() - started,
    }


def pty_run(
    commands: list[str],
    mode: FlowMode,
    latency: float,
    faults: str,
    window: tuple[int, int],
    protocol: str,
) -> dict[str, object]:
    rx_buffer, max_lines = (str(value) for value in window)
    fake_buffer = str(HYREL_RX_BUFFER) if protocol == "hyrel" else rx_buffer
    with tempfile.TemporaryDirectory() as folder:
        job = Path(folder) / "soak.gcode"
        job.write_text("\n".join(commands) + "\n")
        log = Path(folder) / "executed.log"
        stats = Path(folder) / "stats.json"
        fake = BuiltInFake(
            log,
            ["--latency", str(latency), "--faults", faults, "--rx-buffer", fake_buffer,
             "--protocol", protocol, "--stats", str(stats)],
        )  # fmt: skip
        fake.start()
        started, wall = cpu_seconds(), time.monotonic()
        try:
            result = subprocess.run(
                [sys.executable, "-m", "repetrel_host.cli", str(job), "--port", fake.port,
                 "--flow", mode.value, "--no-history", "--rx-buffer", rx_buffer,
                 "--max-lines", max_lines, "--protocol", protocol],
                capture_output=True, text=True, check=False,
            )  # fmt: skip
        finally:
            fake.stop()
        errors = json.loads(stats.read_text())["errors"] if stats.exists() else -1
        seconds = time.monotonic() - wall
        # The host's own commands, not the job's (the cone has none of them): its line-number
        # syncs, who are you, and the status line's temperatures (an M155 or M105 polls).
        own = ("M110", "M115", "M155", "M105")
        assert not any(c.startswith(own) for c in commands), "the job sends the host's commands"
        done = [c for c in log.read_text().splitlines() if not c.startswith(own)]
    summary = re.search(r"(\d+) resend requests", result.stdout)
    return {
        "seconds": seconds,
        "errors": errors,
        "exact": result.returncode == 0 and done == commands,
        "failure": result.stderr.strip()[-200:],
        "resends": int(summary.group(1)) if summary else -1,
        "stalls": -1,  # not reported by the CLI
        "lost_oks": -1,
        "faults": -1,
        "cpu": cpu_seconds() - started,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lines", type=int, default=1_000_000)
    parser.add_argument("--flow", choices=["buffered", "unbuffered", "both"], default="both")
    parser.add_argument("--latency", type=float, default=0.001, help="one-way link delay, s")
    parser.add_argument("--engine", choices=["memory", "pty"], default="memory")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--rx-buffer", type=int, help="the window: the controller's buffer (128), or headroom "
        "with --protocol hyrel (2048), bytes"
    )  # fmt: skip
    parser.add_argument("--max-lines", type=int, help="the host's window, lines (8; hyrel 256)")
    parser.add_argument("--protocol", choices=["reprap", "hyrel"], default="reprap")
    args = parser.parse_args()
    default = DEFAULT_WINDOWS[args.protocol]
    window = (args.rx_buffer or default.rx_buffer, args.max_lines or default.max_lines)
    commands = job_commands(args.lines)
    run = memory_run if args.engine == "memory" else pty_run
    modes = list(FlowMode) if args.flow == "both" else [FlowMode(args.flow)]
    noise = HYREL_NOISE if args.protocol == "hyrel" else NOISE
    noisy_faults = f"{noise} seed={args.seed}"
    print(
        f"soak: {args.lines:,} lines, {args.engine}, {args.protocol}, {args.latency * 1000:g} ms "
        f"each way, window {window[0]} bytes / {window[1]} lines"
    )
    print(f"noise: {noisy_faults}")
    header = (
        f"{'mode':<11}{'lines':>10}{'resends':>9}{'stalls':>8}{'lost oks':>9}"
        f"{'clean s':>10}{'noisy s':>10}{'stall/ok s':>11}{'clean err/10k':>14}{'cpu s':>8}"
        "  verdict"
    )
    print(header)
    verdicts = []
    for mode in modes:
        clean = run(commands, mode, args.latency, "", window, args.protocol)
        noisy = run(commands, mode, args.latency, noisy_faults, window, args.protocol)
        lost = int(noisy["lost_oks"])  # type: ignore[call-overload]
        extra = float(noisy["seconds"]) - float(clean["seconds"])  # type: ignore[arg-type]
        stall = f"{extra / lost:.3f}" if lost > 0 else "-"
        errors = int(clean["errors"])  # type: ignore[call-overload]
        per_10k = f"{errors * 10_000 / args.lines:.2f}" if errors >= 0 else "-"
        exact = bool(clean["exact"]) and bool(noisy["exact"])
        verdicts.append(exact)
        verdict = "exactly once" if exact else f"FAILED {noisy['failure'] or clean['failure']}"
        print(
            f"{mode.value:<11}{args.lines:>10,}{noisy['resends']:>9}{noisy['stalls']:>8}"
            f"{lost:>9}{float(clean['seconds']):>10.1f}{float(noisy['seconds']):>10.1f}"  # type: ignore[arg-type]
            f"{stall:>11}{per_10k:>14}{float(noisy['cpu']):>8.1f}  {verdict}"  # type: ignore[arg-type]
        )
    return 0 if all(verdicts) else 1


if __name__ == "__main__":
    raise SystemExit(main())
