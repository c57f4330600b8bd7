"""The RepRap dialect's greeting: M110 and the probe behind it, retries.

The greeting resets the line numbering (``Nk M110 Nk``, attempt ``k`` from 0) and probes
behind it (``N<k+1> M105``, which draws no error from any firmware); the probe's answer
says the numbering took (see :mod:`~repetrel_host.protocol.dialects.reprap`). This holds
the greeting's own state (its attempts, whether the controller was heard, whether it was
greeted) and its decisions; the dialect sends the lines and reads the replies.
"""

from __future__ import annotations

from enum import Enum

from repetrel_host.protocol.events import ControllerReady, GreetingRetry, ProbeKind
from repetrel_host.protocol.framing import frame, reset_command
from repetrel_host.protocol.history import Line

# A greeting unanswered this long (after the last byte either way) goes again. A live
# controller answers within milliseconds; the wait is for a board that resets when the
# port opens (Marlin on an Arduino's USB): its bootloader takes the first second or two and
# drops what comes meanwhile, then Marlin says "start" (which restarts this wait) and reads
# the next greeting. OctoPrint waits up to 30 s for an answer, Klipper retries its identify
# every 5 s: both for daemons that wait for a printer to be switched on.
HELLO_TIMEOUT = 3.0
# Greetings that go unanswered before the greeting fails: 9 s of silence. The second and
# third cover a board still in its bootloader (and a corrupted M110); more would only make
# the wrong port or baud rate, by far the likeliest causes, a longer wait. Each retry is
# told (GreetingRetry) as it goes. Greeting again after a garbled answer costs nothing here.
HELLO_ATTEMPTS = 3
# A controller heard from (an ok, a resend request, an error, its boot banner) whose answers
# to the greeting get lost or garbled on a noisy link, and a renumbering mid-job: each lost
# answer costs a timeout, and giving up stops a job that could go on.
NOISY_HELLO_ATTEMPTS = 10


class RepRapPhase(Enum):
    """Where the RepRap dialect stands."""

    IDLE = "idle"  # start() not called yet
    GREETING = "greeting"  # M110 and a probe in flight: numbering being (re)set
    RUNNING = "running"
    FAILED = "failed"


class Greeting:
    """The greeting's attempts, and whether the controller answered."""

    def __init__(self) -> None:
        self.heard = False  # a reply of the controller's came (not noise): it is there
        self.greeted = False
        self.started_at = 0.0
        self._attempts = 0
        self._unanswered = 0  # timeouts of this greeting (HELLO_ATTEMPTS)

    def begin(self) -> None:
        """A new greeting (the first, or a renumbering): its attempts count from 0."""
        self._attempts = self._unanswered = 0

    def reset_line(self) -> Line:
        """The next attempt's ``Nk M110 Nk``, a host line (the history restarts with it)."""
        base = self._attempts
        self._attempts += 1
        command = reset_command(base)
        wire = frame(base, command)
        return Line(base, command, None, wire, True, is_reset=True, is_host_line=True, patient=True)

    @staticmethod
    def deadline(last_received_at: float, last_sent_at: float) -> float:
        """When an attempt unanswered goes again (after the last byte either way)."""
        return max(last_received_at, last_sent_at) + HELLO_TIMEOUT

    @property
    def unanswered(self) -> int:
        """Attempts of this greeting that went unanswered."""
        return self._unanswered

    def timed_out(self) -> bool:
        """An attempt went unanswered: True when it was the last, and the greeting fails."""
        self._unanswered += 1
        return self._unanswered >= self._allowed()

    def retry(self, now: float) -> GreetingRetry:
        """The retry to tell, as the next attempt goes."""
        waited = now - self.started_at
        return GreetingRetry(self._unanswered + 1, self._allowed(), waited)

    def _allowed(self) -> int:
        return NOISY_HELLO_ATTEMPTS if self.greeted or self.heard else HELLO_ATTEMPTS

    def finished(self, probe: ProbeKind) -> ControllerReady | None:
        """The numbering took: the event to tell the first time, else None."""
        if self.greeted:
            return None
        self.greeted = True
        return ControllerReady(probe)
