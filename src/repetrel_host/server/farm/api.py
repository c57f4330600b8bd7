"""The farm's API on every node: ``/v1/farm`` (nodes, printers, jobs), ``/v1/farm/jobs``
(submit with requirements, list, cancel), ``/v1/farm/events``, and OctoPrint's upload at
``/farm/api/files/local`` so that a slicer's "Upload and Print" feeds the farm."""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import secrets
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

import psycopg
from fastapi import APIRouter, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import StreamingResponse
from psycopg_pool import PoolTimeout
from pydantic import BaseModel, Field

import repetrel_host as rh
from repetrel_host.config import UserConfig
from repetrel_host.gcode.lint import Severity
from repetrel_host.server.auth import user_of
from repetrel_host.server.farm import estimates, needs, states
from repetrel_host.server.farm.node import FILE_TIMEOUT, TIMEOUT, FarmNode
from repetrel_host.server.print_server import PrintServer, server_of
from repetrel_host.server.uploads import receive, safe_file_name
from repetrel_host.session.job import Job, JobLine
from repetrel_host.session.planning import JobRequest, layer_line, plan_job
from repetrel_host.session.workers import in_worker

log = logging.getLogger("repetrel_host.server.farm")

KEEPALIVE = 15.0
MAX_COPIES = 100


class Recovery(BaseModel):
    """Where a recovered farm job starts (neither: its first line not acknowledged)."""

    from_line: int | None = Field(default=None, ge=1)
    from_layer: int | None = Field(default=None, ge=1)


def farm_of(request: Request) -> FarmNode:
    farm = server_of(request).farm
    if farm is None:
        raise HTTPException(
            404, "this server is not in a farm (start it with --farm postgresql://USER@HOST/DB)"
        )
    return farm


async def _asked(call: Any, timeout: float = TIMEOUT) -> Any:
    """A database call for a request: 503 with a sentence while the database is away
    (the call's own refusals, a LookupError or a ValueError, pass)."""
    try:
        return await asyncio.wait_for(call, timeout + 1)
    except (psycopg.Error, PoolTimeout, ConnectionError, TimeoutError) as exc:
        raise HTTPException(
            503, f"the farm's database does not answer ({type(exc).__name__}): try again"
        ) from None


def job_json(
    job: dict[str, Any], nodes: dict[str, dict[str, Any]], here: str, paces: estimates.Paces
) -> dict[str, Any]:
    """A farm job as the API shows it (``here``: this node's URL, for its recovery command;
    ``paces``: the farm's printers', for its estimate)."""
    node = nodes.get(job["node"] or "")
    # A resumed job is not offered again: its rest is queued (or printed) as resumed_by.
    recoverable = job["state"] in states.RESUMABLE and job["last_line"] > 0
    shown = {key: value for key, value in job.items() if key not in ("fence", "refused")}
    return {
        **shown,
        **_times(job, paces),
        "requires": needs.describe(job["needs"]),
        "node_name": node["name"] if node else None,
        "node_url": node["url"] if node else None,
        "given_back": job["refused"],
        "fence": job["fence"],
        # Where it would go on from, on the printer that printed it (the part is on its
        # bed): the farm's command, and the node's own account (/v1/jobs/LOCAL/resume).
        "resume_from_line": job["last_line"] + 1 if recoverable else None,
        "resume_command": f"hyrel-send --server {here} --farm --resume {job['id']}"
        if recoverable
        else None,
        "resume_url": f"{node['url']}/v1/jobs/{job['local_id']}/resume"
        if node and job["local_id"] and recoverable
        else None,
    }


def _times(job: dict[str, Any], paces: estimates.Paces) -> dict[str, Any]:
    """A job's estimate at the pace of the printer that prints it (the database keeps the
    plan's own seconds), and a printing job's time left as its node last reported it."""
    pace, pace_from = paces.of(job)
    planned = job["estimated_time"]
    heating = min(job.get("estimated_heating") or 0.0, planned or 0.0)  # not at the pace
    end = job["expected_end"]
    return {
        "estimated_time": (planned - heating) * pace + heating if planned is not None else None,
        "estimated_pace": round(pace, 4),
        "estimated_pace_from": pace_from,
        "planned_time": planned,
        "time_left": round(max(0.0, end - time.time())) if end is not None else None,
    }


async def farm_json(farm: FarmNode) -> dict[str, Any]:
    nodes = await _asked(farm.db.nodes(TIMEOUT))
    printers = await _asked(farm.db.printers(TIMEOUT))
    jobs = await _asked(farm.db.jobs(TIMEOUT))
    counts = await _asked(farm.db.counts(TIMEOUT))
    by_id = {node["id"]: node for node in nodes}
    by_job = {job["id"]: job for job in jobs}
    paces = estimates.Paces(printers)
    return {
        "node": {"id": farm.id, "name": farm.settings.name, "ready": farm.ready},
        "nodes": nodes,
        "printers": [
            {
                "node": printer["node"],
                "node_name": printer["node_name"],
                "url": f"{printer['url']}/printers/{printer['name']}",
                "name": printer["name"],
                # A lost node's printers are offline to the farm, whatever they last said.
                "state": "offline" if printer["lost"] else printer["state"],
                "held": printer["held"],
                "job": printer["job"],
                "free_at": free_at(printer, by_job.get(printer["job"])),
                "pace": printer["pace"],
                "capabilities": printer["caps"],
            }
            for printer in printers
        ],
        # Queued and streaming jobs, then the last 200 that ended; the counts are of all.
        "jobs": [job_json(job, by_id, farm.settings.node_url, paces) for job in jobs],
        "counts": counts,
    }


def free_at(printer: dict[str, Any], job: dict[str, Any] | None) -> float | None:
    """When a printing printer should be free (its job's expected end, a timestamp); None
    for any other (a paused one waits for a person) or while its job's end is unknown."""
    if printer["lost"] or printer["state"] != "printing" or job is None:
        return None
    return job["expected_end"] if job["state"] == "printing" else None


def rest_lines(path: Path, line: int) -> int:
    """The lines a job from ``line`` of ``path`` sends (in a thread: it reads the file)."""
    return sum(isinstance(item, JobLine) for item in Job(path).items(start=line))


def _plan_elsewhere(path: Path, printer: dict[str, Any], user: UserConfig) -> Any:
    """The plan another node's printer would make of ``path`` (its machine and loadout as
    registered); None when this node cannot rebuild it (a head type it does not know)."""
    loadout_text = printer["loadout"]
    with tempfile.TemporaryDirectory() as folder:
        loadout = None
        if loadout_text:
            loadout = Path(folder) / "loadout.toml"
            loadout.write_text(loadout_text)
        try:
            plan = plan_job(path, JobRequest(loadout, printer["caps"].get("machine")), user)
            return plan, *in_worker(plan.check_and_count)
        except rh.HostError:
            return None


def eligibility(
    server: PrintServer, farm: FarmNode, path: Path, name: str, wanted: dict[str, Any],
    printers: list[dict[str, Any]],
) -> tuple[list[str], dict[str, str], list[str], int]:  # fmt: skip
    """Which registered printers can print ``path`` (their needs met and the lint without
    errors), why each other cannot, the warnings, and the lines to send (in a thread)."""
    eligible: list[str] = []
    why_not: dict[str, str] = {}
    warnings: list[str] = []
    commands = 0
    # One pass of the lint for each machine and loadout: a farm of alike printers reads a
    # big file once, not once a printer.
    linted: dict[tuple[str | None, str | None], Any] = {}

    def lint(printer: dict[str, Any]) -> Any:
        try:
            if printer["node"] == farm.id and printer["name"] in server.services:
                return server.services[printer["name"]].check(path)
            return _plan_elsewhere(path, printer, server.user)
        except rh.HostError as exc:
            return str(exc).replace(str(path), name)

    for printer in printers:
        key = f"{printer['name']} on {printer['node_name']}"
        lacks = needs.missing(printer["caps"], wanted)
        if lacks:
            why_not[key] = ", ".join(lacks)
            continue
        alike = (printer["caps"].get("machine"), printer["loadout"])
        if alike not in linted:
            linted[alike] = lint(printer)
        checked = linted[alike]
        if isinstance(checked, str):  # the plan itself failed: its sentence
            why_not[key] = checked
            continue
        if checked is None:
            eligible.append(key)  # checked again by the node that claims it
            continue
        _, findings, lines = checked
        errors = [f.format(name) for f in findings if f.severity is Severity.ERROR]
        if errors:
            why_not[key] = "; ".join(errors[:2])
            continue
        eligible.append(key)
        warnings += [f.format(name) for f in findings if f.severity is not Severity.ERROR]
        commands = lines
    return eligible, why_not, sorted(set(warnings)), commands


async def submit(
    request: Request,
    upload: UploadFile,
    requirements: list[str],
    priority: int,
    copies: int,
) -> dict[str, Any]:
    """Check an upload against the farm's printers, store it in the database, queue it."""
    server = server_of(request)
    farm = farm_of(request)
    name, _ = safe_file_name(upload.filename or "")
    if not 1 <= copies <= MAX_COPIES:
        raise HTTPException(400, f"copies: from 1 to {MAX_COPIES}")
    try:
        wanted = needs.parse(requirements)
    except needs.BadRequirement as exc:
        raise HTTPException(400, str(exc)) from None
    farm.cache.mkdir(parents=True, exist_ok=True)
    partial = farm.cache / f".upload-{secrets.token_hex(8)}.part"
    digest = hashlib.sha256()
    try:
        size = await receive(server, upload, partial, digest)
        printers = await _asked(farm.db.printers(TIMEOUT))
        if not printers:
            raise HTTPException(409, "the farm has no printer registered yet")
        eligible, why_not, warnings, commands = await asyncio.to_thread(
            eligibility, server, farm, partial, name, wanted, printers
        )
        if not eligible:
            reasons = "; ".join(f"{key}: {why}" for key, why in why_not.items())
            raise HTTPException(
                400,
                {
                    "error": f"no printer of the farm can print {name} "
                    f"({needs.describe(wanted)}): {reasons}",
                    "printers": why_not,
                },
            )
        file_hash = digest.hexdigest()
        # Stored in the database a chunk at a time (a gigabyte is never held in memory).
        await _asked(farm.db.store_file(partial, file_hash, TIMEOUT), max(TIMEOUT, size / 2e6))
        cached = farm.cache_path(file_hash, name)
        partial.replace(cached)  # this node prints it without fetching it back
    finally:
        partial.unlink(missing_ok=True)
        for service in server.services.values():
            service.forget(partial)  # its check was of the upload, not of a job here
    user = user_of(request)
    ids = await _asked(
        farm.db.submit(name, file_hash, wanted, priority, copies, commands, user, TIMEOUT)
    )
    farm.estimate(ids, cached)  # planned in the background: the listing shows it when made
    shown = ", ".join(map(str, ids))
    log.info("farm: %s queued as job %s (%s)", name, shown, needs.describe(wanted))
    return {
        "jobs": ids,
        "name": name,
        "hash": file_hash,
        "requires": needs.describe(wanted),
        "eligible": eligible,
        "not_eligible": why_not,
        "findings": warnings,
    }


def router() -> APIRouter:
    router = APIRouter()

    @router.get("/v1/farm")
    async def farm_view(request: Request) -> dict[str, Any]:
        """The farm: its nodes, every printer with its state and capabilities, its jobs."""
        return await farm_json(farm_of(request))

    @router.get("/v1/farm/jobs")
    async def jobs(request: Request) -> list[dict[str, Any]]:
        farm = farm_of(request)
        nodes = {node["id"]: node for node in await _asked(farm.db.nodes(TIMEOUT))}
        paces = estimates.Paces(await _asked(farm.db.printers(TIMEOUT)))
        here = farm.settings.node_url
        return [job_json(job, nodes, here, paces) for job in await _asked(farm.db.jobs(TIMEOUT))]

    @router.post("/v1/farm/jobs", status_code=201)
    async def submit_job(
        request: Request,
        file: Annotated[UploadFile, File()],
        require: Annotated[list[str] | None, Form()] = None,
        priority: Annotated[int, Form()] = 0,
        copies: Annotated[int, Form()] = 1,
    ) -> dict[str, Any]:
        """A G-code file for the farm, with requirements (``require``: material=PLA,
        T1.head=MK1-250, tag=abs, machine=..., printer=...), a priority and copies."""
        return await submit(request, file, require or [], priority, copies)

    @router.get("/v1/farm/jobs/{job_id}")
    async def job(request: Request, job_id: int) -> dict[str, Any]:
        farm = farm_of(request)
        found = await _asked(farm.db.job(job_id, TIMEOUT))
        if found is None:
            raise HTTPException(404, f"the farm has no job {job_id}")
        nodes = {node["id"]: node for node in await _asked(farm.db.nodes(TIMEOUT))}
        paces = estimates.Paces(await _asked(farm.db.printers(TIMEOUT)))
        return job_json(found, nodes, farm.settings.node_url, paces)

    @router.post("/v1/farm/jobs/{job_id}/resume", status_code=201)
    async def recover(
        request: Request, job_id: int, wanted: Recovery | None = None
    ) -> dict[str, Any]:
        """Queue the rest of a job that did not complete, for the printer that printed it:
        from its first line not acknowledged, or ``from_line``, or ``from_layer``."""
        farm = farm_of(request)
        wanted = wanted or Recovery()
        found = await _asked(farm.db.job(job_id, TIMEOUT))
        if found is None:
            raise HTTPException(404, f"the farm has no job {job_id}")
        if found["state"] not in states.RESUMABLE:  # said before any file is fetched
            refusal = states.resume_refusal(job_id, found["state"], found["resumed_by"])
            raise HTTPException(409, refusal)
        if wanted.from_layer is not None and wanted.from_line is not None:
            raise HTTPException(400, "from_layer and from_line both say where: give one")
        line = wanted.from_line or found["last_line"] + 1
        path = farm.cache_path(found["file"], found["name"])
        # The rest's lines to send: those after the ones acknowledged, or counted in the file
        # from the line asked for (a resumed job's "lines a/b" are of what it prints).
        rest = max(found["total_lines"] - found["lines"], 0)
        if wanted.from_layer is not None or wanted.from_line is not None or path.exists():
            if not path.exists():
                await _asked(farm.db.fetch_file(found["file"], path, TIMEOUT), FILE_TIMEOUT)
            try:
                if wanted.from_layer is not None:
                    line = await asyncio.to_thread(layer_line, path, wanted.from_layer)
                rest = await asyncio.to_thread(rest_lines, path, line)
            except rh.HostError as exc:
                raise HTTPException(400, str(exc)) from None
        try:
            made = await _asked(farm.db.recover(job_id, line, rest, TIMEOUT))
        except LookupError as exc:
            raise HTTPException(404, str(exc)) from None
        except ValueError as exc:  # resumed meanwhile (states.MoveRefused), or never printed
            raise HTTPException(409, str(exc)) from None
        log.info("farm: job %d recovered from line %d as job %d", job_id, line, made)
        # Its estimate is the whole file's (copied) until the rest is planned: here, when
        # this node has the file (planning another node's file would fetch it first).
        path = farm.cache_path(found["file"], found["name"])
        if path.exists():
            farm.estimate([made], path, line)
        return {"jobs": [made], "resumes": job_id, "from_line": line}

    @router.delete("/v1/farm/jobs/{job_id}")
    async def cancel(request: Request, job_id: int) -> dict[str, Any]:
        """Cancel a queued job; one that streams is cancelled by its node (its safe stop
        first), told at once."""
        farm = farm_of(request)
        was = await _asked(farm.db.cancel(job_id, TIMEOUT))
        if was is None:
            raise HTTPException(404, f"the farm has no job {job_id}")
        if was["state"] == "queued":
            return {"job": job_id, "state": "cancelled"}
        if was["state"] in ("claimed", "printing", "paused"):
            return {"job": job_id, "state": was["state"], "cancelling": True}
        raise HTTPException(409, f"farm job {job_id} is {was['state']}: nothing to cancel")

    @router.get("/v1/farm/events")
    async def events(request: Request) -> StreamingResponse:
        """The farm's changes as they happen (jobs queued, claimed, reported; nodes and
        printers), from PostgreSQL's notifications."""
        farm = farm_of(request)

        async def stream() -> AsyncIterator[str]:
            async with farm.events.listen() as events:
                hello = {"type": "hello", "node": farm.id, "time": time.time()}
                yield f"data: {json.dumps(hello)}\n\n"
                while True:
                    try:
                        event = await asyncio.wait_for(events.get(), KEEPALIVE)
                    except TimeoutError:
                        yield ": keepalive\n\n"
                        continue
                    yield f"data: {json.dumps(event.as_json())}\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream")

    # OctoPrint's face of the farm: a slicer set up with http://NODE/farm as its
    # OctoPrint sends "Upload and Print" into the farm's queue.
    @router.get("/farm/api/version")
    async def version(request: Request) -> dict[str, Any]:
        farm_of(request)
        return {"api": "0.1", "server": "1.11.8", "text": "OctoPrint 1.11.8 (repetrel-host farm)"}

    @router.post("/farm/api/files/local", status_code=201)
    async def octoprint_upload(
        request: Request,
        file: Annotated[UploadFile, File()],
        print_: Annotated[str, Form(alias="print")] = "false",
        path: Annotated[str, Form()] = "",
    ) -> dict[str, Any]:
        if print_.lower() not in ("true", "1", "yes"):
            raise HTTPException(
                409, "the farm prints what it is sent: use Upload and Print (print=true)"
            )
        queued = await submit(request, file, [], 0, 1)
        return {
            "done": True,
            "files": {"local": {"name": queued["name"], "origin": "local", "path": queued["name"]}},
            "farm": queued,
        }

    return router
