"""``hyrel-send --server URL``: the print server from the command line (the standard
library's HTTP client: nothing more to install). Submits a job and follows it through
the server's event stream, lists a printer's queue, cancels a job; the same for a farm's
queue (``--farm``). A job's end is told in hyrel-send's exit codes."""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.error import HTTPError, URLError
from urllib.parse import quote, urlencode
from urllib.request import Request, urlopen

from repetrel_host.cli.exit_codes import (
    EXIT_CONTROLLER_ERROR,
    EXIT_INTERRUPTED,
    EXIT_NOT_SAFE,
    EXIT_OK,
)
from repetrel_host.cli.times import clock_at, duration
from repetrel_host.errors import JobError, LinkError, UsageError

API_KEY_ENV = "HYREL_API_KEY"
TIMEOUT = 30.0
# How a job's end maps to hyrel-send's exit codes.
ENDED = {
    "completed": EXIT_OK,
    "cancelled": EXIT_INTERRUPTED,
    "failed": EXIT_CONTROLLER_ERROR,
    "interrupted": EXIT_CONTROLLER_ERROR,
}


class ServerClient:
    """Requests to one print server; every failure is one sentence (a HostError)."""

    def __init__(self, url: str, api_key: str | None = None) -> None:
        if not url.startswith(("http://", "https://")):
            url = f"http://{url}"
        self.url = url.rstrip("/")
        self.api_key = api_key or os.environ.get(API_KEY_ENV)

    def request(
        self,
        method: str,
        path: str,
        body: bytes | Iterable[bytes] | None = None,
        content_type: str = "",
        length: int | None = None,
    ) -> Any:
        """One call and its JSON answer; ``body`` may come in pieces (``length``: their
        size in all, which a body in pieces must state)."""
        headers = {"Accept": "application/json"}
        if content_type:
            headers["Content-Type"] = content_type
        if length is not None:
            headers["Content-Length"] = str(length)
        if self.api_key:
            headers["X-Api-Key"] = self.api_key
        request = Request(f"{self.url}{path}", data=body, headers=headers, method=method)
        with self._reaching(), urlopen(request, timeout=TIMEOUT) as response:
            data = response.read()
        return json.loads(data) if data else None

    @contextmanager
    def _reaching(self) -> Iterator[None]:
        """A refusal or an unreachable server, as one sentence (a HostError)."""
        try:
            yield
        except HTTPError as exc:
            raise _refused(exc) from None
        except (URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise LinkError(f"cannot reach the print server at {self.url}: {reason}") from None

    def printer(self, name: str | None) -> str:
        """The printer named, or the server's first."""
        printers = [p["name"] for p in self.request("GET", "/v1/printers")]
        if name is None:
            return str(printers[0])
        if name not in printers:
            raise UsageError(f"the server has no printer '{name}' (it has {', '.join(printers)})")
        return name

    def submit(self, printer: str, path: Path) -> dict[str, Any]:
        job: dict[str, Any] = self.upload(f"/v1/printers/{quote(printer)}/jobs", path, [])
        return job

    def upload(self, where: str, path: Path, fields: list[tuple[str, str]]) -> Any:
        """POST ``path`` as the multipart field ``file`` with ``fields``, read from disk as
        it goes (a gigabyte's file is never held in memory)."""
        boundary = uuid.uuid4().hex
        head = "".join(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'
            for name, value in fields
        )
        head += (
            f'--{boundary}\r\nContent-Disposition: form-data; name="file"; '
            f'filename="{path.name}"\r\nContent-Type: application/octet-stream\r\n\r\n'
        )
        tail = f"\r\n--{boundary}--\r\n".encode()
        try:
            size = path.stat().st_size
            handle = path.open("rb")
        except OSError as exc:
            raise JobError(f"{path}: cannot be read ({exc.strerror})") from None

        def body() -> Iterator[bytes]:
            yield head.encode()
            while chunk := handle.read(1 << 20):
                yield chunk
            yield tail

        with handle:
            return self.request(
                "POST",
                where,
                body(),
                f"multipart/form-data; boundary={boundary}",
                len(head.encode()) + size + len(tail),
            )

    def events(self, printer: str | None, where: str = "/v1/events") -> Iterator[dict[str, Any]]:
        """The server's events for ``printer`` (or at ``where``: the farm's), as they come."""
        query = f"?{urlencode({'printer': printer})}" if printer is not None else ""
        headers = {"Accept": "text/event-stream"}
        if self.api_key:
            headers["X-Api-Key"] = self.api_key
        request = Request(f"{self.url}{where}{query}", headers=headers)
        with self._reaching():
            response = urlopen(request, timeout=None)
        with response:
            for raw in response:
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                if line.startswith("data: "):
                    yield json.loads(line[len("data: ") :])


def _refused(exc: HTTPError) -> Exception:
    try:
        detail = json.loads(exc.read()).get("detail", exc.reason)
    except (ValueError, AttributeError):
        detail = exc.reason
    if isinstance(detail, dict):  # a refused job: the lint's findings
        detail = "; ".join([str(detail.get("error")), *detail.get("findings", [])])
    message = f"the print server refused: {detail} (HTTP {exc.code})"
    if exc.code == 403:
        message += f": give --api-key KEY or set {API_KEY_ENV}"
    return JobError(message) if exc.code in (400, 404, 409, 413) else UsageError(message)


def follow(
    client: ServerClient,
    printer: str,
    path: Path,
    show: Callable[[str], None],
    progress: Callable[[int, int, int, str], None],
    release: bool = False,
) -> int:
    """Submit ``path`` and follow it to its end; returns hyrel-send's exit code.
    ``progress``: bytes done, the file's size, lines done, the time left and end (or
    "estimating"); ``release``: the bed is clear, a held queue may go on."""
    events = client.events(printer)  # subscribed before the job exists: nothing missed
    first = next(events)  # the printer as it stands
    job = client.submit(printer, path)
    job_id = job["id"]
    for finding in job.get("findings", []):
        show(finding)
    where = f"printer {printer} ({first.get('state')})"
    show(f"{path.name}: queued on {where} of {client.url} as job {job_id}")
    if release:
        client.request("POST", f"/v1/printers/{quote(printer)}/release")
    elif first.get("held"):
        show(
            f"the queue of printer {printer} is held (a job ended; its part may be on the bed): "
            "release it once the bed is clear (--release, or the status page's button)"
        )
    try:
        return _follow(events, job_id, path, show, progress, client.url)
    except KeyboardInterrupt:
        show(
            f"no longer following job {job_id}: it goes on on the server "
            f"(hyrel-send --server {client.url} --cancel {job_id} stops it)"
        )
        return EXIT_INTERRUPTED


def _follow(
    events: Iterator[dict[str, Any]],
    job_id: int,
    path: Path,
    show: Callable[[str], None],
    progress: Callable[[int, int, int, str], None],
    url: str,
) -> int:
    for event in events:
        kind = event["type"]
        if kind == "progress" and event["job"] == job_id:
            left = job_times(event) or "estimating"
            progress(event["bytes"], event["size"], event["lines"], left)
        elif kind == "message":
            show(f"controller: {event['text']}")
        elif kind == "job" and event["job"]["id"] == job_id:
            record = event["job"]
            state = record["state"]
            if state in ENDED:
                line = record["last_line"]
                summary = f"{path.name}: {state}: {record['lines']} lines (to line {line})"
                show(f"{summary}: {record['error']}" if record["error"] else summary)
                if record.get("safe_stop") == "owed":
                    show(
                        f"not safe: job {job_id}'s safe stop was not confirmed; the server "
                        "sends it as soon as the printer answers"
                    )
                    return EXIT_NOT_SAFE
                return ENDED[state]
            if state != "queued":  # said already
                show(f"{path.name}: {state}")
    raise LinkError(f"the print server at {url} closed its event stream")


def list_jobs(client: ServerClient, printer: str) -> list[str]:
    """The printer's queue and history, a line each, with its times (:func:`job_times`)."""
    running = client.request("GET", f"/v1/printers/{quote(printer)}").get("job") or {}
    lines = []
    for job in client.request("GET", f"/v1/printers/{quote(printer)}/jobs"):
        done = f"{job['lines']}/{job['total_lines']} lines"
        error = f"  {job['error']}" if job["error"] else ""
        times = job_times({**job, **running} if running.get("id") == job["id"] else job)
        lines.append(
            f"{job['id']:>5}  {job['state']:<11}  {done:<18}  {job['name']}{error}"
            + f"  ({times})" * bool(times)
        )
    return lines


def job_times(job: dict[str, Any]) -> str:
    """A job's times as a listing says them, from what the server gives: a queued one's
    estimate and when it should start and end, a running one's time left and end, an ended
    one's duration and end; "" where the server tells none."""
    if job.get("time_left") is not None:
        ends = clock_at(job.get("ends") or job.get("expected_end"))
        return f"{duration(job['time_left'])} left" + f", ends {ends}" * bool(ends)
    if job.get("expected_end") is not None:  # a farm's printing job: its node's end
        return f"ends {clock_at(job['expected_end'])}"
    if job.get("started") is not None and job.get("ended") is not None:
        return f"took {duration(job['ended'] - job['started'])}, ended {clock_at(job['ended'])}"
    said = []
    if job.get("estimated_time") is not None:
        said.append(f"about {duration(job['estimated_time'])}")
    start, end = clock_at(job.get("estimated_start")), clock_at(job.get("estimated_end"))
    if start is not None and end is not None:
        said.append(f"{start} to {end}")
    return ", ".join(said)


def cancel(client: ServerClient, job_id: int) -> dict[str, Any]:
    job: dict[str, Any] = client.request("DELETE", f"/v1/jobs/{job_id}")
    return job


# --- a farm (hyrel-server --farm) ----------------------------------------------------------


def farm_submit(
    client: ServerClient, path: Path, requires: list[str], priority: int, copies: int
) -> dict[str, Any]:
    fields = [("require", r) for r in requires]
    fields += [("priority", str(priority)), ("copies", str(copies))]
    answer: dict[str, Any] = client.upload("/v1/farm/jobs", path, fields)
    return answer


def farm_jobs(client: ServerClient) -> list[str]:
    """The farm's queue, then its jobs claimed or printing, then the last that ended."""
    lines = []
    for job in client.request("GET", "/v1/farm/jobs"):
        where = f"{job['printer']}@{job['node_name']}" if job["printer"] else "-"
        done = f"{job['lines']}/{job['total_lines']} lines"
        error = f"  {job['error']}" if job["error"] else ""
        times = job_times(job)
        lines.append(
            f"{job['id']:>5}  {job['state']:<11}  {where:<16}  {done:<18}  {job['name']}"
            f"  [{job['requires']}]{error}" + f"  ({times})" * bool(times)
        )
    return lines


def farm_recover(
    client: ServerClient, job_id: int, from_line: int | None, from_layer: int | None
) -> dict[str, Any]:
    """Queue the rest of farm job ``job_id`` for the printer that printed it."""
    where = {"from_line": from_line, "from_layer": from_layer}
    body = json.dumps({k: v for k, v in where.items() if v is not None}).encode()
    answer: dict[str, Any] = client.request(
        "POST", f"/v1/farm/jobs/{job_id}/resume", body, "application/json"
    )
    return answer


def farm_cancel(client: ServerClient, job_id: int) -> dict[str, Any]:
    answer: dict[str, Any] = client.request("DELETE", f"/v1/farm/jobs/{job_id}")
    return answer


def farm_follow(
    client: ServerClient,
    ids: list[int],
    events: Iterator[dict[str, Any]],
    show: Callable[[str], None],
) -> int:
    """Follow farm jobs to their ends through the farm's events (subscribed to before
    they were submitted: nothing is missed, and each change comes in the order it was
    made, with the job's new state), telling each change of state; hyrel-send's exit code
    (the worst of theirs). A job interrupted (its node lost) ends the following, saying
    why and how to go on with it."""
    shown: dict[int, str] = {}
    codes: dict[int, int] = {}
    hinted: set[int] = set()

    def told(job_id: int, state: str) -> None:
        job = client.request("GET", f"/v1/farm/jobs/{job_id}")  # who prints it, how far
        if shown.get(job_id) != state:
            shown[job_id] = state
            where = f" on {job['printer']} at node {job['node_name']}" * bool(
                job["printer"] and state != "queued"
            )
            show(f"farm job {job_id} ({job['name']}): {state}{where}")
        if state in ENDED:
            line = f"farm job {job_id}: {job['lines']} lines (to line {job['last_line']})"
            if state == "interrupted":  # its node stopped, or stopped answering: say why
                show(f"farm job {job_id} was interrupted: {job['error'] or 'its node stopped'}")
                show(line)
            else:
                show(f"{line}: {job['error']}" if job["error"] else line)
            if job["resume_command"]:
                show(f"farm job {job_id}: to go on with it: {job['resume_command']}")
            codes[job_id] = ENDED[state]
            if job.get("safe_stop") == "owed":
                show(
                    f"not safe: farm job {job_id}'s safe stop was not confirmed; its node "
                    "sends it as soon as the printer answers"
                )
                codes[job_id] = EXIT_NOT_SAFE
        elif state == "queued" and job_id not in hinted:
            hint = _waiting_hint(client, job_id)  # its printers all held or offline
            if hint:
                hinted.add(job_id)
                show(hint)

    try:
        for event in events:
            if event.get("kind") != "job":
                continue
            state = event.get("state") or ("queued" if event.get("queued") else None)
            for job_id in event.get("jobs", [event.get("job")]):
                if job_id in ids and job_id not in codes and state is not None:
                    told(job_id, state)
            if len(codes) == len(ids):
                break
            if codes:  # one ended: a copy still queued may now wait for a held printer
                for job_id in ids:
                    if shown.get(job_id) == "queued" and job_id not in hinted:
                        told(job_id, "queued")
        else:
            raise LinkError(f"the print server at {client.url} closed the farm's event stream")
    except KeyboardInterrupt:
        show(
            "no longer following: the jobs go on in the farm "
            f"(hyrel-send --server {client.url} --farm --cancel ID stops one)"
        )
        return EXIT_INTERRUPTED
    return max(codes.values(), default=EXIT_OK)


def _waiting_hint(client: ServerClient, job_id: int) -> str:
    """Why a queued farm job cannot start now, when no printer that can take it is free:
    the ones that can are held (a part on the bed) or offline; "" when one is free or busy."""
    from repetrel_host.server.farm.needs import missing

    farm = client.request("GET", "/v1/farm")
    job = next((j for j in farm["jobs"] if j["id"] == job_id), None)
    if job is None or job["state"] != "queued":
        return ""
    able = [
        p
        for p in farm["printers"]
        if not missing(p["capabilities"], job["needs"])
        and f"{p['node']}/{p['name']}" not in job["given_back"]
    ]
    if any(p["state"] != "offline" and not (p["held"] and p["state"] == "ready") for p in able):
        return ""  # one is free, or busy printing: the job waits its turn
    held = [p for p in able if p["held"] and p["state"] == "ready"]
    if held:
        first = held[0]
        node_url = first["url"].rsplit("/printers/", 1)[0]
        names = ", ".join(f"{p['name']} at {p['node_name']}" for p in held)
        return (
            f"farm job {job_id} waits: the printers that can print it are held, a part on the "
            f"bed ({names}); once a bed is clear, release it (hyrel-send --server {node_url} "
            f"--printer {first['name']} --release, or its page)"
        )
    return f"farm job {job_id} waits: no printer that can print it is online"
