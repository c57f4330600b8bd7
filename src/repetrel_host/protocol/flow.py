"""Flow control: how many lines, and how many bytes, may be unanswered at once."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class FlowMode(Enum):
    """How many lines may be unacknowledged at once."""

    UNBUFFERED = "unbuffered"  # one line in flight: wait for each ok
    BUFFERED = "buffered"  # as many as the controller's receive buffer holds


@dataclass(frozen=True, slots=True)
class FlowControl:
    """Flow-control limits.

    In buffered mode the host counts the bytes of unacknowledged lines against
    the controller's receive buffer (character counting, as grbl and
    Repetier-Host do): a line leaves that buffer before it is acknowledged, so
    the buffer never overflows. One byte stays free because a ring buffer of
    N bytes holds N - 1. When the controller reports ADVANCED_OK
    (``ok N<last line> P.. B..``), lines up to that N have left the buffer for the
    command slots and stop counting, so the buffer is kept full.
    """

    mode: FlowMode = FlowMode.BUFFERED
    rx_buffer: int = 128  # the controller's receive buffer in bytes (AVR Marlin: 128)
    max_lines: int = 8  # lines in flight at most, whatever their length

    def __post_init__(self) -> None:
        if self.rx_buffer < 2:
            raise ValueError("rx_buffer must be at least 2 bytes")
        if self.max_lines < 1:
            raise ValueError("max_lines must be at least 1")

    @property
    def byte_limit(self) -> int:
        return self.rx_buffer - 1

    @property
    def line_limit(self) -> int:
        return 1 if self.mode is FlowMode.UNBUFFERED else self.max_lines


# Hyrel's own link: the window is the controller's headroom, not its buffer. It ACKs lines
# while 2 KB of its 8 KB are free, so 2 KB unacknowledged keep the buffer from overflowing.
HYREL_WINDOW = FlowControl(rx_buffer=2048, max_lines=256)
