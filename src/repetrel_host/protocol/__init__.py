"""The pure protocol core: framing, reply classification, host and controller state machines."""

from repetrel_host.protocol.framing import checksum, clean_line, frame
from repetrel_host.protocol.host import (
    ControllerMessage,
    ControllerReady,
    Event,
    Failed,
    FlowControl,
    FlowMode,
    HostProtocol,
    LineAcknowledged,
    ResendRequested,
)

__all__ = [
    "ControllerMessage",
    "ControllerReady",
    "Event",
    "Failed",
    "FlowControl",
    "FlowMode",
    "HostProtocol",
    "LineAcknowledged",
    "ResendRequested",
    "checksum",
    "clean_line",
    "frame",
]
