"""The round-trip estimate and the retransmission timeout (RFC 6298), on injected time."""

from __future__ import annotations

# Clamped as Klipper's serial queue does: short enough that a lost ok costs a fraction
# of a second on a fast link, long enough not to ping during a slow USB frame.
MIN_RTO = 0.025
MAX_RTO = 5.0
INITIAL_RTO = 1.0
# A round trip under a quarter of the smoothed one is taken for an outlier.
RTT_OUTLIER = 0.25
RTT_NUDGE = 0.98
# Marlin ends a line error with an ok, written right behind the resend request;
# some 2.0.x builds leave it out. An ok arriving within half the smoothed round
# trip is that trailing ok, not the answer to a line sent since.
TRAILING_OK_SHARE = 0.5
TRAILING_OK_WINDOW = 0.002  # before any round trip was measured
MAX_BACKOFF_EXPONENT = 4


class RoundTrip:
    """Smoothed round trip, its variation, and the timeout they give."""

    __slots__ = ("rto", "rttvar", "srtt")

    def __init__(self) -> None:
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rto = INITIAL_RTO

    def sample(self, rtt: float) -> bool:
        """Take one measured round trip; False when it was set aside as an outlier."""
        srtt = self.srtt
        if srtt is not None and rtt < srtt * RTT_OUTLIER:
            # Most likely a duplicated ok taken for a line just sent: let it only
            # nudge the estimate, or the trailing-ok window would shrink to nothing.
            self.srtt = srtt * RTT_NUDGE
            return False
        if srtt is None:
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(srtt - rtt)
            self.srtt = 0.875 * srtt + 0.125 * rtt
        self.rto = min(max(self.srtt + 4 * self.rttvar, MIN_RTO), MAX_RTO)
        return True

    def backed_off(self, attempts: int) -> float:
        """The timeout after ``attempts`` unanswered tries: doubled each time, capped."""
        return min(self.rto * 2.0 ** min(attempts, MAX_BACKOFF_EXPONENT), MAX_RTO)

    @property
    def trailing_ok_window(self) -> float:
        return TRAILING_OK_WINDOW if self.srtt is None else self.srtt * TRAILING_OK_SHARE
