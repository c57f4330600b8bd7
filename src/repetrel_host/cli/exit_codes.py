"""hyrel-send's exit codes, in one place: distinct per kind of failure so scripts can tell
them apart. A run streamed here, its ``--console`` and a job followed on a print server
(``--server``, ``--farm``) all end with these."""

EXIT_OK = 0
EXIT_BAD_INPUT = 2  # also what typer uses for a bad option
EXIT_LINK_FAILURE = 3
EXIT_CONTROLLER_ERROR = 4
EXIT_NOT_SAFE = 5  # stopped, but the safe stop was not confirmed: go and look at the machine
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C
