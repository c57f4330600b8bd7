"""Hyrel's own link, the host's side: ACK credit, control bytes, tagged messages (sans-IO).

docs/hyrel-link.md. The controller answers every line it receives with one ACK byte
while its receive buffer has headroom: the window is credit, counted in lines and bytes
as the RepRap dialect counts them, and each ACK releases the oldest line on the wire.
There is no resend: a line the controller refuses (its checksum) cannot be sent again in
its place, so the stream fails, naming it.

An ACK says "received", not "run". What has run is learned from what the controller
writes as it runs commands, in order: ``M115``'s answer (``FIRMWARE_NAME:>Hy: ...``),
which says that every line before that M115 ran too, and the ``>MC:M<n>: ...``
notices of the M-codes it reports (:data:`~repetrel_host.protocol.hyrel.NOTICED`; no
others are awaited). A notice says that a received line of its code and values ran: the
host takes it for the oldest such line not known to have run (so for every line before it,
whose own notices were lost or garbled), and for nothing when none agrees; a command's reply
is complete then. Where every line sent must be known to have run (the end of a job, before
a host action, a command's reply) the host sends an ``M115`` of its own after the last of
them: a *sync*; one goes among the lines too, after as many of them as the answers say run
in :data:`SYNC_INTERVAL` seconds (at most :data:`SYNC_EVERY`), so that what ran (the recovery
point) follows the job, fast or slow, and one just before an ``M0`` (which waits; what
follows it waits behind it). Up to 8 KB of job may wait in the controller when the last ACK
comes: a job ends once a sync's answer says its last line ran, and with it all the
controller wrote meanwhile.

Answers are counted by the link's order, not by their text: nothing in an answer says
which M115 it is for, and taking one too many would call lines run that have not (a job
done during a dwell, a recovery point past lines that never ran). An answer is a line that is
no message (``>IN: FIRMWARE_NAME:...`` quotes the identity; an answer and a message that a
garbled newline ran together are told apart). A controller that says an answer twice
writes the two together: an answer with nothing between it and the one before (no ACK
byte, no message) is that one said again, and is not taken. So that something does come
between two real answers, the host asks for a status report (0x05, answered as it
arrives) after reading one while M115s wait, and sends a sync among the lines only after a
line that takes time (a move, a dwell) and not a few lines behind one still waiting. What
cannot be told this way (two M115s run within that round trip) is not counted: the M115
waiting then may wait for an answer that came. A notice of a later line ends that wait
(the M115 ran: its answer came before); else, once no line follows it, the last M115 goes
again right after itself. An M115 right behind the one an answer was last taken for,
nothing between them, runs as soon as it is received: not answered within
:data:`ANSWER_AT_ONCE` of both, its answer came before, and it waits no longer (it says no
more than that one). An identity line in the answer's very form, unasked, cannot be told
from an answer.

The controller stops its extruders after 30 s without a byte from the host: the dialect
sends the watchdog byte whenever it has been quiet for :data:`KEEPALIVE` seconds, through
heat-ups, dwells and pauses. While lines wait for their ACKs it asks for a status report
(0x05) now and then: an answer means the controller is there, its buffer full behind a
long command; none, several times, means it is gone. Waiting that long also sends a sync,
past the window if need be: its answer releases lines whose ACK was lost.

Cancel is abort (0x08): the controller drops what it holds, and the safe stop goes as
urgent lines (0x09 first). A pause is 0x02 (end of the move) or 0x03 (end of the layer),
an M0 is the controller's own, and both end with end-wait (0x01). A line the controller
refuses (its checksum) stops the job (:class:`LineRefused`); the link goes on.

The reading of what the controller writes (ACKs, answers, notices, messages) is
:class:`~repetrel_host.protocol.dialects.hyrel_replies.HyrelReplies`', this dialect's part
kept apart for its size, as the RepRap dialect's is.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from repetrel_host.errors import UsageError
from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects.hyrel_answers import AnswerCounter
from repetrel_host.protocol.dialects.hyrel_replies import HyrelPhase, HyrelReplies, SentLine
from repetrel_host.protocol.events import (
    DialectFailed,
    Event,
    FailureKind,
    GreetingRetry,
    ProbeKind,
)
from repetrel_host.protocol.flow import HYREL_WINDOW, FlowControl
from repetrel_host.protocol.hyrel import NOTICED, Control, HostReceiver, frame, mark_urgent

DEFAULT_WINDOW = HYREL_WINDOW  # 2 KB: the controller's headroom
# For the ping's answer; a late answer within it is not a reboot. As the RepRap dialect's
# greeting (see there): a live controller answers at once, and 3 pings 3 s apart, each
# retry told (GreetingRetry), give a board still booting 9 s without making the wrong port
# or baud rate a long wait.
HELLO_TIMEOUT = 3.0
HELLO_ATTEMPTS = 3
KEEPALIVE = 10.0  # the longest quiet from the host: well inside the 30 s watchdog
STATUS_ATTEMPTS = 4  # unanswered status requests in a row: the controller is gone
STATUS_AFTER = 5.0  # lines waiting this long for an ACK: ask whether the controller is there
# No ACK for this long while lines wait for theirs: a sync goes (past the window if need
# be), whose answer releases those that ran, whose ACK was lost. A full buffer behind a
# long command holds its ACKs back too: then the sync waits its turn, and does no harm.
SYNC_AFTER = 0.5
SYNC_COMMAND = "M115"  # answered when run: every line before it ran
# A status report asked after an answer (to come between it and the next) and not come in
# this long is asked again: it, or its reply, was lost or garbled.
SEPARATOR_RETRY = 0.5
# An M115 right behind one answered (nothing between them), received, runs at once: its
# answer comes within a round trip. Not come in this long, it came before, not taken.
ANSWER_AT_ONCE = 1.0
# Lines waited this long for an ACK: a sync goes even right behind an M115 still waiting
# (its answer may have come, not taken). The status requests wake the dialect by then.
STALL_PATIENCE = STATUS_AFTER
SYNC_RETRY = 30.0  # an M115 unanswered this long: its answer may be lost, another may go
# Syncs among the lines: each answer says how far the controller got (the recovery point
# after a stop: what ran since the last one runs again), and releases lines whose ACK was
# lost before they fill the window. One goes after as many lines as run in SYNC_INTERVAL
# seconds, as the answers tell: on a slow job 256 lines are minutes of printing. (Not
# after a time since the last one: lines do not flow as they run, but in bursts of the
# headroom, ACKed once 2 KB of the buffer are free, and at once while it fills.) One M115
# a second costs some 12 bytes to the controller and 100 back, under 1 % of a 115,200 baud
# link; on a fast job one among every SYNC_EVERY lines (0.4 % more lines).
SYNC_INTERVAL = 1.0
SYNC_EVERY = 256
# Until answers tell (a job's start, after a wait): a sync among every this many lines,
# whose count doubles at most with each answer (the first lines fill the planner at once).
SYNC_EVERY_MIN = 16
RATE_AFTER = 0.1  # seconds since the last answer that told how fast lines run
# Bytes of the headroom the caller's lines leave free: room for the host's own lines (a
# sync past the window), and against a few ACKs that come late (taken for the next line's,
# each lets one line too many go; a full buffer has no other byte to spare).
HOST_RESERVE = 128
RECENT = 1024  # lines remembered by number (an error names one)
_TAKE_TIME = frozenset({"G0", "G1", "G2", "G3", "G4", "G28"})  # moves, dwells, homing


class HyrelDialect(HyrelReplies):
    """The session's dialect for a Hyrel controller on its own link.

    ``flow``: the window (the controller's headroom; :data:`DEFAULT_WINDOW`);
    ``numbered``: lines carry ``N<n>``, so that the controller's reports name them;
    ``checksum``: they carry the additive checksum too (a mismatch fails the stream);
    ``reply_timeout``: seconds without a word from the controller, while lines wait for
    their ACKs, after which it is taken as gone.
    """

    pause_command = "M0"  # the controller waits at M0 itself, until end-wait
    acks_say_received = True

    def __init__(
        self,
        flow: FlowControl | None = None,
        numbered: bool = True,
        checksum: bool = False,
        *,
        reply_timeout: float = STATUS_AFTER * STATUS_ATTEMPTS,
    ) -> None:
        self.flow = flow = flow or DEFAULT_WINDOW
        self.numbered = numbered
        self.checksum = checksum
        self.stats = Statistics()
        self._status_after = min(STATUS_AFTER, reply_timeout / STATUS_ATTEMPTS)
        self._line_limit = flow.line_limit
        self._host_byte_limit = flow.byte_limit
        self._byte_limit = max(1, flow.byte_limit - min(HOST_RESERVE, flow.byte_limit // 4))
        self._phase = HyrelPhase.IDLE
        # Queued: command, word, tag, confirm, urgent.
        self._pending: deque[tuple[str, str, object, bool, bool]] = deque()
        self._in_flight: deque[SentLine] = deque()  # waiting for their ACK
        self._in_flight_bytes = 0
        self._host_in_flight = 0  # the host's own lines among them
        self._stale_acks = 0  # ACKs that may still come for lines an abort dropped
        self._awaiting: deque[SentLine] = deque()  # confirm lines not yet known to have run
        self._unran: deque[SentLine] = deque()  # the caller's plain lines not known to have run
        self.last_ran: object | None = None  # the tag of the last of them known to have run
        self.last_sent: object | None = None  # the tag of the caller's last line transmitted
        self.on_first_send: Callable[[str, object, bool, int | None], None] | None = None
        # Noticed M-codes not known to have run: a notice may name one. (Few: an answer
        # confirms them all, and one comes every SYNC_EVERY lines at most.)
        self._mcodes: deque[SentLine] = deque()
        # Every M115 on the wire, the caller's and the host's syncs, in order: each
        # "FIRMWARE_NAME:" answer is the oldest one's.
        self._m115s: deque[SentLine] = deque()
        self._stale_answers = 0  # answers that may still come for M115s an abort dropped
        self._answers = AnswerCounter()
        self._separated = True  # a message came since the last answer
        self._cut_tag = False  # the last line was a bare tag: the next may be its text
        self._doubt = False  # the oldest M115 waiting may have had its answer not taken
        self._answered_seq = -1  # the M115 an answer was last taken for, and when
        self._answered_at = 0.0
        self._fence_asked_at: float | None = None  # a status report asked as a separator
        self._recent: dict[int, object] = {}  # line number -> tag, of the last RECENT lines
        self._next_number = 1
        self._seq = 0
        self._last_caller_seq = 0
        self._confirmed_seq = 0  # every line up to this one ran (an answer, a notice said)
        self._synced_seq = 0  # every line up to this one ran (an M115's answer said)
        self._sync_requested = False
        self._sync_sent_at: float | None = None  # an M115 after the last caller line
        self._since_m115 = 0  # caller lines sent since the last M115
        self._moved_since_m115 = False  # a move or a dwell among them: it takes time
        self._asked_again = False  # an M115 waited SYNC_RETRY: another goes in any case
        self._sync_every = SYNC_EVERY_MIN  # lines that run in SYNC_INTERVAL, as told
        self._told_at = 0.0  # the answer that told it last, and the line it confirmed
        self._told_seq = 0
        self._stalled = False  # lines waited for their ACK: a sync may go past the window
        self._acked_at = 0.0  # the last ACK, or the first line to wait for one since
        self._receiver = HostReceiver()
        self._outgoing = bytearray()
        self._events: deque[Event] = deque()
        self._failure: DialectFailed | None = None
        self._hello_attempts = 0
        self._hello_deadline = 0.0
        self._started_at = 0.0
        self._late_pings = 0
        self._last_sent_at = 0.0
        self._last_progress_at = 0.0  # an ACK, an answer: the controller is there
        self._status_asked = 0

    # --- feeding ----------------------------------------------------------------

    def start(self, now: float) -> None:
        """Ping the controller; its ``>Hy:`` answer opens the stream."""
        if self._phase is not HyrelPhase.IDLE:
            raise UsageError("the dialect was already started")
        self._last_sent_at = self._last_progress_at = self._started_at = now
        self._ping(now)

    def send(
        self, command: str, tag: object = None, *, confirm: bool = False, urgent: bool = False
    ) -> None:
        word = command_word(command)
        if word == "M110":
            raise UsageError("M110 sets line numbers, which the host owns; it cannot be queued")
        self._pending.append((command, word, tag, confirm, urgent))
        self._sync_requested = False

    def send_urgent(self, command: str) -> None:
        """Ahead of everything: M108 is end-wait (0x01); M112 is abort (0x08), then an
        urgent M112; anything else an urgent line."""
        word = command_word(command)
        if word == "M108":
            self._outgoing.append(Control.END_WAIT)
            return
        if word == "M112":
            self.abort()
        self._transmit(command, word, None, self._last_sent_at, host_line=True, urgent=True)

    def abort(self) -> bool:
        """Abort (0x08): the controller drops what it holds. What it would have said of
        those lines (ACKs, M115 answers) may still come, and is not taken for what follows."""
        if self._phase is not HyrelPhase.RUNNING:
            return False
        self._outgoing.append(Control.ABORT)
        self._stale_acks += len(self._in_flight)
        self._in_flight.clear()
        self._host_in_flight = 0
        self._in_flight_bytes = 0
        self._stale_answers += len(self._m115s)
        self._m115s.clear()
        self._doubt = False
        self._unran.clear()  # dropped, as far as anyone knows: none of them counts as run
        self._sync_sent_at = None
        self._since_m115 = 0
        self._stalled = False  # the lines after it wait for ACKs afresh
        return True

    def hold(self, at_layer_end: bool = False) -> bool:
        if self._phase is not HyrelPhase.RUNNING:
            return False
        self._outgoing.append(
            Control.PAUSE_AT_LAYER_END if at_layer_end else Control.PAUSE_AT_MOVE_END
        )
        return True

    def end_wait(self) -> None:
        if self._phase is HyrelPhase.RUNNING:
            self._outgoing.append(Control.END_WAIT)

    def request_status(self) -> bool:
        """0x05: the controller answers ``>ST: T:... B:...`` as the byte arrives. (An M105
        would wait its turn behind up to 8 KB of a job: minutes of stale temperatures.)"""
        if self._phase is not HyrelPhase.RUNNING:
            return False
        self._ask_status()
        return True

    def _ask_status(self) -> None:
        self._outgoing.append(Control.STATUS)

    def request_sync(self) -> None:
        self._sync_requested = True

    def cancel_pending(self) -> list[tuple[str, object]]:
        dropped = [(command, tag) for command, _, tag, _, _ in self._pending]
        self._pending.clear()
        return dropped

    @property
    def awaiting(self) -> tuple[str, object] | None:
        waiting = [queue[0] for queue in (self._unran, self._awaiting) if queue]
        if not waiting:
            return None
        oldest = min(waiting, key=lambda sent: sent.seq)
        return oldest.command, oldest.tag

    @property
    def wants_lines(self) -> bool:
        return self._phase is not HyrelPhase.FAILED and len(self._pending) < self._line_limit

    @property
    def is_done(self) -> bool:
        """Every line queued so far ran: an M115's answer says so (written after all the
        controller wrote as it ran them, an M773 report among it)."""
        return (
            self._phase is HyrelPhase.RUNNING
            and not self._pending
            and self._synced_seq >= self._last_caller_seq
        )

    @property
    def is_ready(self) -> bool:
        return self._phase is HyrelPhase.RUNNING

    @property
    def probe(self) -> ProbeKind:
        return ProbeKind.ANSWER

    @property
    def failure(self) -> DialectFailed | None:
        return self._failure

    # --- output -----------------------------------------------------------------

    def data_to_send(self, now: float) -> bytes:
        if self._phase is HyrelPhase.RUNNING:
            pending = self._pending
            if not self._separated and self._fence_asked_at is None and self._m115s:
                # Something between the last answer and the next (an M115's own ACK may be
                # lost, and one that went before the answer came may run at any time).
                self._fence_asked_at = now
                self._ask_status()
            while pending and self._has_room(pending[0][0], pending[0][4]):
                command, word, tag, confirm, urgent_line = pending.popleft()
                # The M0's own notice may be lost, and what follows it waits behind it:
                # a sync just before it says when it is reached.
                sync = None
                if word == self.pause_command:
                    sync = self._transmit(SYNC_COMMAND, SYNC_COMMAND, None, now, host_line=True)
                sent = self._transmit(command, word, tag, now, confirm=confirm, urgent=urgent_line)
                if sync is not None:
                    sync.reaches = sent.seq
                # Not among lines that all run at once: two answers together could not
                # be told from one said twice (the second would not be counted).
                due = self._since_m115 >= self._sync_every and self._moved_since_m115
                if due and self._has_room(SYNC_COMMAND, False, True):
                    self._transmit(SYNC_COMMAND, SYNC_COMMAND, None, now, host_line=True)
            if self._wants_sync(now) and self._has_room(SYNC_COMMAND, False, host_line=True):
                self._transmit(SYNC_COMMAND, SYNC_COMMAND, None, now, host_line=True)
            m115s = self._m115s
            if (
                self._doubt
                and m115s
                and not m115s[-1].again
                and m115s[-1].seq == self._seq
                and not pending
            ):
                # The last M115 may wait for an answer not taken: it goes again, right
                # after itself (past the window if need be), and waits no longer once the
                # repeat's answer is taken for it (see _answered_in_vain_from).
                self._transmit(SYNC_COMMAND, SYNC_COMMAND, None, now, host_line=True).again = True
        if not self._outgoing:
            return b""
        self._last_sent_at = now
        data = bytes(self._outgoing)
        self._outgoing.clear()
        return data

    def _wants_sync(self, now: float) -> bool:
        """Lines must be known to have run and nothing will say so: send an M115 after the
        last of them (after an abort, once they are all received, so that the answers it
        left behind came first), or once lines waited long for their ACK (to release
        those whose ACK was lost)."""
        if self._synced_seq >= self._last_caller_seq or self._sync_sent_at is not None:
            return False
        if self._stalled:
            # Not a few lines behind an M115 still waiting: its answer releases the lines
            # before it, and two M115s run at once could not be told from one answer said
            # twice. (Should that answer not be taken, one goes after STALL_PATIENCE.)
            near = self._m115s and self._since_m115 < SYNC_EVERY_MIN
            return not near or now >= self._acked_at + STALL_PATIENCE or self._asked_again
        wanted = self._sync_requested or bool(self._awaiting)
        return wanted and not self._pending and not (self._stale_answers and self._in_flight)

    def _answered_in_vain_from(self) -> float | None:
        """When the oldest M115 waiting was due to be answered at once: it is right behind
        the one an answer was last taken for (nothing between them) and was received."""
        m115s = self._m115s
        if not m115s or m115s[0].seq != self._answered_seq + 1 or not m115s[0].received:
            return None
        return max(self._answered_at, m115s[0].received_at)

    def _has_room(self, command: str, urgent_line: bool, host_line: bool = False) -> bool:
        if not self._in_flight:
            return True  # a line longer than the window still goes, alone
        size = len(command) + 1 + urgent_line  # its newline, its 0x09
        if self.numbered:
            size += len(str(self._next_number)) + 2  # "N<n> "
        if self.checksum:
            size += 7  # "*<sum>": a line of 96 ASCII bytes sums to at most 5 digits
        limit = self._host_byte_limit if host_line else self._byte_limit
        # The caller's lines: a sync goes past the line limit, and none holds a line back.
        lines = len(self._in_flight) - self._host_in_flight - host_line
        return lines < self._line_limit and self._in_flight_bytes + size <= limit

    def _transmit(
        self,
        command: str,
        word: str,
        tag: object,
        now: float,
        *,
        host_line: bool = False,
        confirm: bool = False,
        urgent: bool = False,
    ) -> SentLine:
        number = self._next_number if self.numbered else None
        self._next_number += 1
        wire = frame(command, number, self.checksum)
        if urgent:
            wire = mark_urgent(wire)
        self._seq = seq = self._seq + 1
        sent = SentLine(number, command, word, tag, len(wire), seq, host_line, confirm)
        if self.on_first_send is not None:  # an urgent line is the caller's (M112, a stop)
            self.on_first_send(command, tag, host_line and not urgent, number)
        received = not self._in_flight  # every line before this one
        if received:  # the first line waiting: its ACK is due from now
            self._last_progress_at = self._acked_at = now
        self._in_flight.append(sent)
        self._host_in_flight += host_line
        self._in_flight_bytes += sent.size
        self._outgoing += wire
        self.stats.bytes_sent += len(wire)
        if number is not None:
            self._recent[number] = tag
            self._recent.pop(number - RECENT, None)
        if word == "M115":
            self._asked_again = False
            self._m115s.append(sent)
            self._sync_sent_at = now
            self._since_m115 = 0
            self._moved_since_m115 = False
            if received:
                self._stale_answers = 0  # what an abort left behind came before those ACKs
        elif not host_line:
            self._sync_sent_at = None  # a line after the last M115: it confirms not this one
            self._since_m115 += 1
            self._moved_since_m115 = self._moved_since_m115 or word in _TAKE_TIME
        if not host_line:
            self._last_caller_seq = seq
            self.stats.lines_sent += 1
            self.last_sent = tag
            if confirm:
                self._awaiting.append(sent)
            else:  # a command (an M105 poll among a job's lines) is told once it ran
                self._unran.append(sent)
            if word in NOTICED:
                self._mcodes.append(sent)
        return sent

    def _ping(self, now: float) -> None:
        self._phase = HyrelPhase.GREETING
        self._hello_attempts += 1
        self._hello_deadline = now + HELLO_TIMEOUT
        self._outgoing.append(Control.PING)
        self.stats.pings += 1

    # --- input (the rest is HyrelReplies') ---------------------------------------

    def _learn_rate(self, seq: int, now: float) -> None:
        """Lines that run in SYNC_INTERVAL: those confirmed since the answer that last told,
        over the time since (a pause, a wait for lines counts: more syncs, for a while)."""
        elapsed = now - self._told_at
        if elapsed >= RATE_AFTER:
            ran = int((seq - self._told_seq) * SYNC_INTERVAL / elapsed)
            self._sync_every = max(SYNC_EVERY_MIN, min(SYNC_EVERY, 2 * self._sync_every, ran))
            self._told_at, self._told_seq = now, seq

    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    # --- time -------------------------------------------------------------------

    def next_deadline(self) -> float | None:
        phase = self._phase
        if phase is HyrelPhase.GREETING:
            return self._hello_deadline
        if phase is not HyrelPhase.RUNNING:
            return None
        deadline = self._last_sent_at + KEEPALIVE
        if self._in_flight:
            deadline = min(deadline, self._last_progress_at + self._status_after)
            if not self._stalled:
                deadline = min(deadline, self._acked_at + SYNC_AFTER)
        if self._sync_sent_at is not None:
            deadline = min(deadline, self._sync_sent_at + SYNC_RETRY)
        if self._fence_asked_at is not None and self._m115s:
            deadline = min(deadline, self._fence_asked_at + SEPARATOR_RETRY)
        answered_at = self._answered_in_vain_from()
        if answered_at is not None:
            deadline = min(deadline, answered_at + ANSWER_AT_ONCE)
        return deadline

    def handle_timeout(self, now: float) -> None:
        phase = self._phase
        if phase is HyrelPhase.GREETING:
            if now < self._hello_deadline:
                return
            waited = now - self._started_at
            if self._hello_attempts >= HELLO_ATTEMPTS:
                self._fail(
                    FailureKind.NO_ANSWER,
                    f"no answer to Hyrel's ping (0x07), sent {self._hello_attempts} times "
                    f"in {waited:.0f} s",
                )
                return
            self._ping(now)
            self._events.append(GreetingRetry(self._hello_attempts, HELLO_ATTEMPTS, waited))
            return
        if phase is not HyrelPhase.RUNNING:
            return
        if self._in_flight and not self._stalled and now >= self._acked_at + SYNC_AFTER:
            self._stalled = True
            self.stats.stalls_recovered += 1  # a sync will release what ran
            # What an abort left to come came before this quiet (or was never sent).
            self._stale_acks = self._stale_answers = 0
        if self._in_flight and now >= self._last_progress_at + self._status_after:
            if self._status_asked >= STATUS_ATTEMPTS:
                self._fail(
                    FailureKind.TIMEOUT,
                    f"the controller fell silent: no ACK and no answer to "
                    f"{STATUS_ATTEMPTS} status requests",
                )
                return
            self._status_asked += 1
            self._last_progress_at = now  # the next request after as long again
            self._ask_status()
        answered_at = self._answered_in_vain_from()
        if answered_at is not None and now >= answered_at + ANSWER_AT_ONCE:
            # Right behind one answered, nothing between them, received: it ran at once,
            # and its answer came then (not taken). It says no more than that one.
            self._answered_seq = self._m115s.popleft().seq
            self._synced_seq = max(self._synced_seq, self._answered_seq)
            self._doubt = False
            if not self._m115s:
                self._sync_sent_at = None
        asked = self._fence_asked_at
        if asked is not None and now >= asked + SEPARATOR_RETRY and self._m115s:
            self._fence_asked_at = now  # its reply, or the report it asked for, was lost
            self._ask_status()
        if self._sync_sent_at is not None and now >= self._sync_sent_at + SYNC_RETRY:
            self._sync_sent_at = None  # its answer was lost, or it waits long: ask again
            self._stalled = self._asked_again = True
        if now >= self._last_sent_at + KEEPALIVE and not self._outgoing:
            self._outgoing.append(Control.WATCHDOG)
