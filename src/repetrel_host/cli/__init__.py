"""``hyrel-send``: the typer app (:mod:`.app`, its exit codes in :mod:`.exit_codes`), a job
streamed at the terminal (:mod:`.send`), sent to a print server or its farm (:mod:`.remote`,
over :mod:`.server_client`), what needs no printer (:mod:`.offline`), the console
(:mod:`.console`), the status line (:mod:`.display`) and the host actions carried out at a
terminal (:mod:`.actions`). Presentation only: the work is the session's."""
