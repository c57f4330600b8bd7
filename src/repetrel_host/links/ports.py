"""Serial port discovery: ``hyrel-send --list-ports`` and ``--port auto``.

The ports come from pyserial's ``serial.tools.list_ports.comports()``; each is classified
by its USB identity (vendor and product IDs, the names the device gives) as a likely
printer board or not. A port without USB information (a built-in ``ttyS*``) is never
a candidate: no printer board hides behind one that a host could tell.

Where the list comes from: OctoPrint (``octoprint.util.comm.serialList``) and Printrun
(``pronsole.scanserial``) only glob device names (``/dev/ttyUSB*``, ``/dev/ttyACM*``...)
and try each; Cura's USB printing (``USBPrinterOutputDeviceManager.getSerialPortList``,
``only_list_usb``) keeps the ports whose ``hwid`` is USB, as here. Klipper's boards
enumerate as ``1d50:614e`` ("usb-Klipper_..." in ``/dev/serial/by-id``) and speak
Klipper's own protocol, not G-code: they are not candidates. The IDs below are the USB
chips and boards Marlin-style printers ship with, and STMicroelectronics' virtual COM
port, which Hyrel's STM32-based controllers (and STM32 Marlin boards) present.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from repetrel_host.errors import LinkError

if TYPE_CHECKING:
    from serial.tools.list_ports_common import ListPortInfo

AUTO_PORT = "auto"

HYREL = "Hyrel?"
MARLIN = "Marlin-style?"
HYREL_OR_MARLIN = "Hyrel or Marlin-style?"

# (vendor, product) -> (what it is, the mark): boards, and USB-serial chips on boards.
_BOARDS: dict[tuple[int, int], tuple[str, str]] = {
    (0x0483, 0x5740): (
        "an STM32 virtual COM port: Hyrel's controllers, STM32 boards",
        HYREL_OR_MARLIN,
    ),
    (0x2341, 0x0010): ("an Arduino Mega 2560", MARLIN),
    (0x2341, 0x0042): ("an Arduino Mega 2560 R3", MARLIN),
    (0x2A03, 0x0042): ("an Arduino Mega 2560 R3 (arduino.org)", MARLIN),
    (0x1A86, 0x7523): ("a CH340 USB-serial chip, as on Creality and many RAMPS boards", MARLIN),
    (0x0403, 0x6001): ("an FTDI FT232R USB-serial chip", MARLIN),
    (0x0403, 0x6015): ("an FTDI FT231X USB-serial chip", MARLIN),
    (0x10C4, 0xEA60): ("a CP210x USB-serial chip", MARLIN),
    (0x1D50, 0x6029): ("an LPC176x board (Marlin's USB serial)", MARLIN),
}
# Vendors whose every serial device is a printer board.
_VENDORS: dict[int, tuple[str, str]] = {
    0x2C99: ("a Prusa Research board", MARLIN),
}


@dataclass(frozen=True, slots=True)
class Board:
    """Why a port looks like a printer board."""

    mark: str  # "Hyrel?", "Marlin-style?", "Hyrel or Marlin-style?"
    reason: str


def classify(port: ListPortInfo) -> Board | None:
    """The board ``port`` looks like, from its USB identity; None when it looks like none."""
    if port.vid is None:
        return None  # no USB information: a built-in port, a Bluetooth one...
    names = " ".join(n for n in (port.manufacturer, port.product, port.description) if n)
    if "hyrel" in names.lower():
        return Board(HYREL, "its USB name says Hyrel")
    known = _BOARDS.get((port.vid, port.pid or 0)) or _VENDORS.get(port.vid)
    if known is None:
        return None
    what, mark = known
    return Board(mark, what)


def usb_id(port: ListPortInfo) -> str:
    """``VID:PID`` in lsusb's form, or "" without USB information."""
    if port.vid is None:
        return ""
    return f"{port.vid:04x}:{port.pid or 0:04x}"


def describe(port: ListPortInfo) -> str:
    """One line for ``--list-ports``: device, description, maker, USB ID, serial, mark."""
    parts = [port.device]
    description = port.description if port.description not in (None, "n/a") else ""
    if port.manufacturer and port.manufacturer not in description:
        description = f"{description} ({port.manufacturer})" if description else port.manufacturer
    if description:
        parts.append(description)
    if port.vid is None:
        parts.append("no USB information")
    else:
        parts.append(f"USB {usb_id(port)}")
    if port.serial_number:
        parts.append(f"serial {port.serial_number}")
    board = classify(port)
    line = "  ".join(parts)
    return f"{line}  {board.mark} ({board.reason})" if board else line


def list_ports() -> list[ListPortInfo]:
    """The machine's serial ports, in natural order (ttyACM2 before ttyACM10)."""
    from serial.tools.list_ports import comports

    return sorted(comports())


@dataclass(frozen=True, slots=True)
class AutoChoice:
    """The port ``auto`` chose, and why."""

    device: str
    reason: str


def choose_auto(ports: Iterable[ListPortInfo], source: str = "--port") -> AutoChoice:
    """The only port that looks like a printer board; a LinkError naming them otherwise.

    ``source`` is where ``auto`` came from, for the sentences."""
    ports = list(ports)
    candidates = [(port, board) for port in ports if (board := classify(port)) is not None]
    if len(candidates) == 1:
        port, board = candidates[0]
        return AutoChoice(
            port.device,
            f"port auto ({source}): {port.device}, the only serial port that looks like a "
            f"printer board ({board.mark[:-1]}: {board.reason}, USB {usb_id(port)})",
        )
    if not candidates:
        found = f"ports found: {_names(ports)}" if ports else "no serial ports found"
        raise LinkError(
            f"port auto ({source}): no serial port looks like a Hyrel or Marlin board "
            f"({found}; hyrel-send --list-ports describes them); give one with --port"
        )
    named = ", ".join(f"{port.device} ({board.mark})" for port, board in candidates)
    raise LinkError(
        f"port auto ({source}): {len(candidates)} serial ports look like printer boards: "
        f"{named}; give one with --port (hyrel-send --list-ports describes them)"
    )


def _names(ports: Sequence[ListPortInfo]) -> str:
    return ", ".join(port.device for port in ports)
