"""The interface between the session and a firmware family's line protocol.

A dialect is pure and sans-IO, like h11's ``Connection``: commands go in with
:meth:`Dialect.send`, bytes from the controller with :meth:`Dialect.receive_data`,
the time wherever it matters; bytes to write come out of
:meth:`Dialect.data_to_send` and happenings out of :meth:`Dialect.next_event`.
The session never asks which dialect it drives: RepRap/Marlin (``dialects/reprap.py``)
or Hyrel's own link (``dialects/hyrel.py``: ACK credit, control bytes). What only one of
them can do (drop what the controller holds, hold it at the end of a move) is asked for
all the same, and the answer says whether it was done.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from repetrel_host.protocol.events import DialectFailed, Event, ProbeKind


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
    lost_acks: int = 0  # Hyrel's link: lines that ran whose ACK never came


class Dialect(Protocol):
    """What the session drives. One instance serves one connection, from its greeting on."""

    stats: Statistics
    # An acknowledgement says only that the controller received the line (Hyrel's link):
    # what ran is :attr:`last_ran`. False: it says the controller took the line to run.
    acks_say_received: bool
    # Where :attr:`acks_say_received`: the tag of the last line (not the host's own, nor a
    # command sent with confirm) known to have run; an abort drops what was not known to
    # have run by then.
    last_ran: object | None
    # The tag of the last line (not the host's own) transmitted for the first time: what
    # reached the wire, for a killed host's progress record.
    last_sent: object | None
    # Called once for each line as it first goes on the wire, in wire order: its command,
    # its tag, whether it is the dialect's own (a greeting, a probe, a sync), and its line
    # number (None: unnumbered); None: not called. For tests that tell the host's own lines
    # from the caller's in what ran.
    on_first_send: Callable[[str, object, bool, int | None], None] | None

    def start(self, now: float) -> None:
        """Greet the controller: the first bytes to send set up the numbering."""

    @property
    def pause_command(self) -> str | None:
        """The command that makes the controller itself wait for :meth:`end_wait` (M0 on
        Hyrel's link); None: the host holds the job at an M0 instead."""

    def send(
        self, command: str, tag: object = None, *, confirm: bool = False, urgent: bool = False
    ) -> None:
        """Queue one clean command; ``tag`` comes back in its events. ``confirm``: its
        :class:`LineAcknowledged` waits until the controller ran it, so that its reply
        is complete (a command's); ``urgent``: ahead of what the controller holds, where
        the link can say so (the safe stop after :meth:`abort`)."""

    def send_urgent(self, command: str) -> None:
        """Put ``command`` on the wire at once, ahead of anything queued (M112, M108)."""

    def abort(self) -> bool:
        """Have the controller drop every line it holds and has not run; False when the
        link cannot (the lines sent run first)."""

    def hold(self, at_layer_end: bool = False) -> bool:
        """Have the controller stop at the end of the move (or layer) and hold the rest
        until :meth:`end_wait`; False when the link cannot (the host stops feeding and
        lets the controller run what it has)."""

    def end_wait(self) -> None:
        """End the controller's wait: a hold, the :attr:`pause_command`."""

    def request_status(self) -> bool:
        """Ask for a status report (the temperatures) out of band, answered at once
        whatever the controller holds: no line, no number (Hyrel's 0x05). False when the
        link has no such request (a poll is then a command: M105)."""

    def request_sync(self) -> None:
        """No more lines for now: have the controller confirm every line sent."""

    def cancel_pending(self) -> list[tuple[str, object]]:
        """Drop queued lines not yet on the wire; return them (command, tag)."""

    @property
    def awaiting(self) -> tuple[str, object] | None:
        """The oldest line on the wire the controller has yet to confirm (command, tag),
        the host's own aside: what it is working on, or will be next."""

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
    def failure(self) -> DialectFailed | None:
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
