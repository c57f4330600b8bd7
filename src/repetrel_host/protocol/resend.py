"""Which resend requests to obey: echoes of one request, loops, lines no longer held."""

from __future__ import annotations

# The same line requested this many times in a row, without progress, is a loop.
RESEND_LOOP_LIMIT = 10


class ResendGuard:
    """Remembers the request being served, to tell a real request from its echoes.

    - *Echoes*: with several lines in flight, a controller that refused one line
      refuses each line behind it too, each time asking for the same line again
      (the resend storm). Those requests are counted off, not obeyed.
    - *Loops*: the same line asked for round after round, with nothing acknowledged
      in between, means the link is too noisy to go on.
    - *Unheld lines*: a request for a line the host no longer holds may be a garbled
      number; only a repeated one is real.
    """

    __slots__ = (
        "_loop_count",
        "_loop_number",
        "_loop_sent_again",
        "_resent",
        "_unheld",
        "echoes",
        "target",
    )

    def __init__(self) -> None:
        self.target: int | None = None  # the line the last obeyed request asked for
        self.echoes = 0  # requests for it still expected from lines that were in flight
        self._loop_number = -1
        self._loop_count = 0
        self._loop_sent_again = False
        self._unheld: dict[int, int] = {}
        self._resent: dict[int, float] = {}  # lines sent again, and when (until progress)

    def expect_echoes(self, number: int, count: int) -> None:
        self.target = number
        self.echoes = count

    def is_echo(self, number: int) -> bool:
        """True (and counted off) when this request repeats the one being served."""
        if self.echoes and number == self.target:
            self.echoes -= 1
            return True
        return False

    def rounds(self, number: int) -> int:
        """Count a request for ``number``; how many rounds in a row it has been asked for.

        A request counts again only once the line went out again: more requests
        before that are echoes the storm rules did not catch.
        """
        if number == self._loop_number:
            if not self._loop_sent_again:
                return 0
            self._loop_count += 1
        else:
            self._loop_number, self._loop_count = number, 1
        self._loop_sent_again = False
        return self._loop_count

    def sent_again(self, number: int, now: float) -> None:
        if number == self._loop_number:
            self._loop_sent_again = True
        self._resent[number] = now

    def just_sent_again(self, number: int, now: float, round_trip: float) -> bool:
        """A request for a line that went out again less than a round trip ago cannot be
        about that transmission: it is one more answer to an older one, still queued
        behind the replies a slow link carries. Obeying it would add another refusal to
        that queue, and another request, without end."""
        resent_at = self._resent.get(number)
        return resent_at is not None and now - resent_at < round_trip

    def progress(self, number: int) -> None:
        """Line ``number`` was acknowledged: only requests repeated without progress count."""
        if number > self._loop_number:
            self._loop_count = 0
        if self._resent:
            self._resent = {n: at for n, at in self._resent.items() if n > number}
        if self._unheld:
            self._unheld.clear()

    def unheld(self, number: int) -> int:
        """Count a request for a line not held; how many times it was seen."""
        seen = self._unheld.get(number, 0) + 1
        self._unheld[number] = seen
        return seen
