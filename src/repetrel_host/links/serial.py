"""The only module that touches pyserial: a serial device, or a pyserial URL
(``socket://host:port``, ``rfc2217://host:port``)."""

from __future__ import annotations

import asyncio
import errno
import functools
import os
from collections.abc import Callable

import serial
import serial_asyncio_fast

from repetrel_host.errors import LinkError


async def open_serial(
    port: str, baudrate: int, protocol_factory: Callable[[], asyncio.Protocol]
) -> tuple[asyncio.Transport, asyncio.Protocol]:
    """Open ``port`` (a device path or a pyserial URL) and connect ``protocol_factory`` to it."""
    loop = asyncio.get_running_loop()
    url = "://" in port
    options = {} if url else {"exclusive": True}
    opener = functools.partial(serial.serial_for_url, port, baudrate=baudrate, **options)
    try:
        serial_port = await loop.run_in_executor(None, opener)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkError(describe_open_error(port, exc)) from None
    protocol = protocol_factory()
    if url:
        # A URL's bytes pass through pyserial's own read and write (RFC 2217's telnet
        # escapes, a socket's framing): the library's transport, as it is.
        return serial_asyncio_fast.SerialTransport(loop, protocol, serial_port), protocol
    return _SerialTransport(loop, protocol, serial_port), protocol


class _SerialTransport(serial_asyncio_fast.SerialTransport):
    """pyserial-asyncio-fast's transport, reading and writing the port's descriptor itself.

    pyserial's write retries a full port buffer in a busy loop, which would freeze the
    event loop (and with it every timeout) on a link that pushes back, and the library
    leaves a drained writer registered, failing an assertion on every turn of the loop
    (its open PR #36). Plain non-blocking ``os.read``/``os.write`` also save the
    ``select`` pyserial makes around each call, on the path from an ok to the next line,
    and a port that fails ends the stream with a sentence instead of a logged traceback.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        protocol: asyncio.Protocol,
        serial_port: serial.Serial,
    ) -> None:
        super().__init__(loop, protocol, serial_port)
        self._fd = serial_port.fileno()

    def _read_ready(self) -> None:
        try:
            data = os.read(self._fd, self._max_read_size)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(exc)
            return
        if not data:  # readable, yet nothing: the device went away
            self._close(serial.SerialException("the port returned no data (disconnected?)"))
            return
        self._protocol.data_received(data)

    def _write_data(self, data: bytes | bytearray | memoryview) -> None:
        try:
            written = os.write(self._fd, data)
        except (BlockingIOError, InterruptedError):
            written = 0
        except OSError as exc:
            self._abort(exc)
            return
        if written == len(data):
            if self._closing:
                self._close()
            return
        self._write_buffer.append(data[written:])  # the rest once the port drains
        self._maybe_pause_protocol()
        self._ensure_writer()

    def _write_ready(self) -> None:
        if not self._write_buffer:
            self._remove_writer()
            return
        super()._write_ready()


def describe_open_error(port: str, exc: BaseException) -> str:
    """One sentence for a port that would not open."""
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code == errno.ENOENT or "No such file" in text:
        return f"cannot open {port}: no such port (is the printer plugged in and on?)"
    if code == errno.EACCES or "Permission denied" in text:
        return (
            f"cannot open {port}: permission denied (on Linux, add yourself to the 'dialout' group)"
        )
    if code == errno.ENOTTY or "Inappropriate ioctl" in text:
        return f"cannot open {port}: it is not a serial port"
    if code == errno.EBUSY or "Resource temporarily unavailable" in text or "busy" in text:
        return f"cannot open {port}: the port is busy (another program has it open)"
    return f"cannot open {port}: {text}"
