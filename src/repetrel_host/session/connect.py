"""``connect``: the way into a printer session. It resolves what the caller chose (port,
machine, loadout, flow control, protocol) against the configuration, makes the link, and
hands back a READY :class:`~repetrel_host.session.printer.Printer` (awaited), or one closed
at the end of an ``async with``.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine, Generator, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from repetrel_host.config import UserConfig, load_user_config
from repetrel_host.gcode.heaters import Heater
from repetrel_host.links import make_link
from repetrel_host.protocol.dialects.reprap import DEFAULT_REPLY_TIMEOUT
from repetrel_host.protocol.flow import FlowControl, FlowMode
from repetrel_host.session.events import PrinterEvent
from repetrel_host.session.planning import (
    JobRequest,
    LinkRequest,
    explicit_machine,
    link_settings,
    resolve_port,
)
from repetrel_host.session.printer import Printer, open_printer
from repetrel_host.session.settings import POLL_INTERVAL, RECONNECT_WAIT, SessionSettings

if TYPE_CHECKING:
    from repetrel_host.fakes.settings import ControllerSettings


class _Connect:
    """``connect(...)``: awaited, a READY printer; with ``async with``, closed at the end."""

    def __init__(self, opening: Callable[[], Coroutine[Any, Any, Printer]]) -> None:
        self._opening = opening
        self._printer: Printer | None = None

    def __await__(self) -> Generator[Any, None, Printer]:
        return self._opening().__await__()

    async def __aenter__(self) -> Printer:
        self._printer = await self._opening()
        return self._printer

    async def __aexit__(self, *exc: object) -> None:
        if self._printer is not None:
            await self._printer.close()


def connect(
    port: str | None = None,
    machine: str | None = None,
    loadout: Path | str | None = None,
    flow: FlowControl | FlowMode | str | None = None,
    config: Path | UserConfig | None = None,
    *,
    baud: int | None = None,
    reply_timeout: float = DEFAULT_REPLY_TIMEOUT,
    reconnect: bool = True,
    reconnect_wait: float = RECONNECT_WAIT,
    poll_interval: float | None = POLL_INTERVAL,
    poll_while_printing: bool = False,
    protocol: str | None = None,
    checksum: bool | None = None,
    fake_log: Path | None = None,
    fake_args: Iterable[str] = (),
    sim: ControllerSettings | None = None,
    line_tap: Callable[[str, bool], None] | None = None,
    on_event: Callable[[PrinterEvent], None] | None = None,
    owe_safe_stop: Iterable[Heater] | None = None,
) -> _Connect:
    """Open a printer session on ``port`` and greet the controller.

    ``port``: a device path, a pyserial URL (``socket://``, ``rfc2217://``), ``auto``
    (the only serial port that looks like a printer board, else a LinkError naming
    them), ``fake`` (the built-in fake on a fresh pty, started and stopped with the
    session) or ``sim`` (the simulator in this process); None: ``$HYREL_PORT``, then the
    configuration's ``[printer] port``, else the fake. ``machine`` and ``loadout``
    choose the profile (else the firmware's M115 answer does), ``flow`` the flow
    control (else the profile's), ``protocol`` the line protocol: ``reprap`` or
    ``hyrel`` (Hyrel's own link; else the profile's, else ``reprap``; the fake and the
    simulator speak it too); ``checksum``: Hyrel's link sends the additive checksum on
    every line (else as the profile says; without it). ``poll_interval``: seconds between
    temperature polls while idle (``poll_while_printing``: while a job prints too), None
    for silence. ``reconnect=False``: a lost port stays
    lost. ``reconnect_wait``: a job whose link failed before its safe stop was confirmed
    ends once the safe stop went after a reconnect, or after this many seconds.
    ``line_tap``: :meth:`Printer.tap_lines` from the greeting's first line on.
    ``on_event``: called at once with each of the session's events (what
    :meth:`Printer.events` yields) from the port's opening on, for the session's life:
    before ``connect()`` returns, an :class:`~repetrel_host.session.events.NoAnswerYet` for each
    greeting that goes again unanswered. It runs on the session's path: it must only take
    note (print a line, set a flag), never block. ``owe_safe_stop``: a safe stop is owed
    from before (a server's restart after its job was cut), for these heaters besides
    those the profile names: it goes first, made whole, once the controller answers
    (:attr:`Printer.owed_safe_stop`).
    """

    async def opening() -> Printer:
        user = config if isinstance(config, UserConfig) else load_user_config(config)
        request = JobRequest(Path(loadout) if loadout is not None else None, machine)
        mode = FlowMode(flow) if isinstance(flow, str) else flow
        link = LinkRequest(
            baud=baud, flow=mode if isinstance(mode, FlowMode) else None, protocol=protocol
        )
        chosen = link_settings(link, explicit_machine(request, user))
        flow_control = flow if isinstance(flow, FlowControl) else chosen.flow
        name = resolve_port(port, user)
        opened = make_link(
            name,
            chosen.baud,
            fake_log=fake_log,
            fake_args=tuple(fake_args),
            sim=sim,
            protocol=chosen.protocol,
        )
        settings = SessionSettings(
            name,
            chosen.baud,
            flow_control,
            reply_timeout,
            reconnect,
            poll_interval,
            chosen.protocol,
            user,
            request,
            chosen.checksum if checksum is None else checksum,
            poll_while_printing,
            reconnect_wait,
        )
        return await open_printer(
            opened, settings, line_tap=line_tap, on_event=on_event, owe_safe_stop=owe_safe_stop
        )

    return _Connect(opening)
