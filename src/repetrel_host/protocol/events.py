"""What a dialect reports to the session: events, and why a stream failed."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import NamedTuple

from repetrel_host.protocol import replies


class FailureKind(Enum):
    """Why the stream cannot go on."""

    CONTROLLER = "controller"  # the controller reported an error of its own
    RESET = "reset"  # the controller (re)booted: its queue and state are gone
    PROTOCOL = "protocol"  # a request the host cannot honour
    TIMEOUT = "timeout"  # the controller fell silent
    # the controller never answered the greeting: nothing there, or not listening (the
    # wrong port, the wrong baud rate, a board still booting, another protocol)
    NO_ANSWER = "no answer"


class ProbeKind(Enum):
    """How the host asks the controller which lines it holds."""

    # N<n> M105*<cs>: a real, harmless line, accepted only once every line before
    # it was; its "ok T:..." says so. It draws no error from the firmware.
    COMMAND = "command"
    # N<n> M105 S<k>*9999: a checksum that never fits, so it never runs; a
    # Marlin-style controller answers "Last Line: n-1 / Resend: n" (an error) when it
    # holds every line before it. For controllers whose ok for M105 says nothing (found
    # at the greeting).
    CHECKSUM = "checksum"
    # M115, which the controller answers as it runs it, once every line before it ran:
    # for links that have no way to ask for a line again (Hyrel's own).
    ANSWER = "answer"


@dataclass(frozen=True, slots=True)
class ControllerReady:
    """The controller confirmed the opening M110 (or answered the ping): it is there and
    numbering agrees. ``identity``: what it said of itself then, where the link has that
    (Hyrel's ``>Hy: ...``)."""

    probe: ProbeKind = ProbeKind.COMMAND
    identity: str = ""


@dataclass(frozen=True, slots=True)
class GreetingRetry:
    """No answer to the greeting within its timeout: it goes again now, as greeting
    ``attempt`` of ``attempts`` (the greeting fails once the last goes unanswered);
    ``waited``: seconds since the first went out. Only before the controller first
    answered (a renumbering mid-stream is not told)."""

    attempt: int
    attempts: int
    waited: float


class LineAcknowledged(NamedTuple):
    """The controller acknowledged a line sent with ``send`` (once per line).

    A named tuple, immutable as the other events: made for every line, it costs a
    third of a frozen dataclass."""

    number: int
    command: str
    tag: object
    data: str  # what followed "ok", e.g. temperatures


@dataclass(frozen=True, slots=True)
class ResendRequested:
    """The controller asked for ``number`` and what follows again; the host will send them."""

    number: int
    command: str
    tag: object


@dataclass(frozen=True, slots=True)
class ControllerMessage:
    """A line that is not flow control: echo, comments, Hyrel reports, busy, line errors.
    ``tag`` is the tag of the line it names by number (Hyrel's ``>ER: ... line 12``), if any."""

    reply: replies.Reply
    text: str
    tag: object = None


@dataclass(frozen=True, slots=True)
class Notice:
    """Something the user should know that does not stop the stream (a high resend rate)."""

    text: str


@dataclass(frozen=True, slots=True)
class LineRefused:
    """The controller will not run a line it received (Hyrel's checksum), or can no longer
    run the job as written (its watchdog stopped the extruders): the job must stop, its
    safe stop first; the connection goes on. ``tag``: the line's, if known."""

    reason: str
    tag: object = None


@dataclass(frozen=True, slots=True)
class DialectFailed:
    """The stream cannot go on. Nothing more is sent; ``reason`` is one sentence."""

    kind: FailureKind
    reason: str
    tag: object = None  # the oldest unacknowledged line's tag, where the trouble most likely is


Event = (
    ControllerReady
    | GreetingRetry
    | LineAcknowledged
    | ResendRequested
    | ControllerMessage
    | Notice
    | LineRefused
    | DialectFailed
)
