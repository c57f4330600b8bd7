"""hyrel-send --console through a real pty: what a user types, and what the terminal shows.

The console runs as a real process (pexpect) on the built-in fake, or on a slowed fake of
its own (``--move-time``) where a job must still be running when the next line is typed.
prompt_toolkit asks the terminal where its cursor is before it draws the status line; the
``Term`` here answers as a terminal does.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pexpect
import pytest

from repetrel_host.fakes.fake_controller import BuiltInFake
from tests.support.helpers import EXAMPLE, executed

CURSOR_QUERY = re.compile(rb"\x1b\[6n")
M110_REFUSED = "error: M110 sets line numbers, which the host owns; it cannot be sent"
PRINTING_REFUSED = "error: a job is printing: type !pause first (a command waits)"
MOVES = "".join(f"G1 X{i % 50} Y{i % 7} F3000\n" for i in range(120))


def _environment(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "HYREL_PORT"}
    env.update(
        TERM="xterm",
        XDG_CONFIG_HOME=str(tmp_path / "config-home"),
        XDG_DATA_HOME=str(tmp_path / "data-home"),
    )
    return env


class Term:
    """hyrel-send --console on a real pty of 40 rows by 120 columns."""

    def __init__(self, tmp_path: Path, *args: str) -> None:
        self.child = pexpect.spawn(
            sys.executable,
            ["-m", "repetrel_host.cli", "--console", "--no-history", *args],
            env=_environment(tmp_path),
            cwd=str(tmp_path),
            dimensions=(40, 120),
            timeout=20,
        )
        self.expect("Type G-code, or !help")

    def expect(self, text: str, regex: bool = False) -> None:
        """Wait for ``text`` on the screen, answering prompt_toolkit's cursor queries."""
        pattern = re.compile(text.encode()) if regex else re.compile(re.escape(text.encode()))
        while self.child.expect([CURSOR_QUERY, pattern]) == 0:
            self.child.send("\x1b[1;1R")  # the cursor is at the top: the screen is below

    def type(self, line: str) -> None:
        self.child.send(line + "\r")

    def exit_code(self) -> int:
        while self.child.expect([CURSOR_QUERY, pexpect.EOF]) == 0:
            self.child.send("\x1b[1;1R")
        self.child.close()
        assert self.child.exitstatus is not None
        return self.child.exitstatus

    def close(self) -> None:
        if self.child.isalive():
            self.child.kill(9)


@pytest.fixture
def term(tmp_path: Path) -> Iterator[Term]:
    console = Term(tmp_path)
    yield console
    console.close()


@pytest.fixture
def slow_fake(tmp_path: Path) -> Iterator[BuiltInFake]:
    """A fake that takes 20 ms a move: a job of 120 moves runs for seconds."""
    with BuiltInFake(tmp_path / "slow.log", ["--move-time", "0.02"]) as fake:
        yield fake


@pytest.mark.timeout(40)
def test_m105_shows_the_temperature_and_ok_and_the_status_line_keeps_it(term: Term) -> None:
    term.type("M105")
    term.expect(r"ok T:\d+\.\d", regex=True)
    # The status line is drawn again under the printed reply: port, state, temperatures.
    term.expect(r"fake ready \| T \d+\.\d/\d+ · B \d+\.\d/\d+", regex=True)
    term.type("!quit")
    assert term.exit_code() == 0


@pytest.mark.timeout(40)
def test_host_owned_words_are_refused_with_the_apis_sentences(term: Term) -> None:
    term.type("M110 N5")
    term.expect(M110_REFUSED)
    term.type("N5 G1 X1*33")
    term.expect("error: line numbers and checksums are the host's: send the command alone")
    term.type("!frobnicate")
    term.expect("error: there is no console command !frobnicate: !help lists them")
    term.type("M115")  # the console goes on
    term.expect("FIRMWARE_NAME:")
    term.type("!help")
    term.expect("!print FILE [--force]")
    term.type("M112")
    term.expect("M112 sent at once: emergency stop")
    term.type("!quit")
    assert term.exit_code() == 0


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_up_arrow_recalls_the_last_command_in_this_and_the_next_session(
    tmp_path: Path,
) -> None:
    first = Term(tmp_path)
    try:
        first.type("M115")
        first.expect("FIRMWARE_NAME:")
        first.child.send("\x1b[A")  # up: M115 again on the line
        first.type("")
        first.expect("ok")
        first.expect("FIRMWARE_NAME:")  # a second answer: it was sent again
        first.child.sendcontrol("d")  # Ctrl-D leaves, as !quit
        assert first.exit_code() == 0
    finally:
        first.close()
    history = tmp_path / "data-home" / "repetrel-host" / "console-history"
    assert "+M115" in history.read_text()
    second = Term(tmp_path)
    try:
        second.child.send("\x1b[A")
        second.type("")
        second.expect("FIRMWARE_NAME:")
        second.type("!quit")
        assert second.exit_code() == 0
    finally:
        second.close()


@pytest.mark.timeout(60)
def test_print_a_job_with_status_then_the_summary(term: Term, tmp_path: Path) -> None:
    term.type(f"!print {EXAMPLE}")
    term.expect("printing square-tube.gcode (machine profile marlin)")
    term.type("!status")
    term.expect("machine profile: marlin")
    term.expect("job: ")
    term.expect(r"square-tube.gcode: done: \d+ lines in [\d.]+s, \d+ lines/s", regex=True)
    term.type("!status")
    term.expect("job: none")
    term.type("!quit")
    assert term.exit_code() == 0


@pytest.mark.timeout(60)
def test_a_job_with_errors_is_refused_unless_forced(term: Term, tmp_path: Path) -> None:
    job = tmp_path / "bad.gcode"
    job.write_text("G28\nM229 E1 D0\nT7\n")
    term.type(f"!print {job}")
    term.expect("bad.gcode:2: error: M229 E1 D0 is an illegal combination")
    term.expect("error: bad.gcode: not sent (2 errors; !print FILE --force sends)")
    term.type(f"!print {job} --force")
    term.expect(r"bad.gcode: done: 3 lines", regex=True)
    term.type("!print")
    term.expect("error: !print takes one FILE, and --force to send it despite errors")
    term.type(f"!print {tmp_path / 'missing.gcode'}")
    term.expect("missing.gcode: no such file")
    term.type("!quit")
    assert term.exit_code() == 0


@pytest.mark.timeout(60)
def test_an_m0_pauses_the_job_until_resume(term: Term, tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\nG1 X10 F3000\nM0 ; load the filament\nG1 X20\nM104 S0\n")
    term.type(f"!print {job}")
    term.expect("paused at job.gcode:3: load the filament - !resume goes on")
    term.type("M105")  # a paused job lets commands go
    term.expect("ok T:")
    term.type("!resume")
    term.expect("resumed")
    term.expect(r"job.gcode: done: \d+ lines", regex=True)
    term.type("!quit")
    assert term.exit_code() == 0


@contextmanager
def printing(tmp_path: Path, fake: BuiltInFake) -> Iterator[Term]:
    """The console on ``fake`` (a slow one) printing MOVES from tmp_path/moves.gcode."""
    job = tmp_path / "moves.gcode"
    job.write_text(MOVES)
    term = Term(tmp_path, "--port", fake.port)
    try:
        term.type(f"!print {job}")
        term.expect("printing moves.gcode")
        yield term
    finally:
        term.close()


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_pause_resume_and_commands_while_printing(tmp_path: Path, slow_fake: BuiltInFake) -> None:
    with printing(tmp_path, slow_fake) as term:
        term.type("M105")
        term.expect(PRINTING_REFUSED)
        term.child.sendcontrol("c")
        term.expect("!cancel stops the job safely")
        term.type("!pause")
        term.expect(r"paused at moves.gcode:\d+ - !resume goes on", regex=True)
        term.type("!status")
        term.expect(r"job: moves.gcode \d+% \d+ lines, at moves.gcode:\d+ \(paused\)", regex=True)
        term.type("!resume")
        term.expect("resumed")
        term.expect(r"moves.gcode: done: 120 lines", regex=True)
        term.type("!quit")
        assert term.exit_code() == 0
    commands = [c for c in executed(slow_fake.log_path) if c.startswith("G1")]
    assert commands == MOVES.splitlines()  # paused and resumed: every move once, in order


@pytest.mark.timeout(60)
def test_cancel_and_quit_stop_the_job_with_the_safe_stop(
    tmp_path: Path, slow_fake: BuiltInFake
) -> None:
    job = tmp_path / "moves.gcode"
    with printing(tmp_path, slow_fake) as term:
        term.type("!cancel")
        term.expect("cancelling moves.gcode: sending the safe-stop sequence")
        term.expect("moves.gcode: stopped (the last line the controller acknowledged is")
        # As hyrel-send does: the command that goes on from where it stopped.
        term.expect(
            f"to resume from the first line not acknowledged: hyrel-send {job} --port "
            f"{slow_fake.port} --from-line ",
        )
        term.type(f"!print {job}")
        term.expect("printing moves.gcode")
        term.type("!quit")
        term.expect("quitting: stopping moves.gcode with the safe-stop sequence first")
        term.expect("moves.gcode: stopped")
        assert term.exit_code() == 0
    done = [c for c in executed(slow_fake.log_path) if c != "M105"]  # less the polls
    assert done[-1] == "M84"  # the safe stop's last: motors off


def piped_console(tmp_path: Path, lines: str) -> subprocess.CompletedProcess[str]:
    """``hyrel-send --console`` on the built-in fake, reading ``lines`` from a pipe."""
    return subprocess.run(
        [sys.executable, "-m", "repetrel_host.cli", "--console", "--no-history"],
        input=lines,
        capture_output=True,
        text=True,
        timeout=50,
        env=_environment(tmp_path),
    )


@pytest.mark.timeout(60)
def test_piped_lines_get_their_replies_and_end_of_input_waits_for_the_job(
    tmp_path: Path,
) -> None:
    result = piped_console(tmp_path, f"M105\n\nM110\n!print {EXAMPLE}\n")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    # From a pipe, each reply line says which command it answers.
    assert re.search(r"^M105: ok T:\d+\.\d", out, re.MULTILINE), out
    assert f"M110: {M110_REFUSED}" in out
    assert "end of input: waiting for square-tube.gcode to end" in out
    assert re.search(r"square-tube.gcode: done: \d+ lines", out), out
    assert "\x1b[" not in out  # no terminal drawing into a pipe


@pytest.mark.timeout(30)
def test_a_job_with_console_is_one_sentence() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "repetrel_host.cli", "--console", str(EXAMPLE)],
        capture_output=True,
        text=True,
        timeout=20,
        stdin=subprocess.DEVNULL,
        env={k: v for k, v in os.environ.items() if k != "HYREL_PORT"},
    )
    assert result.returncode == 2
    assert result.stderr.strip() == "error: --console takes no JOB: type !print JOB at its prompt"
    help_text = subprocess.run(
        [sys.executable, "-m", "repetrel_host.cli", "--help"],
        capture_output=True,
        text=True,
        timeout=20,
    ).stdout
    text = " ".join(help_text.split())
    assert "--console An interactive terminal on the printer" in text
    assert "!print FILE [--force], !pause, !resume, !cancel, !status, !help, !quit" in text


@pytest.mark.timeout(60)
def test_a_line_longer_than_controllers_take_is_refused_and_the_session_goes_on(
    tmp_path: Path,
) -> None:
    # Marlin keeps 96 characters of a line: the rest is lost, its checksum fails, and the
    # resends of it end the link (a paused job's with it).
    result = piped_console(tmp_path, f"G1 X{'1' * 200}\nM105\n")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert (
        f"G1 X{'1' * 25}...: error: the command is 204 characters long; controllers take at "
        "most 96" in out
    )
    assert "greeting the controller again" not in out
    assert re.search(r"^M105: ok T:\d+\.\d", out, re.MULTILINE), out


@pytest.mark.timeout(60)
def test_m112_goes_at_once_even_while_a_job_prints(tmp_path: Path, slow_fake: BuiltInFake) -> None:
    with printing(tmp_path, slow_fake) as term:
        term.type("G28")
        term.expect(PRINTING_REFUSED)  # an ordinary command: the console's words
        term.type("M112")
        term.expect("M112 sent at once: emergency stop")
        term.expect("moves.gcode: failed: stopped by an emergency stop (M112)")
    assert "M112" in executed(slow_fake.log_path)
