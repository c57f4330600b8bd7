"""``hyrel-send``: the typer app (:mod:`.app`), its console (:mod:`.console`), status line
(:mod:`.display`) and the host actions it carries out at a terminal (:mod:`.actions`).
Presentation only: the work is the session's."""
