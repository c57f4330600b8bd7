"""One printer's settings on the print server: its port, and what ``hyrel-send`` would
take for it (machine, loadout, flow, protocol, camera...); and how they open its session."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import repetrel_host as rh
from repetrel_host.config import UserConfig
from repetrel_host.gcode.heaters import Heater
from repetrel_host.session.events import PrinterEvent
from repetrel_host.session.planning import (
    JobRequest,
    LinkRequest,
    explicit_machine,
    link_settings,
)

POLL_INTERVAL = 2.0  # temperatures, for the API and the page


@dataclass(frozen=True)
class PrinterConfig:
    """One printer of the server: its port, and what ``hyrel-send`` would take for it."""

    port: str
    machine: str | None = None
    loadout: str | None = None
    flow: str | None = None  # buffered, unbuffered
    rx_buffer: int | None = None
    max_lines: int | None = None
    baud: int | None = None
    protocol: str | None = None  # reprap, hyrel (None: the machine's, else reprap)
    report: bool = False  # every job asks for the controller's M773 report (M772 S1)
    camera: str | None = None  # a command line for M791/M790 snapshots ({path}: the image)
    layer_snapshots: bool = True  # with a camera: a snapshot at every M790
    snapshots_kept: int = 500
    tags: tuple[str, ...] = ()  # in a farm: what jobs may ask of it (tag=abs)
    moonraker_port: int | None = None  # its own port for Moonraker's clients

    def connect(
        self,
        user: UserConfig,
        on_event: Callable[[PrinterEvent], None] | None = None,
        owe_safe_stop: list[Heater] | None = None,
    ) -> Any:
        """``rh.connect(...)`` for this printer (``on_event``: its events as they come;
        ``owe_safe_stop``: the heaters of a safe stop owed from before a restart)."""
        flow: rh.FlowControl | str | None = self.flow
        if self.rx_buffer is not None or self.max_lines is not None:
            # What is not given is the machine's, else the protocol's window (as hyrel-send).
            loadout = Path(self.loadout) if self.loadout is not None else None
            machine = explicit_machine(JobRequest(loadout, self.machine), user)
            link = LinkRequest(
                flow=rh.FlowMode(self.flow) if self.flow is not None else None,
                rx_buffer=self.rx_buffer,
                max_lines=self.max_lines,
                protocol=self.protocol,
            )
            flow = link_settings(link, machine).flow
        return rh.connect(
            self.port,
            machine=self.machine,
            loadout=self.loadout,
            flow=flow,
            config=user,
            baud=self.baud,
            poll_interval=POLL_INTERVAL,
            # During a job too: the API, the socket and the page show the heat-up as it goes
            # (where the firmware does not report temperatures itself).
            poll_while_printing=True,
            protocol=self.protocol,
            on_event=on_event,
            owe_safe_stop=owe_safe_stop,
        )
