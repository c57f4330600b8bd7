"""``hyrel-send --server URL`` (and ``--farm``): the job goes to a print server
(hyrel-server) or its farm instead of a port, and is followed there; ``--list``,
``--cancel``, ``--release`` and ``--resume`` act on the server's queue. The HTTP calls are
:mod:`.server_client`'s; this module says what they answered."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from repetrel_host.cli.exit_codes import EXIT_OK
from repetrel_host.cli.out import Out
from repetrel_host.errors import UsageError


@dataclass(frozen=True)
class ServerRequest:
    """What hyrel-send --server was asked to do."""

    printer: str | None
    api_key: str | None
    job: Path | None
    list_jobs: bool
    cancel: int | None
    release: bool


@dataclass(frozen=True)
class FarmRequest:
    """What hyrel-send --server URL --farm asks of the farm's job."""

    requires: list[str]
    priority: int
    copies: int
    recover: int | None = None  # a farm job to go on with, on the printer that printed it
    from_line: int | None = None
    from_layer: int | None = None


def run_with_farm(console: Out, url: str, request: ServerRequest, farm: FarmRequest) -> int:
    """hyrel-send --server URL --farm: submit to the farm and follow, list, cancel."""
    from repetrel_host.cli import server_client as client

    server = client.ServerClient(url, request.api_key)

    def show(text: str) -> None:
        console.print(text, markup=False)

    if request.cancel is not None:
        answer = client.farm_cancel(server, request.cancel)
        how = "cancelling (its node stops it, the safe stop first)" * bool(answer.get("cancelling"))
        show(f"farm job {request.cancel}: {how or answer['state']}")
        return EXIT_OK
    if request.list_jobs:
        for line in client.farm_jobs(server):
            show(line)
        if request.job is None:
            return EXIT_OK
    events = server.events(None, "/v1/farm/events")
    if farm.recover is not None:
        if request.job is not None:
            raise UsageError("--resume ID goes on with the farm's own file: give no JOB")
        next(events)  # subscribed before the job exists: nothing is missed
        answer = client.farm_recover(server, farm.recover, farm.from_line, farm.from_layer)
        (made,) = answer["jobs"]
        show(
            f"farm job {farm.recover}: the rest, from line {answer['from_line']}, queued as "
            f"farm job {made} for the printer that printed it"
        )
        return client.farm_follow(server, [made], events, show)
    if request.job is None:
        raise UsageError("give the JOB to send to the farm (or --list, --cancel ID, --resume ID)")
    next(events)  # subscribed before the job exists: nothing is missed
    queued = client.farm_submit(server, request.job, farm.requires, farm.priority, farm.copies)
    for finding in queued["findings"]:
        show(finding)
    ids = ", ".join(map(str, queued["jobs"]))
    show(
        f"{queued['name']}: queued in the farm as job {ids} ({queued['requires']}); "
        f"printers that can take it: {', '.join(queued['eligible'])}"
    )
    return client.farm_follow(server, queued["jobs"], events, show)


def run_with_server(console: Out, url: str, request: ServerRequest) -> int:
    """hyrel-send --server: submit and follow a job, list jobs, cancel one, release."""
    from repetrel_host.cli import server_client as client

    server = client.ServerClient(url, request.api_key)
    if request.cancel is not None:
        ended = client.cancel(server, request.cancel)
        stopping = f" (stopping: {ended['stopping']})" if ended.get("stopping") else ""
        console.print(
            f"job {request.cancel} ({ended['name']}): {ended['state']}{stopping}", markup=False
        )
        return EXIT_OK
    name = server.printer(request.printer)
    job = request.job
    if job is None and request.release:
        server.request("POST", f"/v1/printers/{name}/release")
        console.print(f"printer {name}: the queue goes on", markup=False)
    if request.list_jobs:
        for line in client.list_jobs(server, name):
            console.print(line, markup=False)
    if job is None:
        if request.list_jobs or request.release:
            return EXIT_OK
        raise UsageError("give the JOB to send to the server (or --list, --cancel ID, --release)")
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn

    progress = Progress(
        TextColumn(f"[bold]{escape(job.name)}"),
        BarColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[lines]} lines"),
        TextColumn("[progress.remaining]{task.fields[left]}"),
        console=console.console,
    )
    task = progress.add_task(job.name, total=1, lines=0, left="")

    def update(done: int, size: int, lines: int, left: str) -> None:
        progress.start()
        progress.update(task, completed=done, total=max(size, 1), lines=lines, left=left)

    def show(text: str) -> None:
        console.print(text, markup=False)

    try:
        return client.follow(server, name, job, show, update, request.release)
    finally:
        progress.stop()
