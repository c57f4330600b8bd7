"""What hyrel-send answers without a printer: ``--check`` (the job's findings and the
verdict), ``--dry-run`` (the commands, or with ``--framed`` the wire, that would be sent),
``--list-ports`` and ``--history-list``."""

from __future__ import annotations

import os
import re
import shlex
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

from repetrel_host.cli.exit_codes import EXIT_BAD_INPUT, EXIT_OK
from repetrel_host.cli.out import Out
from repetrel_host.cli.times import duration
from repetrel_host.config import UserConfig, load_user_config
from repetrel_host.errors import HostError
from repetrel_host.gcode.analysis import slicer_estimate
from repetrel_host.gcode.heat_rates import learned_heat_rates
from repetrel_host.gcode.lint import Finding, Severity
from repetrel_host.gcode.timeline import PACE_JOBS, PlannedTime, learned_pace
from repetrel_host.protocol.dialects import create_dialect
from repetrel_host.session import history as print_history
from repetrel_host.session.job import HostAction
from repetrel_host.session.planning import (
    JobPlan,
    LinkRequest,
    choose_port,
    history_folder,
    link_settings,
)
from repetrel_host.session.recovery import RECOVERY_SOURCE, recovery_command

_CONTROL = re.compile(r"[\x00-\x09\x0b-\x1f]")


def check_job(plan: JobPlan, errors: Out) -> list[Finding]:
    """Check the whole file and print the findings."""
    findings = plan.check()
    for finding in findings:
        errors.print(finding.format(plan.job.name), markup=False)
    return findings


def check_verdict(
    console: Out, plan: JobPlan, findings: list[Finding], pace: PrinterPace | None = None
) -> int:
    """hyrel-send --check: the verdict on the findings, and the exit code that says it.
    ``pace``: the printer's the job would go to, as its past jobs tell it."""
    refused = [f for f in findings if f.severity is Severity.ERROR]
    verdict = "refused" if refused else "ok"
    console.print(
        f"{plan.job.name}: {verdict} ({len(findings)} findings) with machine "
        f"profile {plan.profile.describe()}",
        markup=False,
    )
    console.print(f"{plan.job.name}: {time_sentence(plan, pace)}", markup=False)
    return EXIT_BAD_INPUT if refused else EXIT_OK


@dataclass(frozen=True)
class PrinterPace:
    """A printer's pace (actual over planned moving time) from its past jobs, as a job on
    it starts from; ``pace`` None: no past job of it tells one."""

    pace: float | None
    port: str  # the printer's port, as its runs' records name it ("" when none resolves)
    machine: str  # the machine profile its runs were planned with
    heat_rates: dict[str, float] = field(default_factory=dict)  # its heaters', learned


def printer_pace(
    port: str | None, folder: Path | None, user: UserConfig, machine: str
) -> PrinterPace:
    """The pace a job on ``port`` with the ``machine`` profile starts from, as hyrel-send
    finds it: the runs in the history ``folder`` (the configured one, else the default)."""
    found = _printer_history(port, folder, user)
    if found is None:
        return PrinterPace(None, "", machine)
    folder, resolved = found
    known = list(islice(print_history.paces(folder, resolved, machine), PACE_JOBS))
    rates = learned_heat_rates(print_history.heat_rates(folder, resolved, machine))
    return PrinterPace(learned_pace(known) if known else None, resolved, machine, rates)


def port_machine(port: str | None, folder: Path | None, user: UserConfig) -> str | None:
    """The profile the last job on ``port`` (as hyrel-send resolves it) ran with."""
    found = _printer_history(port, folder, user)
    return print_history.last_machine(*found) if found is not None else None


def _printer_history(
    port: str | None, folder: Path | None, user: UserConfig
) -> tuple[Path, str] | None:
    """The history folder and the port as hyrel-send resolves them; None when ``auto``
    finds no single candidate (no printer to ask about)."""
    try:
        return history_folder(folder, user), choose_port(port, user)[0]
    except HostError:
        return None


def time_sentence(plan: JobPlan, pace: PrinterPace | None = None) -> str:
    """The job's print time as a job on the printer would start from it: the plan at the
    printer's pace where its past jobs tell one, else the plan's own figure (said so); the
    plan split into moving, heating and tool changes; where its limits came from; the
    slicer's own figure beside it (never in its place)."""
    found = plan.print_time(heat_rates=pace.heat_rates if pace is not None else None)
    if not found.moves:
        return "no moves: no print time"
    planned = PlannedTime.of(found.seconds, found.heating, found.tool_change_seconds)
    parts = [f"{duration(planned.moving)} moving", f"{duration(planned.heating)} heating"]
    if found.tool_changes:
        parts.append(f"{duration(planned.tool_changes)} for {found.tool_changes} tool changes")
    split = f"{duration(planned.total())} as planned ({', '.join(parts)})"
    if pace is not None and pace.pace is not None:
        whole = (
            f"{duration(planned.total(pace.pace))} at this printer's pace "
            f"({pace.pace:.2f} of the plan, from its past jobs), {split}"
        )
    else:
        whole = f"{split}: {_no_pace(pace)}"
    said = slicer_estimate(plan.job.path)
    slicer = f"; the slicer's: {duration(said)}" if said is not None else ""
    return f"estimated time {whole}; limits from {found.limits_from}{slicer}"


def _no_pace(pace: PrinterPace | None) -> str:
    """Why the plan's own figure is the estimate."""
    if pace is None or not pace.port:
        return "no printer is named whose past jobs tell its pace"
    return f"no past job on port {pace.port} with the {pace.machine} profile tells its pace"


def dry_run(errors: Out, plan: JobPlan, framed: bool, protocol: str | None) -> None:
    """hyrel-send --dry-run: a preview, shown even when the findings would refuse the job."""
    link = link_settings(LinkRequest(protocol=protocol), plan.machine)
    # On stderr: stdout holds the commands alone, for a script to read.
    errors.print(
        f"{plan.job.name}: a dry run, nothing sent; machine profile "
        f"{plan.profile.describe()}, {link.protocol} protocol",
        markup=False,
    )
    _print_commands(plan, framed, link.protocol)


def _print_commands(plan: JobPlan, framed: bool, protocol: str) -> None:
    """The commands on stdout, exactly as they would go; host actions noted on stderr."""
    pause_sync = create_dialect(protocol).pause_command  # M0 where the controller waits
    # A recovered job's preamble is shown with why each line is there (not on the wire).
    notes = iter(plan.recovery.preamble if plan.recovery is not None and not framed else [])

    def commands() -> Iterator[str]:
        for item in plan.items(pause_sync=pause_sync):
            if isinstance(item, HostAction):
                sys.stderr.write(f"{item.position}: host {item.kind}: {item.message}\n")
            elif item.source == RECOVERY_SOURCE and (note := next(notes, None)) is not None:
                yield f"{item.command} ; {note.why}"
            else:
                yield item.command

    if framed:
        from repetrel_host.session.loopback import wire_preview  # only a preview needs it

        for data in wire_preview(commands(), protocol=protocol):
            # Hyrel's control bytes (the ping, 0x07, would ring the terminal's bell) shown.
            text = data.decode("ascii", errors="replace")
            sys.stdout.write(_CONTROL.sub(lambda m: f"<0x{ord(m.group()):02x}>", text))
    else:
        for command in commands():
            sys.stdout.write(command + "\n")
    sys.stdout.flush()


def list_serial_ports(console: Out) -> None:
    """hyrel-send --list-ports: one line a port, candidates marked."""
    from repetrel_host.links.ports import describe, list_ports

    found = list_ports()
    for port in found:
        console.print(describe(port), markup=False)
    if not found:
        console.print("no serial ports found", markup=False)


def history_list(console: Out, folder: Path | None, config: Path | None) -> None:
    """hyrel-send --history-list: the newest runs, how each ended."""
    folder = history_folder(folder, load_user_config(config))
    entries = print_history.entries(folder)
    if not entries:
        console.print(f"no prints in {folder} yet", markup=False)
        return
    console.print(f"Print history in {folder} (newest first):", markup=False)
    for entry in entries:
        line = print_history.describe(entry.run, entry.record, entry.progress, entry.alive)
        console.print(line, markup=False)
        if entry.killed and entry.progress is not None:
            console.print(f"  {_killed_recovery(entry.progress, entry.run.stream)}", markup=False)


def _killed_recovery(progress: print_history.RunProgress, stream: Path) -> str:
    """How a killed run is recovered: from its progress record's line, uncertainly (what was
    sent after the last acknowledged line may have run, and the record may be a moment
    behind the stream)."""
    line = progress.resume_line
    if line is None and progress.all_sent:
        ran = "known to have run" if progress.known_to_run else "acknowledged"
        return f"nothing to resume: every line of the job was {ran}"
    after = print_history.lines_after(stream, progress.stream_bytes)
    later = (
        ""
        if after == 0
        else f"; the stream has {after if after is not None else 'more'} lines after that, "
        "sent later"
    )
    if progress.sent:
        uncertain = f"uncertain: lines up to {progress.sent} were sent and may have run{later}"
    else:
        uncertain = f"uncertain: no line of the job was sent when last recorded{later}"
    what = "to resume" if line is not None else "no line is known to have run: to start again"
    if not progress.command:  # a library user's run: the line only
        where = f"print({progress.path!r}, from_line={line})" if line is not None else "again"
        return f"{what} ({uncertain}): {where}"
    if line is not None:
        command = recovery_command(progress.command, line)
    else:
        command = shlex.join(["hyrel-send", *progress.command])
    if progress.cwd and progress.cwd != os.getcwd():  # a job's relative path is from there
        command = f"cd {shlex.quote(progress.cwd)} && {command}"
    return f"{what} ({uncertain}): {command}"
