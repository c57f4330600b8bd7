"""OctoPrint's face of the print server: its REST API (:mod:`.rest` mounts it, a module a
resource as OctoPrint's ``octoprint/server/api/``: :mod:`.version`, :mod:`.login`,
:mod:`.settings`, :mod:`.printer_profiles`, :mod:`.system`, :mod:`.connection`,
:mod:`.files`, :mod:`.job`, :mod:`.printer`; what they share in :mod:`.common`, their
answers' parts in :mod:`.model`), its push socket (what is pushed and when, :mod:`.push`,
its messages and terminal lines, :mod:`.messages` and :mod:`.terminal`; its transports,
:mod:`.sockjs`) and app keys (:mod:`.appkeys`)."""
