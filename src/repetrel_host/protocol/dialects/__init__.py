"""Dialects by name: the line protocols of firmware families, behind one interface."""

from __future__ import annotations

from repetrel_host.errors import ConfigError
from repetrel_host.protocol.dialect import Dialect
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT, RepRapDialect
from repetrel_host.protocol.events import ProbeKind
from repetrel_host.protocol.flow import FlowControl

DIALECTS = {"reprap": RepRapDialect}


def create_dialect(
    name: str = "reprap",
    flow: FlowControl | None = None,
    *,
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    probe: ProbeKind | None = None,
) -> Dialect:
    """A new dialect for one connection."""
    kind = DIALECTS.get(name)
    if kind is None:
        raise ConfigError(f"unknown protocol '{name}' (known: {', '.join(sorted(DIALECTS))})")
    return kind(flow, reply_timeout=reply_timeout, probe=probe)
