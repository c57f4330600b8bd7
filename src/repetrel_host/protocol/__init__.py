"""The pure protocol core: framing, replies, events, the state parts, and dialects."""

from repetrel_host.protocol.dialect import Dialect, Statistics
from repetrel_host.protocol.dialects import create_dialect
from repetrel_host.protocol.dialects.reprap import RepRapDialect
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    DialectFailed,
    Event,
    FailureKind,
    GreetingRetry,
    LineAcknowledged,
    Notice,
    ProbeKind,
    ResendRequested,
)
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.framing import checksum, clean_line, frame

__all__ = [
    "ControllerMessage",
    "ControllerReady",
    "Dialect",
    "DialectFailed",
    "Event",
    "FailureKind",
    "FlowControl",
    "FlowMode",
    "GreetingRetry",
    "LineAcknowledged",
    "Notice",
    "ProbeKind",
    "RepRapDialect",
    "ResendRequested",
    "Statistics",
    "checksum",
    "clean_line",
    "create_dialect",
    "frame",
]
