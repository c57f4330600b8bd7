"""Moved to :mod:`repetrel_host.fakes.hyrel_simulator`; this name still works."""

from repetrel_host.fakes.hyrel_simulator import *  # noqa: F403
