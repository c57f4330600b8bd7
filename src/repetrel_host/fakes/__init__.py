"""The simulated controllers: the pty fake (``hyrel-fake-controller``), the in-process
simulators of both links, and the loopback that runs a host against them on simulated time.
Low in the house: ``links/`` and the tests use them."""
