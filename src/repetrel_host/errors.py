"""Error types, caught once at the edge (CLI exit codes, later HTTP statuses)."""


class HostError(Exception):
    """Base of every error this package raises on purpose; its text is one sentence."""


class UsageError(HostError):
    """The API was used in a way it cannot be (a command while printing, M110 queued)."""


class JobError(HostError):
    """The job cannot be sent as it is (missing file, a line that cannot be framed)."""


class LinkError(HostError):
    """The serial link could not be opened, or failed or went silent while in use."""


class ProtocolError(HostError):
    """The controller broke the line protocol (e.g. asked for a line no longer held)."""


class ControllerError(HostError):
    """The controller reported an error of its own (``Error:``, ``!!``) or reset mid-job."""


class ConfigError(HostError):
    """A configuration value is missing or invalid."""


class SafeStopError(HostError):
    """A job stopped, but its safe stop was not confirmed: the machine may not be safe
    (heaters on, the head on the part). The sentence says what may be on and what to do."""
