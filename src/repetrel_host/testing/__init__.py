"""The old home of the fake controllers and the pytest plugin, kept so that imports written
for it still work: the controllers are in :mod:`repetrel_host.fakes`, the plugin in
:mod:`repetrel_host.pytest_plugin`."""
