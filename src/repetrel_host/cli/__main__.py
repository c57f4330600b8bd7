"""``python -m repetrel_host.cli``: hyrel-send."""

from repetrel_host.cli.app import main

main()
