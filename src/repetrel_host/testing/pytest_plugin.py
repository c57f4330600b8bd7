"""Moved to :mod:`repetrel_host.pytest_plugin`: its classes are still importable here. The
plugin itself loads from its new name (the ``hyrel`` entry point), once."""

from repetrel_host.pytest_plugin import (  # noqa: F401
    AsyncHyrelPrinter,
    AsyncRunningJob,
    HyrelController,
    HyrelJob,
    HyrelOptions,
    HyrelPrinter,
    PrintResult,
    RunningJob,
)
