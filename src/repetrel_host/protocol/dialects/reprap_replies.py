"""The RepRap dialect's reading of what the controller says: oks, resend requests, errors,
probe answers, and what they acknowledge or confirm.

A part of :class:`~repetrel_host.protocol.dialects.reprap.RepRapDialect`, kept apart for its
size: the state it reads and changes is the dialect's (declared below, set there).
"""

from __future__ import annotations

from collections import deque

from repetrel_host.gcode.commands import command_word
from repetrel_host.protocol import replies
from repetrel_host.protocol.dialect import Statistics
from repetrel_host.protocol.dialects.reprap_greeting import Greeting, RepRapPhase
from repetrel_host.protocol.dialects.reprap_line_errors import (
    is_checksum_error,
    is_number_error,
    stated_last_line,
)
from repetrel_host.protocol.dialects.reprap_probes import PROBE_COMMAND, Probing
from repetrel_host.protocol.events import (
    ControllerMessage,
    DialectFailed,
    Event,
    FailureKind,
    LineAcknowledged,
    Notice,
    ProbeKind,
    ResendRequested,
)
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.protocol.history import History, Line
from repetrel_host.protocol.reports import parse_temperatures, residency_left
from repetrel_host.protocol.resend import RESEND_LOOP_LIMIT, ResendGuard
from repetrel_host.protocol.rtt import RoundTrip
from repetrel_host.protocol.silence import Silence
from repetrel_host.protocol.window import Transmission, Window

PRUNE_STEP = 64  # lines forgotten at a time, past the history's margin
# An error that is not about a line becomes fatal after this long, or this many other
# replies, without a resend request (Marlin halts and says little more).
SUSPECT_ERROR_GRACE = 0.2
SUSPECT_ERROR_LINES = 2
# Warn once when more than this share of lines needed resending (after enough lines).
RESEND_WARNING_RATIO = 0.10
RESEND_WARNING_AFTER = 100
# OctoPrint's virtual printer (its M115: "FIRMWARE_NAME:Virtual Marlin 1.0 ...") reads a
# 64-byte receive buffer, and a write that does not fit waits for room while holding the
# lock its error replies need: with more than 64 bytes in flight, each error it reports (its
# simulated ones, the refusals of lines in flight behind them) stalls it for its 10 s write
# timeout, or several.
VIRTUAL_PRINTER = "FIRMWARE_NAME:Virtual Marlin"
VIRTUAL_PRINTER_RX_BUFFER = 64


class RepRapReplies:
    """What the RepRap dialect reads; :class:`RepRapDialect` is the rest of it."""

    # The dialect's state (see RepRapDialect.__init__).
    flow: FlowControl
    stats: Statistics
    _phase: RepRapPhase
    _history: History
    _window: Window
    _rtt: RoundTrip
    _guard: ResendGuard
    _probing: Probing
    _may_fall_back: bool
    _greeting: Greeting
    _silence: Silence
    _acked_through: int
    _confirmed_through: int
    _last_received_at: float
    _last_progress_at: float
    _machine_waited_until: float
    _previous_reply: replies.Reply | None
    _sync_answers: int
    _trailing_ok_until: float | None
    _suspect_error: tuple[str, float] | None
    _suspect_lines: int
    _line_error_at: float | None
    _warned_resends: bool
    _receive_buffer: bytearray
    _events: deque[Event]
    _failure: DialectFailed | None

    def _restart_greeting(self) -> None:
        """The dialect's: greet again, with the next attempt's numbers."""
        raise NotImplementedError

    # --- input ---------------------------------------------------------------------

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes read from the controller."""
        if not data:
            return
        self._last_received_at = now
        buffer = self._receive_buffer
        buffer += data
        start = 0
        while (end := buffer.find(b"\n", start)) >= 0:
            line_start, start = start, end + 1
            if (
                end - line_start == 2
                and buffer.startswith(b"ok", line_start)
                and self._trailing_ok_until is None
                and self._suspect_error is None
                and self._phase is RepRapPhase.RUNNING
            ):
                # A plain ok in a plain state, the bulk of all replies: the same as
                # the general path below, without decoding and classifying it.
                self._handle_ok(replies.PLAIN_OK, now)
                self._previous_reply = replies.PLAIN_OK
                continue
            text = buffer[line_start:end].decode("ascii", errors="replace").strip()
            if text:
                reply = replies.classify(text)
                trailing = self._trailing_ok_until
                self._trailing_ok_until = None  # it must be the very next line
                # Marlin's trailing ok is a plain one: an "ok T:..." answers a line.
                if not (
                    trailing is not None
                    and now <= trailing
                    and isinstance(reply, replies.Ok)
                    and not reply.data
                ):
                    self._handle_reply(reply, text, now)
                self._previous_reply = reply
        del buffer[:start]

    def _handle_reply(self, reply: replies.Reply, text: str, now: float) -> None:
        if self._phase is RepRapPhase.FAILED:
            return
        if self._suspect_error is not None:
            if isinstance(reply, replies.ResendRequest):
                self._suspect_error = None
            else:
                self._suspect_lines += 1
                if self._suspect_lines > SUSPECT_ERROR_LINES:
                    self._fail_suspect()
                    return
        if not isinstance(reply, replies.OtherReply) or "T:" in text:
            self._greeting.heard = True  # a garbled answer with temperatures is one too
        if isinstance(reply, replies.Ok):
            self._handle_ok(reply, now)
        elif isinstance(reply, replies.ResendRequest):
            self._handle_resend(reply.line_number, now)
        elif isinstance(reply, replies.Start):
            self._handle_start(text)
        elif isinstance(reply, replies.Error):
            if reply.line_error:
                # Told by the resend request that follows it; if none does, the
                # controller dropped the line without asking for it again.
                self._line_error_at = now
            else:
                # Fatal, unless a resend request follows: then it was a line error whose
                # words a garbled newline cut off ("Error:chec" / "ksum mismatch...").
                self._suspect_error = (reply.text, now + max(SUSPECT_ERROR_GRACE, self._rtt.rto))
                self._suspect_lines = 0
        else:
            if isinstance(reply, replies.Busy):
                self._last_progress_at = now  # a long command is running: not a lost ok
                self._silence.busy(now)
            elif isinstance(reply, replies.OtherReply):
                readings = parse_temperatures(text)
                if readings:  # an auto-report, a heat wait's
                    self._silence.temperatures(readings, now, residency_left(text))
                elif text.startswith(VIRTUAL_PRINTER):
                    self._keep_within(VIRTUAL_PRINTER_RX_BUFFER)
            self._events.append(ControllerMessage(reply, text))

    def _handle_ok(self, reply: replies.Ok, now: float) -> None:
        self._last_progress_at = now
        # A line error with an ok after it was answered (its resend request garbled, say);
        # only one the controller fell silent after dropped its line.
        self._line_error_at = None
        window = self._window
        in_flight = window.in_flight
        if not in_flight:
            self.stats.unexpected_oks += 1  # nothing owed one
            return
        readings = parse_temperatures(reply.data) if reply.data else None
        if readings:
            self._silence.temperatures(readings, now)
        if (
            reply.line_number is not None
            and reply.line_number < self._history.next_number
            and self.flow.mode is FlowMode.BUFFERED  # unbuffered means one line in flight
        ):
            window.read_through = reply.line_number
        if readings and self._answered_m105(reply, now):
            return
        transmission = in_flight[0]
        probe = self._probing.current
        if probe is not None and transmission is probe:
            greeting = self._phase is RepRapPhase.GREETING
            if greeting and probe.line is not None and self._may_fall_back and not readings:
                self._fall_back()
                return
            # Nothing is sent after a probe, and a probe draws no plain ok: this ok is one
            # too many (duplicated, or owed to a line already settled).
            self.stats.unexpected_oks += 1
            return
        window.pop_oldest()
        line = transmission.line
        if transmission.stale or line is None:
            return
        # A plain ok taken for the caller's M105, whose answers carry temperatures (one of
        # its own lost, or one said twice): the M105's answer may still come, and must not
        # confirm what follows it.
        if (
            not readings
            and line.command.startswith("M105")  # (a cheap test first: on every ok)
            and not line.is_host_line
            and self._probing.kind is ProbeKind.COMMAND
            and _is_probe_command(transmission)
        ):
            self._probing.stray += 1
        # Karn: no samples from retransmissions. Nor from the time a command took to run: an
        # unbuffered command's ok comes once the machine finished it (a heat-up: minutes),
        # and so do the oks of lines sent behind it. One such sample held the timeout at its
        # ceiling for hundreds of lines: every lost ok then cost 5 s. (M110 is answered at
        # once: its round trip is the first measured.)
        if line.unbuffered and not line.is_reset:
            self._machine_waited_until = now
            if not transmission.retransmitted:
                self._probing.unanswered = 0
        elif (
            not transmission.retransmitted
            and transmission.sent_at >= self._machine_waited_until
            and self._rtt.sample(now - transmission.sent_at)
        ):
            self._probing.unanswered = 0
        if line.is_host_line:
            return  # the probe behind an M110 confirms the reset
        self._acknowledge(line, now, reply.data)

    def _keep_within(self, rx_buffer: int) -> None:
        """OctoPrint's virtual printer said who it is: no more than its buffer in flight."""
        if self._window.byte_limit > rx_buffer:
            self._window.limit_bytes(rx_buffer)
            self._events.append(
                Notice(
                    "the controller is OctoPrint's virtual printer: at most "
                    f"{self._window.byte_limit} bytes in flight, as its receive buffer holds"
                )
            )

    def _set_aside_stray(self) -> bool:
        """The caller's M105 whose place a plain ok took may still answer: an answer is
        taken for its, and confirms nothing (False when none is owed)."""
        if not self._probing.stray:
            return False
        self._probing.stray -= 1
        self.stats.unexpected_oks += 1
        return True

    def _fall_back(self) -> None:
        """The greeting's M105 was answered by a plain ok: this controller's answer to a
        probe cannot be told from another line's. Greet again, probing with checksums."""
        self._may_fall_back = False
        self._probing.kind = ProbeKind.CHECKSUM
        self._events.append(
            Notice(
                "the controller answers M105 with a plain ok (its temperatures apart): "
                "probing with lines whose checksum is wrong on purpose, each of which it "
                "answers with an error"
            )
        )
        self._regreet()

    def _answered_m105(self, reply: replies.Ok, now: float) -> bool:
        """An "ok T:..." is an M105's answer: the first M105 on the wire ran (replies come in
        order, and oks lost before it must not hide it), and so had every line before it.
        True when the answer was taken so (or set aside), False when it is counted as any
        ok: the first M105 is the oldest transmission, the caller's."""
        window = self._window
        for transmission in window.in_flight:
            line = transmission.line
            if line is None:
                continue  # a checksum probe
            if line.is_reset:
                # An M110 is answered by a plain ok, before what follows it: an answer
                # first is an earlier M105's, said twice. (Its ok lost, it greets again.)
                self.stats.unexpected_oks += 1
                return True
            if command_word(line.command) == PROBE_COMMAND:
                break
        else:
            # No M105 on the wire: the late answer of one no longer counted, or one said
            # twice. It answers no other line.
            if not self._set_aside_stray():
                self.stats.unexpected_oks += 1
            return True
        if self._set_aside_stray():
            return True
        if transmission is self._probing.current:
            self._probe_answered(transmission, transmission.number, now)
            return True
        if transmission is window.in_flight[0] and not line.is_host_line:
            return False
        window.drop_through(transmission)
        number = transmission.number
        self._confirm_through(number - 1, now)
        if not line.is_host_line:
            self._acknowledge(line, now, reply.data, counted=False)
        self._confirm_through(number, now)
        return True

    def _handle_resend(self, number: int, now: float) -> None:
        self._last_progress_at = now
        self._line_error_at = None
        previous = self._previous_reply
        stated_last = stated_last_line(previous)
        if stated_last is not None and stated_last + 1 != number:
            self.stats.ignored_resend_requests += 1  # garbled: the two lines disagree
            return
        self._trailing_ok_until = now + self._rtt.trailing_ok_window
        phase = self._phase
        window = self._window
        probe = self._probing.current
        if (
            probe is not None
            and probe.line is None
            and number == probe.number
            and is_checksum_error(previous)
        ):
            self._probe_answered(probe, number - 1, now)
            return
        if self._guard.just_sent_again(number, now, self._rtt.rto):
            # An answer to an older transmission (a stale one, if one is still held): the
            # line's new transmission stays in flight, its own answer still to come. It is
            # one of the echoes expected, too: counted off, the request after them obeyed.
            if window.in_flight and window.in_flight[0].stale:
                window.pop_oldest()
                self._guard.is_echo(number)
            self.stats.ignored_resend_requests += 1
            return
        # An error, its resend request and (on most firmwares) an ok answer one
        # transmission, the oldest: the ok is part of that answer, not another one. A
        # checksum probe is answered so only when refused for its number (the controller
        # misses lines before it); after a checksum error this is another line's answer
        # (its ok was miscounted), and the probe's own is still to come.
        if window.in_flight and (
            window.in_flight[0] is not probe or probe.line is not None or is_number_error(previous)
        ):
            window.pop_oldest()
        if stated_last is not None and phase is RepRapPhase.RUNNING:
            self._confirm_through(stated_last, now)  # true whatever line drew it
        if self._guard.is_echo(number):
            # An echo of the request being served, from a line that was in transit
            # when the first came (the resend storm).
            self.stats.ignored_resend_requests += 1
            return
        if phase is RepRapPhase.GREETING:
            # An earlier greeting's answer, or this M110 did not take (corrupted, or
            # the board still booting): the hello timeout greets again, with new numbers.
            self.stats.ignored_resend_requests += 1
            return
        history = self._history
        if number == history.next_number:
            # "Send me the next line": everything sent was accepted.
            self._mark_in_flight_stale(number, now, expect_echoes=False)
            history.cursor = number
            self._probing.superseded()
            return
        line = history.get(number)
        if line is None or line.is_reset:
            self._unheld_request(number, corroborated=stated_last is not None)
            return
        rounds = self._guard.rounds(number)
        if rounds >= RESEND_LOOP_LIMIT:
            self._fail(
                FailureKind.CONTROLLER,
                f"the controller asked for line {number} ({line.command}) {rounds} times "
                "in a row; the link is too noisy to go on",
            )
            return
        self.stats.resend_requests += 1
        self._mark_in_flight_stale(number, now)
        history.cursor = number
        self._acked_through = min(self._acked_through, number - 1)
        self._probing.superseded()
        self._probing.stray = 0  # flushed, or answered among the stale lines' replies
        self._events.append(ResendRequested(number, line.command, line.tag))
        self._maybe_warn()

    def _probe_answered(self, probe: Transmission, accepted_through: int, now: float) -> None:
        """The controller accepted every line through ``accepted_through`` and nothing after."""
        self._probing.answered()
        self._probing.stray = 0  # every answer owed before the probe's came, or never will
        self._sync_answers += 1
        # Every transmission before the probe was answered (replies come in order),
        # whether or not its ok reached us; none was sent after it.
        self._window.drop_through(probe)
        self._guard.echoes = 0
        self._confirm_through(accepted_through, now)
        self._history.cursor = accepted_through + 1
        if self._phase is RepRapPhase.GREETING:
            self._finish_greeting(accepted_through)

    def _finish_greeting(self, accepted_through: int) -> None:
        self._phase = RepRapPhase.RUNNING
        self._acked_through = accepted_through
        ready = self._greeting.finished(self._probing.kind)
        if ready is not None:
            self._events.append(ready)

    def _handle_start(self, text: str) -> None:
        if self._greeting.greeted:
            # Never resend across a reset: the controller lost its queue and state.
            self._fail(FailureKind.RESET, "the controller reset (it sent 'start')")
        else:
            # The boot banner while greeting: the probe (or its timeout) tells the rest.
            self._events.append(ControllerMessage(replies.Start(), text))

    def _unheld_request(self, number: int, corroborated: bool) -> None:
        # A garbled number must not stop a job; a real request for a line we no
        # longer hold must. The controller repeats real requests.
        history = self._history
        seen = self._guard.unheld(number)
        if seen < 2 and not (corroborated and number < history.floor):
            self.stats.ignored_resend_requests += 1
            return
        if number >= history.next_number:
            reason = (
                f"the controller asked for line {number}, which the host never sent "
                f"(it holds lines {history.held()}): the controller counts lines its own "
                "way; stopping rather than guessing"
            )
        else:
            reason = (
                f"the controller asked for line {number} again, but the host holds only "
                f"lines {history.held()}; stopping rather than guessing"
            )
        self._fail(FailureKind.PROTOCOL, reason)

    def _maybe_warn(self) -> None:
        sent = self.stats.lines_sent
        if (
            not self._warned_resends
            and sent >= RESEND_WARNING_AFTER
            and self.stats.resend_requests > RESEND_WARNING_RATIO * sent
        ):
            self._warned_resends = True
            self._events.append(
                Notice(
                    f"{self.stats.resend_requests} resend requests for {sent} lines: "
                    "the serial link is noisy (check the cable, or lower the baud rate)"
                )
            )

    def _regreet(self) -> None:
        """Greet again with the next attempt's numbers."""
        self._window.forget()
        self._probing.current = None
        self._restart_greeting()

    def _acknowledge(self, line: Line, now: float, data: str = "", counted: bool = True) -> None:
        """``line`` was taken: by its ok (``counted``), or as the controller's numbers say."""
        number = line.number
        if number > self._acked_through:
            self._acked_through = number
        self._guard.progress(number)
        if not line.acknowledged:  # after a resend the controller may acknowledge it again
            line.acknowledged = True
            self._silence.acknowledged(now, counted)
            self._events.append(LineAcknowledged(number, line.command, line.tag, data))
        history = self._history
        if self._acked_through - history.margin > history.floor + PRUNE_STEP:
            history.prune(self._acked_through)  # in steps: not a call for every line

    def _confirm_through(self, number: int, now: float) -> None:
        """The controller said its last accepted line is ``number``: acknowledge up to it."""
        if number <= self._confirmed_through:
            return
        history = self._history
        start = max(self._confirmed_through + 1, history.floor)
        self._confirmed_through = number
        for n in range(start, number + 1):
            line = history.get(n)
            if line is not None and not line.is_host_line:
                self._acknowledge(line, now, counted=False)

    def _mark_in_flight_stale(self, number: int, now: float, expect_echoes: bool = True) -> None:
        # The transmission of line ``number`` drew this request (unless its reply was
        # counted off already); every other one in flight may draw an echo (or
        # nothing, if the controller flushed it or dropped it as a duplicate).
        window = self._window
        cause = any(t.number == number and t.line is not None for t in window.in_flight)
        self._guard.expect_echoes(number, len(window.in_flight) - cause if expect_echoes else 0)
        window.mark_stale(now + self._rtt.rto)
        self._sync_answers = 0  # lines go again: what the probes said is to be said again

    def _fail_suspect(self) -> None:
        assert self._suspect_error is not None
        self._fail(
            FailureKind.CONTROLLER,
            f"the controller reported an error: {self._suspect_error[0]}",
        )

    def _fail(self, kind: FailureKind, reason: str) -> None:
        self._phase = RepRapPhase.FAILED
        oldest = self._history.get(self._acked_through + 1)
        self._failure = DialectFailed(kind, reason, oldest.tag if oldest is not None else None)
        self._events.append(self._failure)


def _is_probe_command(transmission: Transmission) -> bool:
    """The transmission is an M105's (a command probe's, or one of the caller's)."""
    line = transmission.line
    return line is not None and command_word(line.command) == PROBE_COMMAND
