"""repetrel-host: streams G-code to Hyrel printers' motion controllers.

The printer session is the heart::

    import repetrel_host as rh

    async with rh.connect("fake") as printer:
        reply = await printer.command("M115")
        job = await printer.print("part.gcode")
        summary = await job.wait()
"""

from repetrel_host.errors import (
    ConfigError,
    ControllerError,
    HostError,
    JobError,
    LinkError,
    ProtocolError,
    SafeStopError,
    UsageError,
)
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.reports import Firmware, JobReport
from repetrel_host.session.commands import Reply
from repetrel_host.session.connect import connect
from repetrel_host.session.events import (
    Action,
    Done,
    Failed,
    Message,
    NoAnswerYet,
    Notice,
    Paused,
    PauseReason,
    Progress,
    Report,
    Resend,
    Resumed,
    State,
    StateChanged,
    StopDelayed,
    Temperatures,
)
from repetrel_host.session.machine_state import HomeAxes
from repetrel_host.session.print_job import PrintJob
from repetrel_host.session.printer import Printer
from repetrel_host.session.pump import Outcome, Summary

__version__ = "0.2.0"

__all__ = [
    "Action",
    "ConfigError",
    "ControllerError",
    "Done",
    "Failed",
    "Firmware",
    "FlowControl",
    "FlowMode",
    "HomeAxes",
    "HostError",
    "JobError",
    "JobReport",
    "LinkError",
    "Message",
    "NoAnswerYet",
    "Notice",
    "Outcome",
    "PauseReason",
    "Paused",
    "PrintJob",
    "Printer",
    "ProbeKind",
    "Progress",
    "ProtocolError",
    "Reply",
    "Report",
    "Resend",
    "Resumed",
    "SafeStopError",
    "State",
    "StateChanged",
    "StopDelayed",
    "Summary",
    "Temperatures",
    "UsageError",
    "__version__",
    "connect",
]
