"""Moved to :mod:`repetrel_host.fakes.loopback`; this name still works."""

from repetrel_host.fakes.loopback import *  # noqa: F403
