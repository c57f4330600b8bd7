"""What a simulated controller is (its link, buffers, planner, heaters), what goes wrong on
its link (:class:`Faults`), and what it counts.

The defaults are Marlin 2.1.x's, as its source has them (docs/fake-controller.md): 4
command slots (BUFSIZE), 16 planner blocks, a 128-byte receive ring that loses what does
not fit, the receive buffer emptied on every line error, a resent copy of the last line
dropped without a word, ``echo:busy: processing`` every 2 s while a command holds the
queue (HOST_KEEPALIVE_FEATURE), and the emergency parser. Faults come on top of that.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from enum import Enum

from repetrel_host.gcode.estimate import Limits

# Marlin's DEFAULT_KEEPALIVE_INTERVAL: seconds between "busy: processing" lines (M113).
KEEPALIVE_INTERVAL = 2.0


class Overflow(Enum):
    """What the receive buffer does with bytes that do not fit."""

    DROP = "drop"  # a UART: the bytes are lost
    BLOCK = "block"  # USB: the sender is held back


@dataclass(frozen=True, slots=True)
class Faults:
    """What goes wrong, and how often (shares between 0 and 1); and three switches for
    firmwares that are not Marlin 2.1's (``flush_on_error=0``, ``drop_duplicates=0``,
    ``resend_without_ok=1``)."""

    corrupt: float = 0.0  # received lines with one byte changed (the newline too)
    garble: float = 0.0  # reply lines with one byte changed
    drop_ok: float = 0.0  # oks never sent
    duplicate_ok: float = 0.0  # oks sent twice
    spurious_resend: float = 0.0  # accepted lines answered "Resend: <that line>" and ok
    resend_without_ok: bool = False  # line errors end without their ok (some Marlin 2.0.x)
    flush_on_error: bool = True  # a line error empties the receive buffer (Marlin's)
    # A line numbered as the last one accepted, or the one before, gets no reply at all
    # (Marlin 2.1: a resent copy that was already in transit); off: refused as out of order.
    drop_duplicates: bool = True
    # OctoPrint's virtual printer: a bad checksum draws "Resend:" for a count of every
    # valid line received (resent ones included), and no error states "Last Line".
    counted_resend: bool = False
    # Lines dropped with only "Error: No Line Number with checksum, Last Line: <n>":
    # no resend request, no ok.
    drop_with_error: float = 0.0
    # Hyrel's link: M115s answered twice (the identity line said again at once), and G4
    # dwells followed by the identity unasked, quoted in an info line (">IN: FIRMWARE_...").
    identity_twice: float = 0.0
    unasked_identity: float = 0.0
    seed: int = 0

    @classmethod
    def parse(cls, text: str, base: Faults | None = None) -> Faults:
        """``corrupt=0.02 flush_on_error=0 ...`` over ``base``; ValueError on a bad name."""
        values: dict[str, object] = {}
        kinds = {f.name: f.type for f in fields(cls)}
        for item in text.split():
            name, _, raw = item.partition("=")
            if name not in kinds:
                raise ValueError(f"unknown fault '{name}' (known: {', '.join(kinds)})")
            kind = str(kinds[name])
            try:
                if "bool" in kind:
                    values[name] = raw.lower() in ("1", "true", "yes", "on", "")
                elif name == "seed":
                    values[name] = int(raw)
                else:
                    values[name] = float(raw)
            except ValueError:
                raise ValueError(f"{name}: '{raw}' is not a number") from None
        return replace(base or cls(), **values)  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class ControllerSettings:
    """The simulated controller and link. Times in seconds, sizes in bytes."""

    bandwidth: float | None = None  # bytes per second each way; None: unlimited
    latency: float = 0.0  # one-way delay of the link
    rx_buffer: int = 128  # receive buffer; a ring buffer of N bytes holds N - 1
    overflow: Overflow = Overflow.DROP
    slots: int = 4  # command slots (Marlin's BUFSIZE)
    planner: int = 16  # planner blocks
    move_time: float = 0.0  # how long one move takes to execute
    # Moves take the time the firmware's planner gives them (as repetrel_host.gcode.estimate
    # plans them), divided by this: at 100 an hour's print runs in 36 s. Dwells (G4) are
    # part of the plan and scaled too; heat waits keep heat_rate's time. None: move_time.
    time_scale: float | None = None
    # The planner's limits with time_scale, before the job's own M201-M205 lines change
    # them (as a firmware's configuration); None: Marlin's defaults.
    limits: Limits | None = None
    command_time: float = 0.0  # how long any other command takes
    banner: bool = True  # say "start" at boot
    advanced_ok: bool = False  # ADVANCED_OK: "ok N<last line> P<planner free> B<slots free>"
    # Degrees per second a heater moves toward its target (M109/M190 wait that long);
    # None: temperatures reach their targets at once.
    heat_rate: float | None = None
    # Seconds a heat wait holds once its heater is at the target (TEMP_RESIDENCY_TIME;
    # Marlin's default is 10). 0: it ends as the target is reached, and its reports say
    # no W: (as Marlin built with 0).
    residency: float = 0.0
    # "echo:busy: processing" this often while a command holds the queue (a move waiting
    # for the planner, G4, G28, M400...), not during heat waits (Marlin's
    # HOST_KEEPALIVE_FEATURE without BUSY_WHILE_HEATING); None: never.
    keepalive: float | None = KEEPALIVE_INTERVAL
    faults: Faults = field(default_factory=Faults)
    extruders: int = 1  # hotends T0..T<n-1> (Marlin's EXTRUDER_COUNT)
    extruder_count: bool = True  # M115 says EXTRUDER_COUNT (some firmwares do not)
    chamber: bool = False  # a heated chamber (M141, M191; C: in reports)
    # Marlin's EMERGENCY_PARSER: M108, M112 and M410 act as they arrive, ahead of the
    # queue (M108's line still runs in its turn, and draws its ok). Without it they run
    # in their turn, like any line: M108 cannot end the heat wait it queues behind.
    emergency_parser: bool = True
    # Marlin's AUTOREPORT_TEMP: M155 S<n> reports temperatures every n seconds. Without it
    # M115 says Cap:AUTOREPORT_TEMP:0 and M155 is an unknown command: a host must poll.
    autoreport: bool = True
    # The first M115 after a start (or a reset) takes this long to run, holding the queue
    # behind it: a controller slow to say who it is (busy at boot, a loaded host's fake).
    identify_time: float = 0.0

    def __post_init__(self) -> None:
        if self.time_scale is not None and not self.time_scale > 0:
            raise ValueError("time_scale must be above zero")
        if self.time_scale is not None and self.move_time:
            raise ValueError("time_scale and move_time each say how long a move takes: give one")
        if self.keepalive is not None and not self.keepalive > 0:
            raise ValueError("keepalive must be above zero (None: no busy lines)")


@dataclass(slots=True)
class FaultCounts:
    corrupted_lines: int = 0
    garbled_replies: int = 0
    dropped_oks: int = 0
    duplicated_oks: int = 0
    spurious_resends: int = 0
    flushed_bytes: int = 0
    dropped_with_error: int = 0


@dataclass(slots=True)
class LinkCounters:
    """What the link and the firmware saw, for benchmarks (times in the simulator's clock)."""

    bytes_received: int = 0  # bytes that reached the receive buffer (or were dropped there)
    bytes_dropped: int = 0  # lost to a full receive buffer
    peak_rx_buffer: int = 0  # most bytes waiting in the receive buffer at once
    peak_slots: int = 0  # most command slots in use at once
    commands: int = 0  # commands accepted into the command slots
    # Error lines the firmware wrote ("Error:...", Hyrel's ">ER:..."): on a healthy link a
    # host that draws none leaves this at 0.
    errors: int = 0
    first_command_at: float | None = None  # the host's greeting, M110
    first_job_command_at: float | None = None  # the first command that is not M110 or M115
    last_command_at: float | None = None
    # bytes_received when those two commands were accepted: the job's own bytes between.
    bytes_at_first_job_command: int = 0
    bytes_at_last_command: int = 0
    # Time with nothing to execute (slots, planner and the command in hand all done)
    # that ended because a new command arrived: the controller waited for the host.
    starved: float = 0.0
