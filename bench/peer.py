"""One streaming run of one host, for bench/run.py; prints its own cost as JSON.

    python bench/peer.py ours PORT JOB [hyrel-send options...]
    python bench/peer.py printcore PORT JOB
    python bench/peer.py ideal PORT JOB

``ideal`` is the least a host can do in unbuffered mode: write a framed line, block
until its ok, repeat, with no checks at all. It measures what the fake controller
itself allows one line at a time, which the emulated link's round trip alone does not.

Each host runs in its own process so that its CPU time (user + sys, every thread)
and peak RSS are its own. The clock starts after the imports: both hosts are
measured from reading the job to its last acknowledgement.
"""

from __future__ import annotations

import json
import resource
import sys
import threading
import time
from pathlib import Path


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_ours(port: str, job: str, options: list[str]) -> int:
    from repetrel_host.cli.app import app  # imported already: the clock has not started

    keep = "--history" in options  # bench/run.py --history: the stream is kept
    arguments = [job, "--port", port, *([] if keep else ["--no-history"]), "--no-header", *options]
    code = app(arguments, standalone_mode=False)
    return int(code or 0)


def run_printcore(port: str, job: str) -> int:
    from printrun import gcoder  # imported already: the clock has not started
    from printrun.printcore import printcore

    online, finished = threading.Event(), threading.Event()
    core = printcore()
    core.onlinecb = online.set
    core.endcb = finished.set
    core.connect(port, 115200)
    if not online.wait(10):
        print("printcore: the controller did not answer", file=sys.stderr)
        return 3
    # As printcore's own command line does: the whole file, parsed, then streamed.
    with open(job) as handle:
        lines = [line.strip() for line in handle]
    core.startprint(gcoder.LightGCode(lines))
    finished.wait()
    time.sleep(0.05)  # let the closing "M110 N-1" go out before the port closes
    core.disconnect()
    return 0


def run_ideal(port: str, job: str) -> int:
    import os
    import tty

    from repetrel_host.protocol.framing import frame, reset_command
    from repetrel_host.session.job import Job

    commands = [line.command for line in Job(Path(job)).lines()]
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    pending = b""

    def send_and_wait(data: bytes) -> None:
        nonlocal pending
        os.write(fd, data)
        while b"ok" not in pending:
            pending += os.read(fd, 4096)
        pending = pending[pending.index(b"ok") + 2 :]

    send_and_wait(frame(0, reset_command(0)))
    for number, command in enumerate(commands, start=1):
        send_and_wait(frame(number, command))
    os.close(fd)
    return 0


def main() -> int:
    host, port, job, *options = sys.argv[1:]
    if host == "ours":
        import repetrel_host.cli.app  # noqa: F401
    else:
        import printrun.printcore  # noqa: F401
    started = cpu_seconds()
    if host == "ours":
        code = run_ours(port, job, options)
    elif host == "printcore":
        code = run_printcore(port, job)
    else:
        code = run_ideal(port, job)
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    report = {"code": code, "cpu_seconds": cpu_seconds() - started, "peak_rss_bytes": peak_rss}
    print("PEER " + json.dumps(report), flush=True)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
