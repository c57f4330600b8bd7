"""A job's host codes on the print server: the snapshots of a printer's camera (M791, and
M790 at each new layer), and M792's actions, told rather than done (the server speaks,
shows and runs nothing: SHELL stays refused)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

from repetrel_host.server.events import PrinterMessage, ServerEvent, SnapshotTaken
from repetrel_host.server.printers.config import PrinterConfig
from repetrel_host.server.printers.running import Running
from repetrel_host.session.camera import Camera
from repetrel_host.session.job import ActionKind, HostAction

log = logging.getLogger("repetrel_host.server")


def snapshot_name(tail: str) -> str:
    """A snapshot's name without its suffix: the time first, so that names sort by it."""
    return f"{datetime.now():%Y%m%d-%H%M%S-%f}{tail}"


class HostActions:
    """One printer's camera, and what its jobs' host codes do: told as the server's events."""

    def __init__(
        self,
        name: str,
        config: PrinterConfig,
        data_dir: Path,
        publish: Callable[[ServerEvent], None],
    ) -> None:
        self.name = name
        self.config = config
        self.publish = publish  # the server's events
        self.camera: Camera | None = None
        if config.camera is not None:
            self.camera = Camera(
                config.camera,
                data_dir / "snapshots" / name,
                config.snapshots_kept,
                on_taken=self._snapshot_taken,
                on_failed=lambda why: self.tell(f"no snapshot: {why}"),
            )

    async def perform(self, action: HostAction, running: Running | None) -> bool:
        """A job's host codes on the server (``running``: the job that sent them):
        snapshots; M792's actions are told, not done (the server speaks, shows and runs
        nothing: SHELL stays refused)."""
        if action.kind is ActionKind.LAYER and running is not None:
            running.new_layers += 1
        if action.kind is ActionKind.SNAPSHOT or (
            action.kind is ActionKind.LAYER and self.config.layer_snapshots
        ):
            self._snap(action, running)
        elif action.kind in (ActionKind.ACTIONS, ActionKind.PAUSE):
            for verb, argument in action.actions:
                why = "the server runs no programs" if verb == "SHELL" else "not done on the server"
                self.tell(f"{action.position}: {verb} {argument} ({why})")
        return True

    def _snap(self, action: HostAction, running: Running | None) -> None:
        if self.camera is None:
            if action.kind is ActionKind.SNAPSHOT:
                self.tell(f"{action.position}: M791, but printer {self.name} has no camera set")
            return
        tail = ""
        if running is not None:
            layer = action.kind is ActionKind.LAYER
            where = f"layer{running.new_layers}" if layer else f"line{action.source_line}"
            tail = f"-job{running.record.id}-{where}"
        if not self.camera.take(snapshot_name(tail), wait_turn=action.kind is ActionKind.SNAPSHOT):
            log.info(
                "printer %s: %s: the last snapshot is still being taken", self.name, action.position
            )

    def _snapshot_taken(self, path: Path) -> None:
        log.info("printer %s: snapshot %s", self.name, path.name)
        self.publish(SnapshotTaken(self.name, path.name, self.url(path)))

    def url(self, snapshot: Path) -> str:
        """Where the API serves ``snapshot``."""
        return f"/v1/printers/{self.name}/snapshots/{snapshot.name}"

    def tell(self, text: str) -> None:
        """A message about the printer: logged, and told as the server's event."""
        log.info("printer %s: %s", self.name, text)
        self.publish(PrinterMessage(self.name, text))
