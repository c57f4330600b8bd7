"""The interface between the session and a firmware family's line protocol.

A dialect is pure and sans-IO, like h11's ``Connection``: commands go in with
:meth:`Dialect.send`, bytes from the controller with :meth:`Dialect.receive_data`,
the time wherever it matters; bytes to write come out of
:meth:`Dialect.data_to_send` and happenings out of :meth:`Dialect.next_event`.
The session never asks which dialect it drives: RepRap/Marlin today, Hyrel's
native link (ACK credit, control bytes) next.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from repetrel_host.protocol.events import Event, Failed, ProbeKind


@dataclass(slots=True)
class Statistics:
    lines_sent: int = 0  # first transmissions
    retransmissions: int = 0
    resend_requests: int = 0  # honoured requests
    ignored_resend_requests: int = 0  # echoes of one request, garbled numbers
    unexpected_oks: int = 0
    pings: int = 0  # probes sent
    stalls_recovered: int = 0  # timeouts answered by a probe
    bytes_sent: int = 0


class Dialect(Protocol):
    """What the session drives. One instance serves one connection, from its greeting on."""

    stats: Statistics

    def start(self, now: float) -> None:
        """Greet the controller: the first bytes to send set up the numbering."""

    def send(self, command: str, tag: object = None) -> None:
        """Queue one clean command; ``tag`` comes back in its events."""

    def send_urgent(self, command: str) -> None:
        """Put ``command`` on the wire at once, ahead of anything queued (M112)."""

    def request_sync(self) -> None:
        """No more lines for now: have the controller confirm every line sent."""

    def cancel_pending(self) -> list[tuple[str, object]]:
        """Drop queued lines not yet on the wire; return them (command, tag)."""

    @property
    def wants_lines(self) -> bool:
        """The queue is short enough that a new line could go out soon."""

    @property
    def is_done(self) -> bool:
        """Every line queued so far is confirmed accepted by the controller itself."""

    @property
    def is_ready(self) -> bool:
        """The greeting is over: lines flow."""

    @property
    def probe(self) -> ProbeKind:
        """How this connection asks the controller which lines it holds."""

    @property
    def failure(self) -> Failed | None:
        """Why the stream stopped, once it did."""

    def data_to_send(self, now: float) -> bytes:
        """Bytes to write now."""

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes read from the controller."""

    def next_event(self) -> Event | None:
        """The oldest event not yet taken, or None."""

    def next_deadline(self) -> float | None:
        """When :meth:`handle_timeout` wants to be called, or None."""

    def handle_timeout(self, now: float) -> None:
        """Act on a deadline that passed (a lost ok, a silent controller)."""
