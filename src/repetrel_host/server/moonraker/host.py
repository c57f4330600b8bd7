"""What the face tells of the machine the server runs on (Linux's /proc; zeros elsewhere)."""

from __future__ import annotations

import time


def meminfo(field: str) -> int:
    """A field of /proc/meminfo in kB (``MemTotal``, ``MemAvailable``)."""
    return _field("/proc/meminfo", field)


def own_memory() -> int:
    """The server's resident memory in kB."""
    return _field("/proc/self/status", "VmRSS")


def uptime() -> float:
    """Seconds since the machine started."""
    try:
        with open("/proc/uptime") as found:
            return float(found.read().split()[0])
    except (OSError, ValueError):
        return time.monotonic()


def _field(path: str, field: str) -> int:
    try:
        with open(path) as found:
            for line in found:
                if line.startswith(f"{field}:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0
