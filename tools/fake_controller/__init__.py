"""Command-line entry: ``python -m tools.fake_controller --link /tmp/hyrel0``.

The controller itself lives in :mod:`repetrel_host.fakes.fake_controller` so that it
ships in the wheel with the pytest plugin.
"""
