"""The printer session: one long-lived connection to one controller (:mod:`.printer`),
opened by :mod:`.connect` over a link's connection (:mod:`.connection`, with
:mod:`.settings`), greeted (:mod:`.greeting`) and opened or greeted again
(:mod:`.reconnect`), knowing what the controller is (:mod:`.identify`) and what safe stop it
still owes (:mod:`.owed`); the commands it sends (:mod:`.commands`, waiting in
:mod:`.command_queue`), the jobs it streams (:mod:`.job_control`, :mod:`.print_job`,
:mod:`.job`, :mod:`.planning`, with the Hyrel :mod:`.header`), the machine's state along a
job (:mod:`.machine_state`) and a stopped print's recovery (:mod:`.recovery`), the sans-IO
pump between them and the dialect (:mod:`.pump`) and what the pump tells it
(:mod:`.listener`), the events it tells (:mod:`.events`, handed out by :mod:`.hub`) and its
record (:mod:`.history`). The public API is re-exported from ``repetrel_host``."""
