"""Dialects by name: the line protocols of firmware families, behind one interface."""

from __future__ import annotations

from repetrel_host.errors import ConfigError
from repetrel_host.protocol.dialect import Dialect
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT, RepRapDialect
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.flow import FlowControl

PROTOCOLS = ("reprap", "hyrel")


def create_dialect(
    name: str = "reprap",
    flow: FlowControl | None = None,
    *,
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    probe: ProbeKind | None = None,
    checksum: bool = False,
) -> Dialect:
    """A new dialect for one connection: ``reprap`` (``probe``: how to probe, None: found
    at the greeting) or ``hyrel`` (``checksum``: the additive checksum on every line)."""
    if name == "reprap":
        return RepRapDialect(flow, reply_timeout=reply_timeout, probe=probe)
    if name == "hyrel":  # imported here: a RepRap session starts without it
        from repetrel_host.protocol.dialects.hyrel import HyrelDialect

        return HyrelDialect(flow, checksum=checksum, reply_timeout=reply_timeout)
    raise ConfigError(f"unknown protocol '{name}' (known: {', '.join(PROTOCOLS)})")


def release_bytes(name: str) -> bytes:
    """What to write on a connection before its greeting when a safe stop is owed, so that
    nothing the controller still holds or waits for holds the safe stop up: on Hyrel's
    link abort (the job's lines it holds are dropped: they must not run after a failed
    job) and end-wait (a pause, its own M0, a heat-up); on the RepRap link ``M108``, which
    ends a heat wait where the firmware reads it at once (Marlin's emergency parser), and
    elsewhere is one more command, answered before the greeting's quiet ends."""
    if name == "hyrel":
        from repetrel_host.protocol.hyrel import Control

        return bytes([Control.ABORT, Control.END_WAIT])
    return b"M108\n"
