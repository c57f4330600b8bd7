"""Port discovery: which serial ports look like a printer board, ``hyrel-send
--list-ports`` and ``--port auto`` (from the option, ``$HYREL_PORT`` or the configuration),
and ``rh.connect("auto")``."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
import serial.tools.list_ports
from serial.tools.list_ports_common import ListPortInfo
from typer.testing import CliRunner

import repetrel_host as rh
from repetrel_host.cli import app as cli
from repetrel_host.errors import LinkError
from repetrel_host.fakes.fake_controller import BuiltInFake
from repetrel_host.links import ports
from tests.support.helpers import EXAMPLE, hyrel_send

pytestmark = pytest.mark.timeout(60)


def usb_port(
    device: str,
    vid: int,
    pid: int,
    manufacturer: str | None = None,
    product: str | None = None,
    serial_number: str | None = None,
) -> ListPortInfo:
    """A port as pyserial's Linux lister (``SysFS``) builds one for a USB device: the
    sysfs attributes, then ``apply_usb_info`` for the description and hwid."""
    port = ListPortInfo(device, skip_link_detection=True)
    port.vid, port.pid = vid, pid
    port.serial_number = serial_number
    port.location = "1-1.2:1.0"
    port.manufacturer, port.product = manufacturer, product
    port.apply_usb_info()
    return port


def builtin_port(device: str = "/dev/ttyS0") -> ListPortInfo:
    """A built-in UART as pyserial lists it: no USB information ("n/a")."""
    return ListPortInfo(device, skip_link_detection=True)


HYREL_BY_NAME = usb_port("/dev/ttyACM0", 0x1234, 0x0001, "Hyrel 3D", "Hydra controller")
STM32_VCP = usb_port(
    "/dev/ttyACM1", 0x0483, 0x5740, "STMicroelectronics", "STM32 Virtual ComPort", "205C3"
)
MEGA = usb_port("/dev/ttyACM2", 0x2341, 0x0042, "Arduino (www.arduino.cc)", "Mega 2560 R3")
CH340 = usb_port("/dev/ttyUSB0", 0x1A86, 0x7523, None, "USB Serial")
PRUSA = usb_port(
    "/dev/ttyACM3", 0x2C99, 0x0002, "Prusa Research (prusa3d.com)", "Original Prusa i3 MK3"
)
KLIPPER = usb_port("/dev/ttyACM4", 0x1D50, 0x614E, "Klipper", "stm32f446xx")
MOUSE_LIKE = usb_port("/dev/ttyACM5", 0x046D, 0xC52B, "Logitech", "USB Receiver")


@pytest.mark.parametrize(
    ("port", "mark"),
    [
        (HYREL_BY_NAME, ports.HYREL),
        (STM32_VCP, ports.HYREL_OR_MARLIN),
        (MEGA, ports.MARLIN),
        (CH340, ports.MARLIN),
        (PRUSA, ports.MARLIN),
        (usb_port("/dev/ttyUSB1", 0x0403, 0x6001, "FTDI", "FT232R USB UART"), ports.MARLIN),
        (usb_port("/dev/ttyUSB2", 0x10C4, 0xEA60, "Silicon Labs", "CP2102"), ports.MARLIN),
        (usb_port("/dev/ttyACM6", 0x1D50, 0x6029, None, "Marlin USB Device"), ports.MARLIN),
    ],
)
def test_printer_boards_are_candidates(port: ListPortInfo, mark: str) -> None:
    board = ports.classify(port)
    assert board is not None and board.mark == mark
    assert mark in ports.describe(port)


@pytest.mark.parametrize("port", [builtin_port(), KLIPPER, MOUSE_LIKE])
def test_other_ports_are_not(port: ListPortInfo) -> None:
    assert ports.classify(port) is None
    assert "?" not in ports.describe(port)


def test_a_port_line_names_its_usb_identity() -> None:
    line = ports.describe(STM32_VCP)
    assert line.startswith("/dev/ttyACM1  STM32 Virtual ComPort (STMicroelectronics)  ")
    assert "USB 0483:5740  serial 205C3  Hyrel or Marlin-style? (an STM32" in line
    assert ports.describe(builtin_port()) == "/dev/ttyS0  no USB information"


def test_auto_takes_the_only_candidate_and_says_why() -> None:
    choice = ports.choose_auto([builtin_port(), MOUSE_LIKE, MEGA], "$HYREL_PORT")
    assert choice.device == "/dev/ttyACM2"
    assert choice.reason.startswith("port auto ($HYREL_PORT): /dev/ttyACM2, the only serial")
    assert "Marlin-style: an Arduino Mega 2560 R3, USB 2341:0042" in choice.reason


def test_auto_names_the_candidates_or_the_ports() -> None:
    with pytest.raises(LinkError) as several:
        ports.choose_auto([STM32_VCP, builtin_port(), CH340])
    assert str(several.value) == (
        "port auto (--port): 2 serial ports look like printer boards: /dev/ttyACM1 (Hyrel or "
        "Marlin-style?), /dev/ttyUSB0 (Marlin-style?); give one with --port (hyrel-send "
        "--list-ports describes them)"
    )
    with pytest.raises(LinkError, match=r"no serial port looks like .*ports found: /dev/ttyS0;"):
        ports.choose_auto([builtin_port()])
    with pytest.raises(LinkError, match=r"\(no serial ports found; hyrel-send --list-ports"):
        ports.choose_auto([])


# --- as real processes, on this machine's real ports -------------------------------


def this_machines_ports() -> tuple[list[ListPortInfo], list[ListPortInfo]]:
    found = sorted(serial.tools.list_ports.comports())
    return found, [port for port in found if ports.classify(port) is not None]


@pytest.mark.timeout(30)
def test_list_ports_lists_this_machines_ports() -> None:
    found, _ = this_machines_ports()
    result = hyrel_send("--list-ports")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    if not found:
        assert lines == ["no serial ports found"]
    else:
        assert [line.split("  ")[0] for line in lines] == [port.device for port in found]
        assert lines == [ports.describe(port) for port in found]


@pytest.mark.timeout(30)
def test_port_auto_on_this_machine(tmp_path: Path) -> None:
    """Whatever this machine's ports are (none or several candidates: a link failure
    naming them)."""
    found, candidates = this_machines_ports()
    if len(candidates) == 1:
        pytest.skip(f"{candidates[0].device} looks like a printer: the job would go to it")
    for how in (["--port", "auto"], []):
        env = {} if how else {"HYREL_PORT": "auto"}
        result = hyrel_send(str(EXAMPLE), *how, "--no-history", env=env)
        source = "--port" if how else "$HYREL_PORT"
        assert result.returncode == 3
        assert "Traceback" not in result.stderr
        assert result.stderr.startswith(f"link failure: port auto ({source}): ")
        for port in candidates or found:
            assert port.device in result.stderr


@pytest.mark.timeout(30)
def test_port_auto_from_the_configuration(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text('[printer]\nport = "auto"\n')
    _, candidates = this_machines_ports()
    if len(candidates) == 1:
        pytest.skip(f"{candidates[0].device} looks like a printer: the job would go to it")
    result = hyrel_send(str(EXAMPLE), "--config", str(config), "--no-history")
    assert result.returncode == 3
    assert result.stderr.startswith("link failure: port auto ([printer] port): ")


def test_list_ports_takes_no_job() -> None:
    result = hyrel_send(str(EXAMPLE), "--list-ports")
    assert result.returncode == 2
    assert result.stderr.strip() == "error: --list-ports and --history-list take no JOB"


# --- one and several candidates: in this process, comports() replaced ------------


@pytest.mark.timeout(30)
def test_connect_auto_opens_the_only_candidate(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No USB board can exist on the machine the tests run on: comports() is replaced
    by one that lists a built-in UART and the fake controller's pty as an STM32 virtual
    COM port (built as pyserial builds it); the session really opens that pty."""
    with BuiltInFake(tmp_path / "fake.log") as fake:
        board = usb_port(fake.port, 0x0483, 0x5740, "STMicroelectronics", "STM32 VCP")
        monkeypatch.setattr(serial.tools.list_ports, "comports", lambda: [builtin_port(), board])

        async def scenario() -> str:
            async with rh.connect("auto", poll_interval=None) as printer:
                assert printer.port == fake.port
                reply = await printer.command("M115")
                return reply.lines[0]

        assert asyncio.run(scenario()).startswith("FIRMWARE_NAME:")
        # hyrel-send says which port and why, and streams there.
        result = CliRunner().invoke(
            cli.app, [str(EXAMPLE), "--port", "auto", "--history", str(tmp_path / "h")]
        )
    assert result.exit_code == 0, result.output
    assert (
        f"port auto (--port): {fake.port}, the only serial port that looks like a printer "
        "board (Hyrel or Marlin-style: an STM32 virtual COM port" in result.output
    )
    assert "square-tube.gcode: done: 334 lines" in result.output


def test_several_candidates_are_named(monkeypatch: pytest.MonkeyPatch) -> None:
    """As above, comports() replaced: two boards plugged in."""
    monkeypatch.setattr(serial.tools.list_ports, "comports", lambda: [CH340, STM32_VCP])
    result = CliRunner().invoke(cli.app, [str(EXAMPLE), "--port", "auto", "--no-history"])
    assert result.exit_code == 3
    assert "link failure: port auto (--port): 2 serial ports look like printer boards: " in (
        result.output
    )

    async def scenario() -> None:
        async with rh.connect("auto"):
            pass

    with pytest.raises(LinkError, match=r"/dev/ttyACM1 .* /dev/ttyUSB0"):
        asyncio.run(scenario())
