"""The printer session: one long-lived connection to one controller (:mod:`.printer`), the
jobs it streams (:mod:`.job`, :mod:`.planning`, :mod:`.resume`), the sans-IO pump between
them and the dialect (:mod:`.pump`), the events it tells (:mod:`.events`) and its record
(:mod:`.history`). The public API is re-exported from ``repetrel_host``."""
