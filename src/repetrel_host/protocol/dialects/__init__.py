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
