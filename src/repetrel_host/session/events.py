"""What a printer session tells its users: state changes, temperatures, controller
messages, and each job's progress and end. Frozen and slotted, as h11's events."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum

from repetrel_host.errors import HostError
from repetrel_host.protocol.events import Notice
from repetrel_host.protocol.reports import JobReport
from repetrel_host.session.job import ActionKind
from repetrel_host.session.pump import Summary

__all__ = [
    "Action",
    "Done",
    "Failed",
    "JobEvent",
    "Message",
    "NoAnswerYet",
    "Notice",
    "PauseReason",
    "Paused",
    "PrinterEvent",
    "Progress",
    "Report",
    "Resend",
    "Resumed",
    "State",
    "StateChanged",
    "StopDelayed",
    "Temperatures",
]


class State(Enum):
    """Where a printer session stands."""

    CONNECTING = "connecting"  # opening the port, greeting the controller
    READY = "ready"  # greeted; commands and jobs may start
    PRINTING = "printing"
    PAUSED = "paused"  # a job waits: commands may move the machine meanwhile
    DISCONNECTED = "disconnected"  # the port went away (reconnecting, unless told not to)
    CLOSED = "closed"


@dataclass(frozen=True, slots=True)
class StateChanged:
    state: State
    previous: State | None
    reason: str = ""


@dataclass(frozen=True, slots=True)
class Temperatures:
    """A temperature report, or the readings with a target the controller acknowledged
    (``text``: that command, targets.py): ``readings`` maps a sensor (``T``, ``T1``, ``B``,
    ``C``) to (current, target); the target is None when the report gave none."""

    readings: dict[str, tuple[float, float | None]]
    text: str


@dataclass(frozen=True, slots=True)
class Message:
    """A line from the controller that is not an answer to a command (echo:, //, >IN:...)."""

    text: str


@dataclass(frozen=True, slots=True)
class NoAnswerYet:
    """The controller on ``port`` has not answered the greeting yet: it goes again now, as
    greeting ``attempt`` of ``attempts`` (the connection fails once the last one goes
    unanswered); ``waited``: seconds since the first. Told as it happens: to ``connect()``'s
    ``on_event`` before it returns, and in :meth:`Printer.events` when the session greets
    again (after a reset, an unplug)."""

    port: str
    baud: int
    attempt: int
    attempts: int
    waited: float

    @property
    def text(self) -> str:
        return f"no answer yet: greeting again, {self.attempt} of {self.attempts}"


@dataclass(frozen=True, slots=True)
class Progress:
    """How far a job is: the controller acknowledged ``lines`` of its lines, up to byte
    ``offset`` of ``size``, the last at ``position`` (``part.gcode:1234``)."""

    lines: int
    offset: int
    size: int
    position: str


@dataclass(frozen=True, slots=True)
class Resend:
    """The controller asked for a job line again."""

    position: str


@dataclass(frozen=True, slots=True)
class Action:
    """A host action the job asked for (M792, or the text of an M0)."""

    kind: ActionKind
    message: str
    actions: tuple[tuple[str, str], ...]
    position: str


class PauseReason(StrEnum):
    REQUEST = "pause"  # Printer.pause()
    M0 = "M0"  # the job's M0 (or M1): the operator resumes


@dataclass(frozen=True, slots=True)
class Paused:
    """The job is paused, and waits for :meth:`Printer.resume`."""

    reason: PauseReason
    message: str
    position: str


@dataclass(frozen=True, slots=True)
class Resumed:
    pass


@dataclass(frozen=True, slots=True)
class StopDelayed:
    """The job is stopping, but its safe stop is held up: ``reason`` says by what, and
    ``heaters`` names those that may be on meanwhile. It still goes as soon as the
    controller takes it; an emergency stop (M112) would end it all at once."""

    reason: str
    heaters: tuple[str, ...]
    # M112 would act at once (Marlin's emergency parser, Hyrel's urgent line); without
    # it M112 too waits its turn behind what holds the stop: only the power switch helps.
    can_emergency_stop: bool = True


@dataclass(frozen=True, slots=True)
class Report:
    """The controller's M773 job report (sent at M30 after ``M772 S1``), before Done."""

    report: JobReport


@dataclass(frozen=True, slots=True)
class Done:
    """The job ended: completed, or cancelled after its safe stop."""

    summary: Summary


@dataclass(frozen=True, slots=True)
class Failed:
    """The job failed; ``error`` is what :meth:`PrintJob.wait` raises."""

    error: HostError


PrinterEvent = StateChanged | Temperatures | Message | Notice | NoAnswerYet
JobEvent = (
    Progress
    | Resend
    | Message
    | Notice
    | Action
    | Paused
    | Resumed
    | StopDelayed
    | Report
    | Done
    | Failed
)
