"""The Hyrel dialect's reading of what the controller writes: the ACK bytes (each releases
the oldest line on the wire), M115's answers (that M115 ran, and every line before it), the
notices of the M-codes it ran, its messages and error reports, and its identity (the ping's
answer, or a controller that reset); and the dialect's failure.

A part of :class:`~repetrel_host.protocol.dialects.hyrel.HyrelDialect`, kept apart for its
size: the state it reads and changes is the dialect's (declared below, set there). How
answers are told apart and counted is on that module's page.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects.hyrel_answers import (
    ANSWER_NAME,
    ANSWER_PARTS,
    AnswerCounter,
    answer_name_at,
    answer_run_in,
    answer_starts,
    line_named,
    message_run_on,
    notice_agrees,
)
from repetrel_host.protocol.events import (
    ControllerMessage,
    ControllerReady,
    DialectFailed,
    Event,
    FailureKind,
    LineAcknowledged,
    LineRefused,
    ProbeKind,
)
from repetrel_host.protocol.hyrel import Control, HostReceiver, HyrelNotice, parse_notice

_FATAL = re.compile(r"checksum|watchdog", re.IGNORECASE)


class HyrelPhase(Enum):
    """Where the Hyrel dialect stands."""

    IDLE = "idle"
    GREETING = "greeting"
    RUNNING = "running"
    FAILED = "failed"


@dataclass(slots=True)
class SentLine:
    """A line on the wire, kept until it is known to have arrived or run."""

    number: int | None
    command: str
    word: str
    tag: object
    size: int
    seq: int  # its place on the wire, the host's own lines counted
    host_line: bool = False  # a sync, an urgent M112: not the caller's
    confirm: bool = False  # told once it ran, not once it was received
    reaches: int = 0  # a sync just before an M0: its answer says the M0 was reached too
    again: bool = False  # an M115 sent right after the last one, which may wait in vain
    received: bool = False  # its ACK came (or an answer said it ran)
    received_at: float = 0.0


class HyrelReplies:
    """What the Hyrel dialect reads; :class:`HyrelDialect` is the rest of it."""

    # The dialect's state (see HyrelDialect.__init__).
    stats: Statistics
    last_ran: object | None
    _phase: HyrelPhase
    _failure: DialectFailed | None
    _events: deque[Event]
    _outgoing: bytearray
    _receiver: HostReceiver
    _in_flight: deque[SentLine]
    _in_flight_bytes: int
    _host_in_flight: int
    _stale_acks: int
    _awaiting: deque[SentLine]
    _unran: deque[SentLine]
    _mcodes: deque[SentLine]
    _m115s: deque[SentLine]
    _stale_answers: int
    _answers: AnswerCounter
    _separated: bool
    _cut_tag: bool
    _doubt: bool
    _answered_seq: int
    _answered_at: float
    _fence_asked_at: float | None
    _recent: dict[int, object]
    _seq: int
    _confirmed_seq: int
    _synced_seq: int
    _sync_sent_at: float | None
    _stalled: bool
    _acked_at: float
    _hello_attempts: int
    _hello_deadline: float
    _late_pings: int
    _last_progress_at: float
    _status_asked: int

    def _learn_rate(self, seq: int, now: float) -> None:
        """The dialect's: how many lines run in a while, from an answer's line ``seq``."""
        raise NotImplementedError

    # --- input ------------------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        if not data or self._phase is HyrelPhase.FAILED:
            return
        receiver = self._receiver
        lines = receiver.feed(data)
        acks = receiver.take_acks()
        taken = 0
        for text, before, acked, inside in zip(
            lines, receiver.acks_before, receiver.acked_ahead, receiver.acks_inside, strict=True
        ):
            for _ in range(before - taken):  # in the order the controller wrote them
                self._acknowledged(now)
            taken = before
            self._handle_line(text, now, acked, inside)
            if self._failure is not None:
                return
        for _ in range(acks - taken):
            self._acknowledged(now)

    def _acknowledged(self, now: float) -> None:
        if self._stale_acks:
            self._stale_acks -= 1  # for a line an abort dropped: the controller is there
            self._last_progress_at = self._acked_at = now
            return
        if not self._in_flight:
            self.stats.unexpected_oks += 1  # an ACK nothing was owed
            return
        self._last_progress_at = self._acked_at = now
        self._status_asked = 0
        self._stalled = False
        self._release(self._in_flight.popleft(), now)

    def _release(self, sent: SentLine, now: float) -> None:
        """A line leaves the window; a plain caller's line is acknowledged with it."""
        self._in_flight_bytes -= sent.size
        self._host_in_flight -= sent.host_line
        if not sent.received:
            sent.received, sent.received_at = True, now
        if not sent.host_line and not sent.confirm:
            self._tell(sent)

    def _tell(self, sent: SentLine) -> None:
        number = sent.number if sent.number is not None else -1
        self._events.append(LineAcknowledged(number, sent.command, sent.tag, ""))

    def _handle_line(
        self, text: str, now: float, acked: bool = False, acks_inside: Sequence[int] = ()
    ) -> None:
        """``acked``: an ACK came between the line before and this one; ``acks_inside``:
        where in it ACKs came."""
        run_in = answer_run_in(text)
        if run_in:  # a message whose newline was garbled, and an answer after it
            self._handle_line(text[: run_in - 1], now, acked)
            text, acked, acks_inside = text[run_in:], False, [a - run_in for a in acks_inside]
        run_on = message_run_on(text) if not text.startswith(">") and ANSWER_NAME in text else 0
        if run_on:  # an answer whose newline was garbled, and a message after it
            self._handle_line(text[:run_on], now, acked, acks_inside)
            text, acked = text[run_on:], False
        reply = replies.classify(text)
        self._last_progress_at = now
        self._status_asked = 0
        hyrel = reply if isinstance(reply, replies.HyrelReport) else None
        cut_tag, self._cut_tag = self._cut_tag, hyrel is not None and not hyrel.text
        answers = self._answers.count(text, hyrel)  # first: one cut in two may read ">Hy: ..."
        if answers or any(part in text for part in ANSWER_PARTS):
            # Written apart from the line before: an ACK, or bytes of garbled ones, came
            # before its name, whole (not a garbled byte of it, nor that line's newline).
            name_at = answer_name_at(text)
            if answers and (name_at > 0 or (name_at == 0 and acked)):
                self._separated = True
            if cut_tag:
                self._separated = False  # ">IN:" and, cut off, the identity it quoted
            starts = answer_starts(text, answers)
            for index in range(answers):  # run together by a garbled newline
                # Two ACKs between them: written apart (the newline, garbled, is one byte).
                if index and sum(starts[index - 1] < at <= starts[index] for at in acks_inside) > 1:
                    self._separated = True
                self._answered(reply, text, now)
            if not answers and ANSWER_NAME in text:  # a quote, or one run into a message
                self._doubt = self._doubt or bool(self._m115s)  # (a newline garbled)
            if not answers:
                self._events.append(ControllerMessage(reply, text))
            return
        if acked or (hyrel is not None and hyrel.tag != "HY" and hyrel.text):
            self._separated = True
            self._fence_asked_at = None
        elif not self._separated and self._m115s:
            self._fence_asked_at = None  # a status reply garbled, maybe: ask again at once
        if hyrel is not None and hyrel.tag == "HY":
            self._identity(text, now)
            return
        number = line_named(text) if hyrel is not None else None
        named = self._recent.get(number or -1)
        if hyrel is not None and hyrel.tag == "ER" and _FATAL.search(text):
            # A line refused cannot be sent again in its place; the watchdog stopped the
            # extruders: the job cannot go on as written. The link can.
            self._events.append(LineRefused(f"the controller says: {text}", named))
            return
        self._events.append(ControllerMessage(reply, text, named))
        if hyrel is not None and hyrel.tag == "MC":
            notice = parse_notice(hyrel.text)
            if notice is not None:
                self._noticed(notice)

    def _identity(self, text: str, now: float) -> None:
        """``>Hy: ...``: the answer to a ping, or, unasked, a controller that restarted."""
        if self._phase is HyrelPhase.GREETING:
            self._phase = HyrelPhase.RUNNING
            self._late_pings = self._hello_attempts - 1  # pings that may be answered yet
            self._events.append(ControllerReady(ProbeKind.ANSWER, text))
        elif self._late_pings and now <= self._hello_deadline:
            self._late_pings -= 1  # the late answer to an earlier ping
        else:
            self._fail(FailureKind.RESET, f"the controller reset (it says: {text})")

    def _answered(self, reply: replies.Reply, text: str, now: float) -> None:
        """An M115 ran, so did every line before it (whatever ACKs were lost on the way),
        unless this is the answer before said again."""
        separated, self._separated = self._separated, False
        self._fence_asked_at = None
        m115s = self._m115s
        if not separated:
            # Not taken. Should it have been an M115's own, the oldest waits in vain.
            self._doubt = self._doubt or bool(m115s)
            return
        if self._stale_answers:
            self._stale_answers -= 1  # an M115's that an abort dropped: it ran before
            return
        if not self._m115s:
            self._events.append(ControllerMessage(reply, text))  # nobody asked
            return
        m115 = m115s.popleft()
        if not m115.host_line:
            self._events.append(ControllerMessage(reply, text))  # the caller's answer
        self._doubt = self._doubt and bool(m115s)  # the next may be the one answered
        self._answered_seq, self._answered_at = m115.seq, now
        if not m115s:
            self._sync_sent_at = None
        seq = max(m115.seq, m115.reaches)
        self._learn_rate(seq, now)
        self._synced_seq = max(self._synced_seq, seq)
        self._confirm_through(seq)
        # What ran was received: an ACK not here yet for it was lost. (It cannot be on
        # its way still: the controller sent it as the line came, or, lacking headroom
        # then, once it had read out enough lines, before the line ran.)
        in_flight = self._in_flight
        while in_flight and in_flight[0].seq <= seq:
            self.stats.lost_acks += 1
            self._release(in_flight.popleft(), now)

    def _noticed(self, notice: HyrelNotice) -> None:
        """``>MC:`` for an M-code: a line of its code and values ran, and every line before
        it. It is taken for the oldest such line not known to have run that the controller
        received (its ACK came: a line is ACKed before it runs), or for nothing (a notice
        garbled, of a line an answer confirmed, of an M-code the host did not send). The
        line it is about is that one or a later one: the notices of those before were lost
        or garbled, or never sent. A command's reply is complete then; a job is done only
        once an answer says so."""
        received = self._in_flight[0].seq if self._in_flight else self._seq + 1
        for sent in self._mcodes:
            if sent.seq >= received:
                return
            if sent.word == notice.code and notice_agrees(notice, sent.command):
                self._confirm_through(sent.seq)
                self._ran_before(sent.seq)
                return

    def _ran_before(self, seq: int) -> None:
        """The M115s before line ``seq`` ran (its notice came): their answers came before,
        taken or not. None of them waits any longer."""
        m115s = self._m115s
        if not m115s or m115s[0].seq >= seq:
            return
        while m115s and m115s[0].seq < seq:
            self._answered_seq = m115s.popleft().seq
        self._synced_seq = max(self._synced_seq, self._answered_seq)
        self._answered_at = self._last_progress_at
        self._doubt = False
        if not m115s:
            self._sync_sent_at = None

    def _confirm_through(self, seq: int) -> None:
        """Every line up to ``seq`` ran: commands up to it have their reply."""
        if seq <= self._confirmed_seq:
            return
        self._confirmed_seq = seq
        unran = self._unran
        while unran and unran[0].seq <= seq:
            self.last_ran = unran.popleft().tag
        awaiting = self._awaiting
        while awaiting and awaiting[0].seq <= seq:
            self._tell(awaiting.popleft())
        mcodes = self._mcodes
        while mcodes and mcodes[0].seq <= seq:
            mcodes.popleft()

    def _fail(self, kind: FailureKind, reason: str) -> None:
        if self._phase is HyrelPhase.RUNNING:
            # Whatever it holds must not run on (should it be there, and not have reset):
            # the safe stop goes at the next greeting.
            self._outgoing.append(Control.ABORT)
        oldest = next((s for s in self._in_flight if not s.host_line), None)
        if oldest is None and self._awaiting:
            oldest = self._awaiting[0]
        tag = oldest.tag if oldest is not None else None
        self._failure = DialectFailed(kind, reason, tag)
        self._phase = HyrelPhase.FAILED
        self._events.append(self._failure)
