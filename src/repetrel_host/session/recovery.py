"""Going on with a print that stopped (Ctrl-C, a lost link, a controller error, a killed
host) from a source line: where it starts, and the sentences that offer it.

"Recovery" here is Marlin's word (power-loss recovery), kept apart from "resume", which in
this package only ever means ending a pause. The lines that restore the machine before the
file goes on are :func:`~repetrel_host.session.machine_state.preamble`'s. Stored and wire names
(``--from-line``, ``resume_line`` in history files and the server's JSON, ``/resume`` paths)
keep the words users already type and read.

Pure: nothing here touches a file or port.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from typing import Protocol

from repetrel_host.session.machine_state import MachineState, PreambleLine

RECOVERY_SOURCE = "resume"  # JobLine.source of the preamble's lines


@dataclass(frozen=True)
class RecoveryPoint:
    """Where a recovered job starts: its first source line, the preamble that goes first, and
    the byte offset the file's progress starts from."""

    line: int  # the first command's source line
    requested: int  # the line asked for (the first command is on it or after it)
    state: MachineState
    preamble: list[PreambleLine]
    start_offset: int  # bytes of the file skipped (up to the end of the last skipped command)


class EndedJob(Protocol):
    """What a job that did not complete says of where it stopped (the session's
    :class:`~repetrel_host.session.print_job.PrintJob`)."""

    @property
    def recovery_line(self) -> int | None: ...

    @property
    def recovery_known_to_run(self) -> bool: ...

    @property
    def sent_through(self) -> int | None: ...


def recovery_from(job: EndedJob, arguments: tuple[str, ...]) -> tuple[str, str] | None:
    """Where a job that did not complete goes on, as hyrel-send and the console say it:
    which first line (``not acknowledged``, or ``not known to have run``) and the command
    from it; None where none of it ran."""
    line = job.recovery_line
    if line is None:
        return None
    after = "not known to have run" if job.recovery_known_to_run else "not acknowledged"
    return after, recovery_command(arguments, line)


def recovery_window(job: EndedJob, arguments: tuple[str, ...]) -> str | None:
    """After :func:`recovery_from`'s line, what is not sure: lines sent and not confirmed when
    the job ended (a lost link takes their oks with it), some of which may have run; the
    sentence says which command repeats them and which skips them. None when none were."""
    line, sent = job.recovery_line, job.sent_through
    if line is None or sent is None or sent < line:
        return None
    skip = recovery_command(arguments, sent + 1)
    return (
        f"lines {line} to {sent} were sent and not confirmed: some may have run. Resuming "
        f"from line {line} runs them again (any that ran, twice); this skips them (any that "
        f"did not run, never): {skip}"
    )


def recovery_command(arguments: tuple[str, ...], line: int, option: str = "--from-line") -> str:
    """hyrel-send's command line with ``--from-line line`` (or ``option``) in place of any
    earlier recovery's."""
    kept: list[str] = []
    skip = False
    for argument in arguments:
        if skip:
            skip = False
        elif argument in ("--from-line", "--from-layer"):
            skip = True  # and its value
        elif not argument.startswith(("--from-line=", "--from-layer=")):
            kept.append(argument)
    return shlex.join(["hyrel-send", *kept, option, str(line)])
