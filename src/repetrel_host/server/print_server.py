"""The print server itself: its printers, their store, the data folder and who may use it,
put together, and started and stopped with the app; every face of its API (native,
OctoPrint's, a farm's) finds it in a request with :func:`server_of`."""

from __future__ import annotations

import asyncio
import json
import logging
import uuid
from collections.abc import Awaitable, Sequence
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from fastapi import HTTPException, Request

from repetrel_host.config import UserConfig
from repetrel_host.server.access import Access
from repetrel_host.server.analyses import Analyses
from repetrel_host.server.events import EventHub, FileChanged, JobChanged
from repetrel_host.server.printers.config import PrinterConfig
from repetrel_host.server.printers.service import SAFE_STOP_TIMEOUT, PrinterService, Refused
from repetrel_host.server.store import Store

if TYPE_CHECKING:
    from repetrel_host.server.farm.node import FarmNode, FarmSettings


log = logging.getLogger("repetrel_host.server")

T = TypeVar("T")


class PrintServer:
    """The printers, their store and the data folder; started and stopped with the app."""

    def __init__(
        self,
        data_dir: Path,
        printers: dict[str, PrinterConfig],
        api_key: str,
        max_upload: int,
        user: UserConfig | None = None,
        automatic_transition: bool = False,
        start_waits_for_release: bool = False,
        public_read: bool = False,
        trusted: Sequence[IPv4Network | IPv6Network] = (),
        presets: dict[str, dict[str, float | None]] | None = None,
        farm: FarmSettings | None = None,
        stop_timeout: float = SAFE_STOP_TIMEOUT,
    ) -> None:
        self.data_dir = data_dir
        self.files = data_dir / "files"
        self.files.mkdir(parents=True, exist_ok=True)
        self.access = Access(data_dir, api_key, public_read, trusted)
        self.max_upload = max_upload
        self.presets = presets or {}  # material: {"head", "bed", "chamber"} temperatures
        self.user = user or UserConfig()
        self.store = Store(data_dir / "jobs.sqlite")
        self.events = EventHub()
        self._uuids: dict[str, str] | None = None  # printer_uuid's, once read
        # Each file's analysis, kept in the data folder (made at its upload).
        self.analyses = Analyses(data_dir / "analysis", data_dir, self._analysed)
        self.services = {
            name: PrinterService(
                name, config, self.store, data_dir, self.user, self.events.publish, self.analyses
            )
            for name, config in printers.items()
        }
        first = next(iter(self.services.values()), None)
        if first is not None:  # files are planned as the first printer plans its jobs
            self.analyses.plan_as = lambda path: first.checks.plan(path).plan_settings
            self.analyses.plan_key = first.plan_key
        for service in self.services.values():
            service.automatic_transition = automatic_transition
            service.start_waits_for_release = start_waits_for_release
            service.stop_timeout = stop_timeout
        # The printers whose safe stop a stop left owed (the exit code says so).
        self.left_owing: list[str] = []
        self.default = next(iter(self.services))
        # In a farm, the printers' jobs come from its shared queue too (farm/node.py).
        self.farm: FarmNode | None = None
        if farm is not None:
            from repetrel_host.server.farm.node import FarmNode

            self.farm = FarmNode(farm, data_dir, self.store, self.services, self.analyses)
        for record in self.store.interrupt_active():
            log.warning(
                "job %d (%s) on printer %s was interrupted: acknowledged through at least "
                "line %d; its safe stop goes first",
                record.id,
                record.name,
                record.printer,
                record.last_line,
            )
            # Nothing starts by itself after it: its part may be on the bed.
            if record.printer in self.services:
                self.services[record.printer].hold(
                    f"job {record.id} was interrupted: its part may be on the bed"
                )
        for service in self.services.values():
            owing = self.store.owing(service.name)
            if owing:  # interrupted, or ended without its safe stop confirmed (connect sends it)
                log.warning(
                    "printer %s: the safe stop of job %s is owed: it goes as soon as the "
                    "printer answers",
                    service.name,
                    ", ".join(map(str, owing)),
                )
            if service.hold_reason is not None:  # kept from before the restart
                log.warning(
                    "printer %s: the queue is held (%s): POST /v1/printers/%s/release%s "
                    "releases it",
                    service.name,
                    service.hold_reason,
                    service.name,
                    "" if start_waits_for_release else ", or a print started from a client,",
                )

    async def start(self) -> None:
        for service in self.services.values():
            service.start()
        if self.farm is not None:
            await self.farm.start()

    async def stop(self) -> None:
        """Every printer stopped (a running job with its safe stop), then the farm's part;
        the store stays open for what reports their ends (:meth:`close` after)."""
        await asyncio.gather(*(service.stop() for service in self.services.values()))
        self.left_owing = [name for name in self.services if self.store.owing(name)]
        if self.farm is not None:  # after the printers: their jobs' ends are reported
            await self.farm.stop()

    def _analysed(self, path: Path) -> None:
        """A file's analysis was made in the background (its thread): the faces are told, so
        that a list shows its print time (OctoPrint's MetadataAnalysisFinished), and a
        queue listing the estimate of each queued job that prints it."""
        if path.is_relative_to(self.files):
            where = path.relative_to(self.files).as_posix()
            self.events.publish_from_thread(
                FileChanged("analysed", where, path.name, False, "analyse")
            )
        for name in self.services:
            for record in self.store.queued(name):
                if self.data_dir / record.file == path:
                    self.events.publish_from_thread(JobChanged(name, record))

    def close(self) -> None:
        self.store.close()

    def printer_uuid(self, name: str) -> str:
        """A printer's UUID, the same across restarts (OctoPrint's discovery ``upnpUuid``,
        which Home Assistant takes for the printer's identity)."""
        path = self.data_dir / "uuids.json"
        if self._uuids is None:  # read once: clients ask for the settings often
            self._uuids = json.loads(path.read_text()) if path.exists() else {}
        known = self._uuids
        if name not in known:
            known[name] = str(uuid.uuid4())
            partial = path.with_suffix(".part")
            partial.write_text(json.dumps(known, indent=1))
            partial.replace(path)
        return known[name]

    def file_pace(self) -> float:
        """The pace a file's time is listed at: the first printer's, whose plan the files'
        analyses are (:attr:`Analyses.plan_as`); 1 without printers."""
        first = next(iter(self.services.values()), None)
        return first.pace() if first is not None else 1.0

    def service(self, name: str | None) -> PrinterService:
        service = self.services.get(name or self.default)
        if service is None:
            raise HTTPException(404, f"no printer '{name}' (printers: {', '.join(self.services)})")
        return service


def server_of(request: Request) -> PrintServer:
    server: PrintServer = request.app.state.server
    return server


async def answered(call: Awaitable[T]) -> T:
    """What the printer's ``call`` gives; its :class:`Refused` as an HTTP error."""
    try:
        return await call
    except Refused as exc:
        raise HTTPException(exc.status, str(exc)) from None
