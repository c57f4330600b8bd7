"""Moved to :mod:`repetrel_host.fakes.simulator`; this name still works."""

from repetrel_host.fakes.simulator import *  # noqa: F403
