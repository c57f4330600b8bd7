"""The print server: a daemon that owns the printers (``hyrel-server``)."""
