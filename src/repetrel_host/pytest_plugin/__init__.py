"""The pytest plugin: the same test on the fake controller and on the printer on the bench.

Installed with the package (the ``pytest11`` entry point ``hyrel``; ``-p no:hyrel``
turns it off). Without ``--hyrel-port`` every test gets the built-in fake controller on a
fresh pty, started for that test alone; with it, one session on the real port serves the
whole test run, as a printer is one physical thing. Fixtures:

- ``hyrel_printer``: a READY printer session behind a synchronous facade
  (:class:`HyrelPrinter`); ``hyrel_aprinter``: the same, awaitable (:class:`AsyncHyrelPrinter`),
  from any asyncio event loop (pytest-asyncio, anyio on asyncio, ``asyncio.run``);
- ``hyrel_controller``: what the test talks to (:class:`HyrelController`): its port, and
  on the fake its executed commands, fault switches and heaters;
- ``hyrel_job``: jobs from text or a file (:class:`HyrelJob`).

Markers: ``hyrel_hardware``, ``hyrel_fake_only``, ``hyrel_machine(NAME...)``,
``hyrel_fake(heat_rate=..., faults=...)``. A failed test's report gets the last lines
exchanged on the wire and the controller's messages. Teardown leaves the machine safe:
a job still running is cancelled (the safe stop first); after a failed test and at the
end of a bench run the safe-stop sequence is sent (a heat wait ended first with M108),
and a safe stop not confirmed in time fails the teardown.

Models: pytest-embedded (options in a group, a DUT fixture, its log in the report),
labgrid's pytest plugin (the same test on a board or on an emulator).

The plugin's modules: ``options`` (command line, environment, ini file, markers),
``fixtures``, ``facade`` (what tests hold), ``teardown`` (the machine left safe) and
``report`` (the wire in a failed test's report). This module gathers their hooks and
fixtures, which is what pytest reads from a plugin.
"""

try:
    import pytest  # noqa: F401  (what every module here needs)
except ModuleNotFoundError:  # the plugin without its extra, imported by hand
    raise ModuleNotFoundError(
        "repetrel_host.pytest_plugin needs pytest: pip install -e '.[hil]' in repetrel-host's clone"
    ) from None

from repetrel_host.pytest_plugin.facade import (
    AsyncHyrelPrinter,
    AsyncRunningJob,
    HyrelController,
    HyrelPrinter,
    RunningJob,
)
from repetrel_host.pytest_plugin.fixtures import (
    _hyrel_session,
    hyrel_aprinter,
    hyrel_controller,
    hyrel_job,
    hyrel_options,
    hyrel_printer,
)
from repetrel_host.pytest_plugin.jobs import HyrelJob, PrintResult
from repetrel_host.pytest_plugin.options import (
    HyrelOptions,
    pytest_addoption,
    pytest_collection_modifyitems,
    pytest_configure,
    pytest_runtest_setup,
)
from repetrel_host.pytest_plugin.report import WireRecorder, pytest_runtest_makereport

__all__ = [
    "AsyncHyrelPrinter",
    "AsyncRunningJob",
    "HyrelController",
    "HyrelJob",
    "HyrelOptions",
    "HyrelPrinter",
    "PrintResult",
    "RunningJob",
    "WireRecorder",
    "_hyrel_session",
    "hyrel_aprinter",
    "hyrel_controller",
    "hyrel_job",
    "hyrel_options",
    "hyrel_printer",
    "pytest_addoption",
    "pytest_collection_modifyitems",
    "pytest_configure",
    "pytest_runtest_makereport",
    "pytest_runtest_setup",
]
