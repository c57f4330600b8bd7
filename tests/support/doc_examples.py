"""The docs' fenced blocks as the tests read them, and the fresh shell of a reader who
runs them in a clone (tests/test_docs.py says the rules; tests/test_wheel.py runs the
install)."""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from tests.support.paths import ROOT

DOCS = ROOT / "docs"
README = ROOT / "README.md"
VENV = Path(sys.prefix)  # the venv the tests run in: the one the README's set-up makes
BIN = VENV / "bin"
ACTIVATE = ". .venv/bin/activate"
SHELLS = {"sh", "bash", "console"}  # the fences whose lines a reader types at a shell

_FENCE = re.compile(r"^```(\S*)")
_MARKER = re.compile(r"^<!-- test: (\w+) -->$")
_INCLUDE = re.compile(r'^--8<-- "([^":]+\.md)', re.M)


@dataclass(frozen=True)
class Fence:
    """A fenced block of a page; ``kind`` is its marker's (``<!-- test: KIND -->`` on the
    line before it), None without one."""

    page: str  # relative to the repository
    line: int  # the opening fence's
    lang: str
    kind: str | None
    code: str
    activated: bool  # the page said ". .venv/bin/activate" before the block

    def __str__(self) -> str:
        return f"{self.page}:{self.line}:{self.kind or self.lang}"

    def commands(self) -> list[tuple[str, bool]]:
        """Its command lines, each with whether the venv is activated for it: a trailing
        backslash joins a line to the next; a console block's commands are its ``$``
        lines; a here-document's lines are not commands."""
        found: list[tuple[str, bool]] = []
        activated = self.activated
        pending, heredoc = "", None
        for raw in self.code.splitlines():
            if heredoc is not None:
                heredoc = None if raw.strip() == heredoc else heredoc
                continue
            line = pending + raw
            if line.endswith("\\"):
                pending = line[:-1] + " "
                continue
            pending = ""
            if self.lang == "console":
                if not line.startswith("$ "):
                    continue  # the program's output
                line = line[2:]
            if line.strip() and not line.strip().startswith("#"):
                found.append((line, activated))
            activated = activated or line.strip().startswith(ACTIVATE)
            opened = re.search(r"<<-?\s*'?(\w+)'?", line)
            heredoc = opened[1] if opened else None
        return found


def markdown_files() -> list[Path]:
    """The README, the pages, and the Markdown files the pages include (bench/README.md)."""
    pages = [README, *sorted(DOCS.rglob("*.md"))]
    included = {
        ROOT / name for page in pages for name in _INCLUDE.findall(page.read_text(encoding="utf-8"))
    }
    return pages + sorted(included - set(pages))


def fences(path: Path) -> list[Fence]:
    lines = path.read_text(encoding="utf-8").splitlines()
    found: list[Fence] = []
    said = False  # the page said ". .venv/bin/activate" so far
    number = 0
    while number < len(lines):
        opening = _FENCE.match(lines[number])
        if opening is None:
            said = said or ACTIVATE in lines[number]
            number += 1
            continue
        end = next(i for i in range(number + 1, len(lines)) if lines[i].startswith("```"))
        marker = _MARKER.match(lines[number - 1]) if number else None
        code = "".join(f"{line}\n" for line in lines[number + 1 : end])
        page = str(path.relative_to(ROOT))
        kind = marker[1] if marker else None
        found.append(Fence(page, number + 1, opening[1], kind, code, said))
        said = said or ACTIVATE in code
        number = end + 1
    return found


def examples_in(path: Path) -> list[Fence]:
    """The page's marked blocks."""
    return [fence for fence in fences(path) if fence.kind is not None]


def fresh_shell(tmp: Path) -> dict[str, str]:
    """A new shell's environment: no venv on PATH, no HYREL_* setting, the print history,
    configuration and temporary files in ``tmp``."""
    env = {
        name: value
        for name, value in os.environ.items()
        if not name.startswith("HYREL_") and name != "VIRTUAL_ENV"
    }
    path = [part for part in env.get("PATH", "").split(os.pathsep) if Path(part) != BIN]
    env.update(
        PATH=os.pathsep.join(path),
        XDG_DATA_HOME=str(tmp / "data"),
        XDG_CONFIG_HOME=str(tmp / "config"),
        TMPDIR=str(tmp),
        NO_COLOR="1",
        # The clone's folders are the repository's own: pytest keeps no cache in them.
        PYTEST_ADDOPTS="-p no:cacheprovider",
    )
    return env


def clone(tmp: Path) -> Path:
    """A clone as the README's set-up leaves it: the repository's files (linked) and its
    ``.venv``, which is the venv the tests run in."""
    assert sys.prefix != sys.base_prefix, "the tests run in a venv (the README's set-up)"
    folder = tmp / "clone"
    folder.mkdir()
    for entry in ROOT.iterdir():
        if entry.name not in (".venv", "build"):  # a fresh clone has no build's leftovers
            (folder / entry.name).symlink_to(entry)
    (folder / ".venv").symlink_to(VENV)
    return folder
