"""The fake controller on Hyrel's link, driven byte by byte on simulated time."""

from __future__ import annotations

import os
import select
import subprocess
import sys
import time
import tty
from pathlib import Path

import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.fakes.hyrel_simulator import (
    M115_REPLY,
    PING_REPLY,
    RESTART_REPLY,
    HyrelControllerSimulator,
)
from repetrel_host.fakes.settings import ControllerSettings, Faults
from repetrel_host.protocol.hyrel import NOTICED, Control, HostReceiver, frame, mark_urgent
from repetrel_host.protocol.reports import ReportReader


class Wire:
    """The host's end: what it wrote, and what came back split as the host splits it."""

    def __init__(self, controller: HyrelControllerSimulator) -> None:
        self.controller = controller
        self.host = HostReceiver()
        self.lines: list[str] = []
        self.now = 0.0

    def send(self, data: bytes) -> None:
        self.controller.receive(data, self.now)

    def run(self, until: float) -> None:
        self.now = until
        self.controller.advance(until)
        self.lines += self.host.feed(self.controller.take_output(until))


def test_every_line_earns_an_ack_and_m_codes_are_noticed_as_they_run() -> None:
    controller = HyrelControllerSimulator()
    wire = Wire(controller)
    wire.send(frame("G28") + frame("M104 T11 S200", 15) + frame("G1 X5", 16, checksum=True))
    wire.run(0.1)
    assert wire.host.take_acks() == 3
    assert controller.executed == ["G28", "M104 T11 S200", "G1 X5"]
    assert wire.lines == [">MC:M104: T11: S200:"]
    assert controller.temperatures(0.1)["T"][1] == 200.0


@pytest.mark.parametrize("code", sorted(NOTICED | {"M73", "M82", "M204", "M220", "M221"}))
def test_the_fake_notices_exactly_the_m_codes_the_host_awaits_notices_of(code: str) -> None:
    wire = Wire(HyrelControllerSimulator())
    wire.send(frame(f"{code} S1"))
    wire.run(0.1)
    notices = [line for line in wire.lines if line.startswith(">MC:")]
    assert notices == ([f">MC:{code}: S1:"] if code in NOTICED else [])


def test_acks_wait_for_headroom_in_the_receive_buffer() -> None:
    settings = ControllerSettings(rx_buffer=200, slots=1, command_time=1.0, banner=False)
    controller = HyrelControllerSimulator(settings, ack_headroom=150)
    wire = Wire(controller)
    wire.send(b"".join(frame(f"M117 line {i}") for i in range(8)))  # 13 bytes each
    wire.run(0.0)
    # One line in the slot, the rest in the buffer: once it has less than 150 bytes free,
    # the lines that come are owed their ACK.
    early = wire.host.take_acks()
    assert 0 < early < 8 and controller.owed_acks == 8 - early
    wire.run(30.0)  # every command done: the buffer emptied, every line acknowledged
    assert wire.host.take_acks() == 8 - early and controller.owed_acks == 0
    assert len(controller.executed) == 8


def test_a_bad_checksum_is_reported_and_not_run() -> None:
    controller = HyrelControllerSimulator()
    wire = Wire(controller)
    wire.send(b"N7 G1 X5*1\n" + frame("G1 X6"))
    wire.run(0.1)
    assert wire.lines == [">ER: checksum mismatch (line 7): not run"]
    assert controller.executed == ["G1 X6"] and wire.host.take_acks() == 2


def test_control_bytes_ping_pause_end_wait_abort_and_urgent_lines() -> None:
    settings = ControllerSettings(rx_buffer=8192, move_time=0.5, banner=False)
    controller = HyrelControllerSimulator(settings)
    wire = Wire(controller)
    wire.send(bytes([Control.PING]))
    wire.run(0.01)
    assert wire.lines == [PING_REPLY.decode().strip()]
    wire.send(bytes([Control.PAUSE_AT_MOVE_END]) + frame("M107") + frame("G1 X1"))
    wire.run(5.0)
    assert controller.executed == []  # held
    wire.send(bytes([Control.END_WAIT]))
    wire.run(10.0)
    assert controller.executed == ["M107", "G1 X1"] and wire.host.end_wait_echoes == 1
    moves = b"".join(frame(f"G1 X{i}") for i in range(2, 40))
    wire.send(moves + mark_urgent(frame("M104 S0")))
    wire.run(10.2)
    # It ran while moves sent before it still wait (the planner took the first 16).
    assert "M104 S0" in controller.executed and "G1 X39" not in controller.executed
    wire.send(bytes([Control.ABORT]))
    wire.run(10.3)
    done = len(controller.executed)
    wire.run(60.0)
    assert len(controller.executed) == done < 40  # nothing after the abort
    assert ">IN: aborted: every queued command dropped" in wire.lines


def test_the_watchdog_stops_the_extruders_when_the_host_falls_silent() -> None:
    controller = HyrelControllerSimulator(watchdog=30.0)
    wire = Wire(controller)
    wire.send(frame("M104 S200"))
    wire.run(29.0)
    assert controller.watchdog_trips == 0
    wire.send(bytes([Control.WATCHDOG]))  # a keepalive
    wire.run(58.0)
    assert controller.watchdog_trips == 0 and controller.temperatures(58.0)["T"][1] == 200.0
    wire.run(60.0)
    assert controller.watchdog_trips == 1
    assert controller.temperatures(60.0)["T"][1] == 0.0
    assert wire.lines[-1] == ">ER: host watchdog: no byte for 30 s; every extruder stopped"
    wire.run(200.0)
    assert controller.watchdog_trips == 1  # once, until the host is heard again


@pytest.mark.timeout(30)
def test_the_pty_fake_speaks_hyrels_link(tmp_path: Path) -> None:
    log = tmp_path / "executed.log"
    with BuiltInFake(log, ["--protocol", "hyrel", "--no-banner"], control=True) as fake:
        port = os.open(fake.port, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(port)
            receiver = HostReceiver()
            os.write(port, bytes([Control.PING]) + frame("G28", 1) + frame("M104 S200", 2))
            lines: list[str] = []
            deadline = time.monotonic() + 10
            while (len(lines) < 2 or receiver.acks < 2) and time.monotonic() < deadline:
                if select.select([port], [], [], 0.5)[0]:
                    lines += receiver.feed(os.read(port, 4096))
        finally:
            os.close(port)
        fake.request("status")  # the log is complete
    assert lines == [PING_REPLY.decode().strip(), ">MC:M104: S200:"]
    assert receiver.take_acks() == 2
    assert log.read_text().splitlines() == ["G28", "M104 S200"]


def test_m0_waits_until_end_wait_and_urgent_lines_keep_their_order() -> None:
    controller = HyrelControllerSimulator()
    wire = Wire(controller)
    wire.send(frame("G28") + frame("M0") + frame("G1 X1"))
    wire.run(1.0)
    assert controller.executed == ["G28", "M0"] and wire.lines == [">MC:M0:"]
    wire.send(mark_urgent(frame("M104 S0")) + mark_urgent(frame("M140 S0")))
    wire.send(bytes([Control.END_WAIT]))
    wire.run(2.0)
    assert controller.executed == ["G28", "M0", "M104 S0", "M140 S0", "G1 X1"]


def test_m772_arms_the_m773_report_that_m30_sends_before_its_notice() -> None:
    controller = HyrelControllerSimulator()
    wire = Wire(controller)
    moves = ["G1 X10 F600", "G1 X20 E2", "G91", "G1 Y10", "G90", "M30"]
    wire.send(frame("G1 X5") + frame("M772 S1") + b"".join(frame(m) for m in moves))
    wire.run(1.0)
    report = ReportReader()
    shown = [line for text in wire.lines for line in report.feed(text)]
    assert shown == [">MC:M772: S1:", ">MC:M30:"]
    assert report.report is not None and report.report.complete
    fields = report.report.fields
    # Counted from M772 (the fake starts from X0): 10 mm at 600 mm/min, 10 mm extruding,
    # 10 mm in Y.
    assert fields["Printing moves"] == ["1.0", "0.010"]
    assert fields["Non-printing moves"] == ["2.0", "0.020"]
    assert fields["Totals"] == ["3.0", "0.030"]
    assert fields["approx filament (E)"] == ["0.002 m"]


def test_acks_lost_on_the_way_and_faults_that_are_marlins_refused() -> None:
    settings = ControllerSettings(rx_buffer=8192, banner=False, faults=Faults(drop_ok=0.5))
    controller = HyrelControllerSimulator(settings)
    wire = Wire(controller)
    wire.send(b"".join(frame(f"G1 X{i}") for i in range(100)))
    wire.run(1.0)
    assert wire.host.take_acks() == 100 - controller.counts.dropped_oks
    assert 25 < controller.counts.dropped_oks < 75 and len(controller.executed) == 100
    with pytest.raises(ValueError, match="'spurious_resend' is not a fault of Hyrel's link: it"):
        controller.control("set spurious_resend=0.1", 1.0)
    with pytest.raises(ValueError, match="'flush_on_error' is not a fault of Hyrel's link"):
        HyrelControllerSimulator(ControllerSettings(faults=Faults(flush_on_error=False)))
    with pytest.raises(ValueError, match="ACKs sent twice cannot be told from two"):
        HyrelControllerSimulator(ControllerSettings(faults=Faults(duplicate_ok=0.01)))


def test_a_reset_says_so_with_a_hyrel_identity_line() -> None:
    controller = HyrelControllerSimulator()
    wire = Wire(controller)
    wire.send(frame("!!DEBUG:reset"))
    wire.run(0.1)
    assert wire.lines == [RESTART_REPLY.decode().strip()]


def test_an_identity_said_twice_and_one_unasked_after_a_dwell() -> None:
    faults = Faults(identity_twice=1.0, unasked_identity=1.0)
    settings = ControllerSettings(rx_buffer=8192, banner=False, faults=faults)
    wire = Wire(HyrelControllerSimulator(settings))
    wire.send(frame("M115") + frame("G4 P500") + frame("G1 X1"))
    wire.run(0.1)
    answer = M115_REPLY.decode().strip()
    assert wire.lines == [answer, answer]  # at once, nothing between them
    wire.run(0.6)
    assert wire.lines[2:] == [f">IN: {answer}"]  # once the dwell ended, unasked
    assert wire.controller.executed == ["M115", "G4 P500", "G1 X1"]
    # They are this link's: Marlin's fake refuses them.
    fake = subprocess.run(
        [sys.executable, "-m", "repetrel_host.fakes.fake_controller", "--faults",
         "identity_twice=1"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert fake.returncode != 0
    assert fake.stderr.strip() == (
        "hyrel-fake-controller: --faults: identity_twice and unasked_identity are faults of "
        "Hyrel's link"
    )
