"""What the face tells of the machine the server runs on (Linux's /proc; zeros elsewhere)."""

from __future__ import annotations

import os
import time


def meminfo(field: str) -> int:
    """A field of /proc/meminfo in kB (``MemTotal``, ``MemAvailable``)."""
    return _field("/proc/meminfo", field)


def system_memory() -> dict[str, int]:
    """The machine's memory in kB, as Moonraker's process statistics give it (KlipperScreen
    reads it from every ``notify_proc_stat_update``)."""
    total, available = meminfo("MemTotal"), meminfo("MemAvailable")
    return {"total": total, "available": available, "used": total - available}


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


def interfaces() -> dict[str, dict[str, object]]:
    """The network interfaces by name, with their MAC address (Moonraker's system info;
    their addresses are not read: Python has no portable way)."""
    found: dict[str, dict[str, object]] = {}
    try:
        names = sorted(os.listdir("/sys/class/net"))
    except OSError:
        return found
    for name in names:
        try:
            with open(f"/sys/class/net/{name}/address") as address:
                mac = address.read().strip()
        except OSError:
            mac = ""
        found[name] = {"mac_address": mac, "ip_addresses": []}
    return found


class Usage:
    """The machine's CPU use (each CPU's and the whole's, in %) and each network
    interface's counters and bandwidth, since the last sample (Linux's /proc)."""

    def __init__(self) -> None:
        self.at = time.monotonic()
        self.cpus: dict[str, tuple[int, int]] = {}  # name: (all ticks, idle ticks)
        self.bytes: dict[str, int] = {}  # an interface's bytes both ways
        self.sample()  # the first figures count from here

    def sample(self) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
        now = time.monotonic()
        elapsed, self.at = max(now - self.at, 1e-3), now
        return self._cpu(), self._network(elapsed)

    def _cpu(self) -> dict[str, float]:
        usage: dict[str, float] = {}
        try:
            with open("/proc/stat") as stat:
                lines = [line.split() for line in stat if line.startswith("cpu")]
        except OSError:
            return usage
        for name, *ticks in lines:
            total, idle = sum(int(t) for t in ticks), int(ticks[3])
            last = self.cpus.get(name)
            if last is not None:
                ticks_since, busy = total - last[0], (total - last[0]) - (idle - last[1])
                usage[name] = round(100 * busy / ticks_since, 2) if ticks_since else 0.0
            self.cpus[name] = (total, idle)
        return usage

    def _network(self, elapsed: float) -> dict[str, dict[str, float]]:
        found: dict[str, dict[str, float]] = {}
        try:
            with open("/proc/net/dev") as dev:
                lines = [line for line in dev if ":" in line]
        except OSError:
            return found
        for line in lines:
            name, _, numbers = line.partition(":")
            n = [int(x) for x in numbers.split()]
            name = name.strip()
            both = n[0] + n[8]
            last = self.bytes.get(name)
            self.bytes[name] = both
            found[name] = {
                "rx_bytes": n[0],
                "tx_bytes": n[8],
                "rx_packets": n[1],
                "tx_packets": n[9],
                "rx_errs": n[2],
                "tx_errs": n[10],
                "rx_drop": n[3],
                "tx_drop": n[11],
                "bandwidth": round((both - last) / elapsed, 2) if last is not None else 0.0,
            }
        return found
