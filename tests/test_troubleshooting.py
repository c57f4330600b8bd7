"""docs/troubleshooting.md explains every sentence the programs print when something goes
wrong (collected from the source: tests/support/troubleshooting_sentences.py says what counts),
and quotes none that the code no longer says.

The page quotes a sentence as a list item that starts with it in backticks::

    - `cannot open PORT: no such port (is the printer plugged in and on?)`
      What it means. What to do.

A placeholder of the code (``{port}``) matches any text there, so the page writes it in
capitals (``PORT``); whitespace is free.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from tests.support.troubleshooting_sentences import (
    EXCLUDED,
    SRC,
    Sentence,
    collect,
    excludes,
    shown,
    unique,
)

PAGE = Path(__file__).resolve().parents[1] / "docs" / "troubleshooting.md"
_QUOTE = re.compile(r"^- `([^`]+)`", re.MULTILINE)  # at the margin: not in an admonition


def page_quotes(text: str) -> list[str]:
    """The sentences the page quotes: each list item that starts with one in backticks."""
    return [" ".join(q.split()) for q in _QUOTE.findall(text)]


def explained(sentence: Sentence, quotes: list[str]) -> bool:
    """A sentence is quoted whole; a piece of one (a reason put into another sentence) is
    found inside a quote."""
    pattern = sentence.pattern()
    if sentence.fragment:
        return any(pattern.search(q) for q in quotes)
    return any(pattern.fullmatch(q) for q in quotes)


def unexplained(sentences: list[Sentence], quotes: list[str]) -> list[Sentence]:
    return [s for s in unique(sentences) if not explained(s, quotes)]


def stale(quotes: list[str], sentences: list[Sentence]) -> list[str]:
    """Quotes that no sentence of the code matches (whole, or a piece of one inside)."""
    wholes = [s.pattern() for s in unique(sentences) if not s.fragment]
    pieces = [s.pattern() for s in unique(sentences) if s.fragment]
    return [
        q
        for q in quotes
        if not any(p.fullmatch(q) for p in wholes) and not any(p.search(q) for p in pieces)
    ]


def paste_form(missing: list[Sentence]) -> str:
    lines = [
        f"{len(missing)} sentences the page does not explain. Paste each under its section "
        f"of {PAGE.name}, name its placeholders, and say what it means and what to do:",
        "",
    ]
    for sentence in missing:
        lines += [f"- `{sentence.paste()}`", f"  (src/repetrel_host/{sentence.where})"]
    return "\n".join(lines)


@pytest.fixture(scope="module")
def sentences() -> list[Sentence]:
    return shown(collect())


@pytest.fixture(scope="module")
def quotes() -> list[str]:
    return page_quotes(PAGE.read_text())


def test_the_collector_finds_the_errors(sentences: list[Sentence]) -> None:
    """A few hundred, from every part of the house (a broken collector finds few)."""
    assert len(unique(sentences)) > 250
    places = {s.where.split("/")[0].split(":")[0] for s in sentences}
    for place in ("cli", "session", "config.py", "server", "pytest_plugin", "fakes"):
        assert place in places


def test_every_sentence_is_on_the_page(sentences: list[Sentence], quotes: list[str]) -> None:
    missing = unexplained(sentences, quotes)
    assert not missing, paste_form(missing)


def test_every_quote_is_still_in_the_code(sentences: list[Sentence], quotes: list[str]) -> None:
    gone = stale(quotes, sentences)
    assert not gone, (
        f"{len(gone)} sentences quoted on {PAGE.name} that the code no longer says "
        "(remove them, or quote the new wording):\n" + "\n".join(f"- `{q}`" for q in gone)
    )


def test_each_exclusion_still_excludes_something() -> None:
    """An exclusion whose message is gone goes too (it would hide a new one)."""
    everything = collect()
    for rule in EXCLUDED:
        assert any(excludes(rule, s) for s in everything), rule


def test_a_new_error_is_caught(tmp_path: Path, quotes: list[str]) -> None:
    """A raise added to the code, and not to the page, fails the check."""
    root = tmp_path / "repetrel_host"
    shutil.copytree(SRC, root, ignore=shutil.ignore_patterns("page", "__pycache__"))
    with (root / "planning.py").open("a") as handle:
        handle.write(
            "\n\ndef _new(port: str) -> None:\n"
            '    raise JobError(f"{port}: a brand-new sentence nobody explained")\n'
        )
    missing = unexplained(shown(collect(root)), quotes)
    assert [s.paste() for s in missing] == ["PORT: a brand-new sentence nobody explained"]
    assert "- `PORT: a brand-new sentence nobody explained`" in paste_form(missing)


def test_a_quote_must_match_whole() -> None:
    """Placeholders match any text, the rest must be there, in order."""
    sentence, *_ = [
        s
        for s in unique(collect())
        if s.paste().startswith("cannot open PORT: the port is busy")
        and s.where.startswith("links/serial.py")
    ]
    assert explained(sentence, ["cannot open PORT: the port is busy (another program has it open)"])
    assert explained(
        sentence, ["cannot open  /dev/ttyUSB0: the port is busy (another program has it open)"]
    )
    assert not explained(sentence, ["cannot open PORT: the port is busy"])
    assert stale(["cannot open PORT: the port is on fire"], [sentence])
