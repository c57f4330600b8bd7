"""The fake controller: a :class:`ControllerSimulator` behind a real pseudo-terminal.

Run ``hyrel-fake-controller --link /tmp/hyrel0`` and open ``/tmp/hyrel0`` like a
serial port. Once the pty is ready the process prints ``ready <path>`` on
stdout. ``--log FILE`` writes every executed command, one a line, in order;
``--stats FILE`` writes the link counters as JSON when the process ends
(times on ``time.monotonic()``'s clock, which other processes share).
``--control`` takes requests on stdin, one a line, and answers each with one line
of JSON on stdout (see :meth:`PtyController.control`); the fake stops when stdin
closes, so it never outlives whoever started it.

:class:`BuiltInFake` runs it in a subprocess for the ``fake`` port: the whole path
(process, pty, termios, pyserial) is the real one.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import pty
import select
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO, TextIO

from repetrel_host.errors import LinkError
from repetrel_host.fakes.hyrel_simulator import RX_BUFFER as HYREL_RX_BUFFER
from repetrel_host.fakes.hyrel_simulator import HyrelControllerSimulator
from repetrel_host.fakes.hyrel_simulator import check_faults as check_hyrel_faults
from repetrel_host.fakes.settings import KEEPALIVE_INTERVAL, ControllerSettings, Faults, Overflow
from repetrel_host.fakes.simulator import ControllerSimulator

READ_SIZE = 4096
# Starting Python and the fake takes well under a second; leave room for a slow CI.
FAKE_START_TIMEOUT = 15.0
SPIN = 0.0003  # seconds of polling instead of sleeping: before an event, after a reply


class PtyController:
    """Owns the pty pair and pumps bytes between it and the simulator in real time."""

    def __init__(
        self,
        settings: ControllerSettings,
        link: Path | None = None,
        log: TextIO | None = None,
        received: BinaryIO | None = None,
        control: tuple[BinaryIO, TextIO] | None = None,
        protocol: str = "reprap",
    ) -> None:
        self.link = link
        self._control = control
        self._requests = bytearray()
        self._open_pty()
        self._log = log
        self._received = received
        self._unflushed = False
        simulator = HyrelControllerSimulator if protocol == "hyrel" else ControllerSimulator
        self.simulator = simulator(settings, now=time.monotonic(), on_execute=self._execute)
        self._to_write = bytearray()
        self._poll_until = 0.0
        self._stopping = False
        # stop() comes from a signal handler: select() would sleep on after it (PEP 475
        # retries it), so it also writes here to wake the loop at once.
        self._wake_read, self._wake_write = os.pipe()
        for fd in (self._wake_read, self._wake_write):
            os.set_blocking(fd, False)

    def _open_pty(self) -> None:
        self._master, self._slave = pty.openpty()
        # Raw mode: no echo, no line editing, bytes pass unchanged. We keep the
        # slave open ourselves so that the pty survives the host closing it.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        if self.link is not None:
            if self.link.is_symlink():
                self.link.unlink()  # left behind by an earlier run
            self.link.symlink_to(self.path)

    def _close_pty(self) -> None:
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _drop_link(self, seconds: float, selector: selectors.BaseSelector) -> None:
        """The cable is pulled: the pty goes away, and a new one appears after ``seconds``."""
        selector.unregister(self._master)
        self._close_pty()
        self._to_write.clear()
        self.simulator.unplug()
        time.sleep(seconds)
        self._open_pty()
        selector.register(self._master, selectors.EVENT_READ)

    def _execute(self, command: str) -> None:
        if self._log is not None:
            self._log.write(command + "\n")
            self._unflushed = True

    def stop(self) -> None:
        self._stopping = True
        with contextlib.suppress(OSError):
            os.write(self._wake_write, b"\0")

    def run(self) -> None:
        # select(2) takes its timeout in microseconds; epoll and poll round it up to a
        # whole millisecond, which would add up to 1 ms to every emulated delay.
        selector = selectors.SelectSelector()
        selector.register(self._master, selectors.EVENT_READ)
        selector.register(self._wake_read, selectors.EVENT_READ)
        if self._control is not None:
            selector.register(self._control[0], selectors.EVENT_READ)
        blocked = self.simulator.settings.overflow is Overflow.BLOCK
        try:
            while not self._stopping:
                now = time.monotonic()
                wants_read = not blocked or self.simulator.room() > 0
                events = selectors.EVENT_READ if wants_read else 0
                if self._to_write:
                    events |= selectors.EVENT_WRITE
                if events:
                    selector.modify(self._master, events)
                    timeout = self._timeout(now)
                    ready = selector.select(timeout)
                else:
                    time.sleep(min(self._timeout(now), 0.05))
                    ready = []
                now = time.monotonic()
                for key, mask in ready:
                    if key.fileobj == self._wake_read:
                        continue  # stop() was called
                    if self._control is not None and key.fileobj is self._control[0]:
                        self._read_requests(now)
                    elif mask & selectors.EVENT_READ:
                        self._read(now, blocked)
                    if mask & selectors.EVENT_WRITE:
                        self._flush_writes()
                self.simulator.advance(now)
                if self.simulator.link_drop_requested is not None:
                    seconds = self.simulator.link_drop_requested
                    self.simulator.link_drop_requested = None
                    self._drop_link(seconds, selector)
                    continue
                output = self.simulator.take_output(now)
                if output:
                    self._to_write += output
                    self._flush_writes()
                    # The host answers within microseconds: poll for its next line
                    # rather than sleep, so that a wake-up's delay is not added to it.
                    self._poll_until = now + SPIN
                if self._unflushed:
                    self._flush_logs()
        finally:
            selector.close()

    def _timeout(self, now: float) -> float:
        if now < self._poll_until:
            return 0.0
        wakeup = self.simulator.next_wakeup()
        if wakeup is None:
            return 0.5  # wake now and then to notice stop()
        # Sleeping wakes late (timer slack, scheduling): sleep until shortly before the
        # event, then poll, so that emulated delays are what they say.
        return min(0.5, max(0.0, wakeup - now - SPIN))

    def _read(self, now: float, blocked: bool) -> None:
        size = min(READ_SIZE, self.simulator.room()) if blocked else READ_SIZE
        if size <= 0:
            return
        try:
            data = os.read(self._master, size)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            # EIO: no process has the slave open right now. Ours is open, so
            # this is rare; wait a moment rather than spin.
            time.sleep(0.01)
            return
        self.simulator.receive(data, now)
        if self._received is not None:
            self._received.write(data)
            self._unflushed = True

    def _read_requests(self, now: float) -> None:
        assert self._control is not None
        data = os.read(self._control[0].fileno(), READ_SIZE)
        if not data:
            self.stop()  # whoever started us is gone
            return
        self._requests += data
        while (end := self._requests.find(b"\n")) >= 0:
            request = self._requests[:end].decode("ascii", errors="replace")
            del self._requests[: end + 1]
            self.simulator.advance(now)
            answer = self.control(request, now)
            self._flush_logs()  # what was executed is in the log before the answer
            self._control[1].write(json.dumps(answer) + "\n")
            self._control[1].flush()

    def control(self, request: str, now: float) -> dict[str, object]:
        """A request from the ``--control`` channel: ``status`` (temperatures, fault
        switches and counts, commands executed), or what :meth:`ControllerSimulator.control`
        takes. The answer says ``ok``, or why not in ``error``."""
        simulator = self.simulator
        if request.strip() != "status":
            try:
                simulator.control(request, now)
            except ValueError as exc:
                return {"ok": False, "error": str(exc)}
            return {"ok": True}
        return {
            "ok": True,
            "temperatures": simulator.temperatures(now),
            "faults": dataclasses.asdict(simulator.faults),
            "counts": dataclasses.asdict(simulator.counts),
            "commands": simulator.link.commands,
            "errors": simulator.link.errors,
            "hung": simulator.hung,
        }

    def _flush_writes(self) -> None:
        if not self._to_write:
            return
        try:
            written = os.write(self._master, self._to_write)
        except (BlockingIOError, InterruptedError):
            return
        del self._to_write[:written]

    def _flush_logs(self) -> None:
        for stream in (self._log, self._received):
            if stream is not None:
                stream.flush()
        self._unflushed = False

    def close(self) -> None:
        self._flush_logs()
        self._close_pty()
        for fd in (self._wake_read, self._wake_write):
            with contextlib.suppress(OSError):
                os.close(fd)


class _DefaultsShown(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in --help: argparse's ``(default: X)``, ``off`` for a flag;
    an option whose default is "none" says what that means in its own help."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "(default" in text or action.default is argparse.SUPPRESS:
            return text
        if action.default is False:
            return f"{text} (default: off)"
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hyrel-fake-controller",
        description="A fake motion controller on a pseudo-terminal: Marlin-style, or on "
        "Hyrel's own link (--protocol hyrel). By default it runs every command at once on "
        "an unlimited link; --move-time (or --time-scale), --command-time, --heat-rate, "
        "--bandwidth and --latency slow it down, --faults makes it noisy.",
        formatter_class=_DefaultsShown,
    )
    parser.add_argument(
        "--link",
        type=Path,
        metavar="PATH",
        help="create a symlink to the pty at this path (default: none; the pty's own path "
        "is printed as 'ready PATH')",
    )
    parser.add_argument(
        "--own-link-folder",
        action="store_true",
        help="the folder --link is in is this fake's own: remove it when the fake ends, "
        "even when whoever started it was killed (default: the folder stays)",
    )
    parser.add_argument(
        "--log",
        type=Path,
        metavar="FILE",
        help="write every executed command to this file (default: none)",
    )
    parser.add_argument(
        "--received",
        type=Path,
        metavar="FILE",
        help="write every byte received to this file (default: none)",
    )
    parser.add_argument(
        "--bandwidth", type=float, default=None, help="link bytes/s each way (default: unlimited)"
    )
    parser.add_argument(
        "--latency",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="one-way link delay (default: 0)",
    )
    parser.add_argument(
        "--protocol",
        choices=["reprap", "hyrel"],
        default="reprap",
        help="the link: RepRap/Marlin lines with ok and Resend, or Hyrel's own (ACK bytes, "
        "control bytes, tagged messages, the host watchdog, M0 waits, the M773 report)",
    )
    parser.add_argument(
        "--rx-buffer",
        type=int,
        default=None,
        help=f"receive buffer in bytes (default: 128; {HYREL_RX_BUFFER} with --protocol hyrel)",
    )
    parser.add_argument(
        "--overflow",
        choices=[o.value for o in Overflow],
        default=Overflow.DROP.value,
        help="drop bytes that do not fit (UART) or hold the sender back (USB)",
    )
    parser.add_argument("--slots", type=int, default=4, help="command slots (Marlin BUFSIZE)")
    parser.add_argument("--planner", type=int, default=16, help="planner blocks")
    parser.add_argument(
        "--move-time",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="time a move takes (default: 0, at once)",
    )
    parser.add_argument(
        "--time-scale",
        type=float,
        default=None,
        metavar="X",
        help="each move takes the time the firmware's planner gives it (accelerations, "
        "feed rates, junction speeds, as the host's estimate plans them), divided by X: 100 "
        "runs an hour's print in 36 s; G4 dwells are divided too (default: none, "
        "--move-time's time)",
    )
    parser.add_argument(
        "--command-time",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="time any other command takes (default: 0, at once)",
    )
    parser.add_argument("--no-banner", action="store_true", help="do not say 'start' at boot")
    parser.add_argument(
        "--advanced-ok",
        action="store_true",
        help="answer 'ok N<last line> P<planner free> B<slots free>' (Marlin's ADVANCED_OK)",
    )
    parser.add_argument(
        "--heat-rate",
        type=float,
        default=None,
        help="degrees per second a heater moves toward its target, so that M109 and M190 "
        "wait (default: targets are reached at once)",
    )
    parser.add_argument(
        "--residency",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="a heat wait holds this long once its heater is at the target, its reports "
        "counting down W: (Marlin's TEMP_RESIDENCY_TIME, 10 there) (default: 0)",
    )
    parser.add_argument(
        "--keepalive",
        type=float,
        default=KEEPALIVE_INTERVAL,
        metavar="SECONDS",
        help="'echo:busy: processing' this often while a command holds the queue, heat waits "
        "aside (Marlin's host keepalive; M113 changes it); 0: never",
    )
    parser.add_argument(
        "--extruders",
        type=int,
        default=1,
        metavar="N",
        help="hotends T0..T<N-1>: M104 T<i> for one it does not have is refused, as Marlin "
        "refuses it (on Hyrel's link: heads T0..T<N-1>, T47 every one)",
    )
    parser.add_argument(
        "--no-extruder-count",
        action="store_true",
        help="M115 does not say EXTRUDER_COUNT, as some firmwares (a host learns the hotends "
        "from the commands it sent)",
    )
    parser.add_argument(
        "--chamber", action="store_true", help="a heated chamber (M141, M191; C: in reports)"
    )
    parser.add_argument(
        "--no-emergency-parser",
        action="store_true",
        help="without Marlin's EMERGENCY_PARSER: M108 and M112 run in their turn, so M108 "
        "cannot end a heat wait it queues behind (M115 says Cap:EMERGENCY_PARSER:0)",
    )
    parser.add_argument(
        "--no-autoreport",
        action="store_true",
        help="without Marlin's AUTOREPORT_TEMP: M115 says Cap:AUTOREPORT_TEMP:0 and M155 is "
        "an unknown command, so that a host must poll temperatures (M105)",
    )
    parser.add_argument(
        "--identify-time",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="the first M115 after a start (or a reset) takes this long to run, holding the "
        "commands behind it: a controller slow to say who it is (default: 0, at once)",
    )
    parser.add_argument(
        "--stats",
        type=Path,
        metavar="FILE",
        help="write the link counters here as JSON at exit (default: none)",
    )
    parser.add_argument(
        "--control",
        action="store_true",
        help="take requests on stdin (status, set FAULTS, reset, hang, link_drop S, "
        "heat_rate R), answer each with a line of JSON; stop when stdin closes",
    )
    parser.add_argument(
        "--faults",
        default="",
        help="faults to inject, e.g. 'corrupt=0.02 garble=0.01 drop_ok=0.01 duplicate_ok=0.01 "
        "spurious_resend=0.005 seed=7'; older firmwares' ways: resend_without_ok=1, "
        "flush_on_error=0 (a line error keeps the receive buffer), drop_duplicates=0 (a resent "
        "copy of the last line is refused, not dropped); two controllers' ways: "
        "counted_resend=1 (OctoPrint's "
        "virtual printer's answer to a bad checksum) and drop_with_error=0.01 (lines dropped "
        "with only an error line); with --protocol hyrel: corrupt, garble, drop_ok (ACK "
        "bytes lost), identity_twice=0.1 (M115s answered twice) and unasked_identity=1 (the "
        "identity in an info line after G4 dwells) (default: none)",
    )
    return parser


def settings_from_args(args: argparse.Namespace) -> ControllerSettings:
    if args.rx_buffer is None:
        args.rx_buffer = HYREL_RX_BUFFER if args.protocol == "hyrel" else 128
    if args.identify_time < 0 or args.residency < 0 or args.keepalive < 0:
        raise SystemExit(
            "hyrel-fake-controller: --identify-time, --residency and --keepalive must not be "
            "negative"
        )
    if args.time_scale is not None and args.move_time:
        raise SystemExit(
            "hyrel-fake-controller: --time-scale and --move-time each say how long a move "
            "takes: give one"
        )
    if args.time_scale is not None and not args.time_scale > 0:
        raise SystemExit("hyrel-fake-controller: --time-scale must be above zero")
    if args.rx_buffer < 2 or args.slots < 1 or args.planner < 1 or args.extruders < 1:
        raise SystemExit(
            "hyrel-fake-controller: --rx-buffer, --slots, --planner and --extruders must be "
            "positive"
        )
    try:
        faults = Faults.parse(args.faults)
        if args.protocol == "hyrel":
            check_hyrel_faults(faults)
        elif faults.identity_twice or faults.unasked_identity:
            raise ValueError("identity_twice and unasked_identity are faults of Hyrel's link")
    except ValueError as exc:
        raise SystemExit(f"hyrel-fake-controller: --faults: {exc}") from None
    return ControllerSettings(
        bandwidth=args.bandwidth,
        latency=args.latency,
        rx_buffer=args.rx_buffer,
        overflow=Overflow(args.overflow),
        slots=args.slots,
        planner=args.planner,
        move_time=args.move_time,
        time_scale=args.time_scale,
        command_time=args.command_time,
        banner=not args.no_banner and args.protocol != "hyrel",  # "start" is Marlin's
        advanced_ok=args.advanced_ok,
        heat_rate=args.heat_rate,
        residency=args.residency,
        keepalive=args.keepalive or None,
        faults=faults,
        extruders=args.extruders,
        extruder_count=not args.no_extruder_count,
        chamber=args.chamber,
        emergency_parser=not args.no_emergency_parser,
        autoreport=not args.no_autoreport,
        identify_time=args.identify_time,
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = settings_from_args(args)
    try:
        log = args.log.open("w", encoding="ascii", errors="replace") if args.log else None
        received = args.received.open("wb") if args.received else None
    except OSError as exc:
        print(
            f"hyrel-fake-controller: cannot write {exc.filename}: {exc.strerror}", file=sys.stderr
        )
        return 2
    try:
        control = (sys.stdin.buffer, sys.stdout) if args.control else None
        controller = PtyController(
            settings,
            link=args.link,
            log=log,
            received=received,
            control=control,
            protocol=args.protocol,
        )
    except FileExistsError:
        print(f"hyrel-fake-controller: {args.link} exists and is not a link", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"hyrel-fake-controller: cannot create the pty: {exc.strerror}", file=sys.stderr)
        return 3
    for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(signum, lambda *_: controller.stop())
    try:
        print(f"ready {controller.link or controller.path}", flush=True)
        controller.run()
    except BrokenPipeError:  # whoever started us is gone (killed while we started)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing to flush to
    finally:
        controller.close()
        for stream in (log, received):
            if stream is not None:
                stream.close()
        if args.own_link_folder and args.link is not None:
            with contextlib.suppress(OSError):  # only once it is empty: nothing but ours
                args.link.parent.rmdir()
        if args.stats is not None:
            counters = dataclasses.asdict(controller.simulator.link)
            args.stats.write_text(json.dumps(counters, indent=1) + "\n")
    return 0


class BuiltInFake:
    """The fake controller in a subprocess, on its own pty, for demos and tests.

    The pty is reached through a link in a private folder, so its path stays the same
    when the fake unplugs and replugs it (``!!DEBUG:link_drop``).
    """

    def __init__(
        self, log_path: Path | None = None, extra_args: Sequence[str] = (), control: bool = False
    ) -> None:
        # None: no log (nobody asked for one; a temporary file would be left behind).
        self.log_path = log_path
        self.extra_args = [*extra_args, "--control"] if control else list(extra_args)
        self.control = control
        self.port = ""
        self.process: subprocess.Popen[bytes] | None = None
        self._folder: str | None = None

    def start(self) -> str:
        """Start the fake and return the path of its pty."""
        self._folder = tempfile.mkdtemp(prefix="hyrel-fake-")
        link = Path(self._folder) / "tty"
        command = [
            sys.executable,
            "-m",
            "repetrel_host.fakes.fake_controller",
            "--link",
            str(link),
            "--own-link-folder",  # so that it goes even when this process is killed
            *(["--log", str(self.log_path)] if self.log_path is not None else []),
            *self.extra_args,
        ]
        self.process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stdin=subprocess.PIPE if self.control else subprocess.DEVNULL,
            start_new_session=True,
        )
        assert self.process.stdout is not None
        line = _read_line(self.process.stdout.fileno(), FAKE_START_TIMEOUT)
        if not line.startswith("ready "):
            self.stop()
            raise LinkError("the built-in fake controller did not start")
        self.port = line.split(" ", 1)[1]
        return self.port

    def request(self, text: str, timeout: float = 10.0) -> dict[str, Any]:
        """Send one ``--control`` request and return its answer (started with ``control``)."""
        process = self.process
        if process is None or process.stdin is None or process.stdout is None:
            raise LinkError("the fake controller is not running with --control")
        try:
            process.stdin.write(text.encode("ascii") + b"\n")
            process.stdin.flush()
        except BrokenPipeError:
            raise LinkError("the fake controller has stopped") from None
        line = _read_line(process.stdout.fileno(), timeout)
        if not line:
            raise LinkError(f"the fake controller did not answer '{text}'")
        answer: dict[str, Any] = json.loads(line)
        return answer

    def stop(self) -> None:
        """Stop the fake; its log is complete once this returns."""
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process is not None:
            for stream in (self.process.stdin, self.process.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()
        self.process = None
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def __enter__(self) -> BuiltInFake:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _read_line(fd: int, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    data = b""
    while not data.endswith(b"\n"):
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        readable, _, _ = select.select([fd], [], [], remaining)
        if not readable:
            break
        chunk = os.read(fd, 256)
        if not chunk:
            break
        data += chunk
    return data.decode("ascii", errors="replace").strip()


if __name__ == "__main__":
    raise SystemExit(main())
