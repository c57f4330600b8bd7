"""How ``hyrel-send`` writes a duration and a clock time, everywhere it writes one.

A duration: ``4.2s`` (tenths under ten seconds, where a short run's figure would read 0),
``42s``, ``13m 05s``, ``1h 02m 03s``. A clock time: the local 24-hour ``20:05``, with the
date before it when it is not today (``2025-05-21 20:05``). Light on purpose: ``--check``
and the server client use it without loading the progress bar.
"""

from __future__ import annotations

from datetime import datetime, timedelta


def duration(seconds: float) -> str:
    """``seconds`` as ``4.2s``, ``42s``, ``13m 05s`` or ``1h 02m 03s``."""
    seconds = max(0.0, seconds)
    if seconds < 9.95:  # 9.96 would round to "10.0s": whole seconds from there
        return f"{seconds:.1f}s"
    minutes, second = divmod(int(seconds + 0.5), 60)
    hours, minute = divmod(minutes, 60)
    if hours:
        return f"{hours}h {minute:02d}m {second:02d}s"
    if minute:
        return f"{minute}m {second:02d}s"
    return f"{second}s"


def clock_time(when: datetime) -> str:
    """``when`` (naive: local; aware: converted to local) as ``20:05``, or with its date
    (``2025-05-21 20:05``) when that is not today."""
    local = when.astimezone() if when.tzinfo is not None else when
    now = datetime.now(local.tzinfo)
    return f"{local:%H:%M}" if local.date() == now.date() else f"{local:%Y-%m-%d %H:%M}"


def clock_in(seconds: float) -> str:
    """The clock time ``seconds`` from now (a job's end from its time left)."""
    return clock_time(datetime.now() + timedelta(seconds=seconds))


def clock_at(timestamp: float | str | None) -> str | None:
    """A server's time (seconds since the epoch, or ISO 8601) as a clock time; None as is."""
    if timestamp is None:
        return None
    if isinstance(timestamp, str):
        return clock_time(datetime.fromisoformat(timestamp))
    return clock_time(datetime.fromtimestamp(timestamp))
