"""Moved to :mod:`repetrel_host.fakes.fake_controller`; this name still works."""

from repetrel_host.fakes.fake_controller import *  # noqa: F403
from repetrel_host.fakes.fake_controller import main

if __name__ == "__main__":
    main()
