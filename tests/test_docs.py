"""The documentation site: it builds with ``mkdocs build --strict`` (a broken link, anchor
or snippet, a page left out of the nav, a docstring that does not render fails it), every
page in docs/ is in the nav and one click from the README, the README's links land on a
page and an anchor that exist, and the pages' examples run.

An example runs when a marker comment stands on the line before its fence::

    <!-- test: python -->    the block runs as a Python script (from the repository's root)
    <!-- test: shell -->     each command line runs in bash and must exit 0
    <!-- test: script -->    the block runs as one bash script in a folder of its own (with
                             examples/); its background processes are stopped after it, and
                             the server's port 8765 becomes a free one
    <!-- test: pytest -->    the block is a test file, run by pytest (the hyrel plugin)
    <!-- test: loadout -->   a loadout file: hyrel-send --check of the example job with it
    <!-- test: config -->    a configuration file: hyrel-send --dry-run of the example job

Every command runs without a printer (the built-in fake, or a dry run), with the print
history and configuration in a temporary folder.
"""

from __future__ import annotations

import contextlib
import html.parser
import os
import re
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"
BIN = Path(sys.executable).parent  # the venv's hyrel-send, hyrel-server...

_MARKER = re.compile(r"^<!-- test: (\w+) -->\n```[^\n]*\n(.*?)^```", re.M | re.S)
_ANY_MARKER = re.compile(r"<!-- test: (\w+) -->")
MKDOCS_BUILD = [sys.executable, "-m", "mkdocs", "build", "--strict"]
KINDS = {"python", "shell", "script", "pytest", "loadout", "config"}


@dataclass(frozen=True)
class Example:
    page: str  # relative to the repository
    line: int
    kind: str
    code: str

    def __str__(self) -> str:
        return f"{self.page}:{self.line}:{self.kind}"


def markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def examples_in(path: Path) -> list[Example]:
    text = path.read_text(encoding="utf-8")
    found = []
    for match in _MARKER.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        found.append(Example(str(path.relative_to(ROOT)), line, match.group(1), match.group(2)))
    return found


EXAMPLES = [example for path in markdown_files() for example in examples_in(path)]


def test_every_marker_is_an_example_of_a_known_kind():
    """A marker not followed by a fence, or of a kind nobody runs, would be skipped silently."""
    for path in markdown_files():
        text = path.read_text(encoding="utf-8")
        markers = _ANY_MARKER.findall(text)
        assert set(markers) <= KINDS, f"{path.name}: unknown example kinds {set(markers) - KINDS}"
        assert len(markers) == len(examples_in(path)), (
            f"{path.name}: a '<!-- test: ... -->' marker not right before a fenced block"
        )
    assert {example.kind for example in EXAMPLES} == KINDS  # every kind is exercised
    assert len(EXAMPLES) >= 15


# --- the site ---------------------------------------------------------------------------


def mkdocs_build(
    site: Path, config: Path = ROOT / "mkdocs.yml"
) -> subprocess.CompletedProcess[str]:
    # Not --quiet: it hides the warnings from the counter that --strict fails on.
    return subprocess.run(
        [*MKDOCS_BUILD, "--config-file", str(config), "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=400,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("site")
    built = mkdocs_build(folder)
    assert built.returncode == 0, f"mkdocs build --strict failed:\n{built.stderr}{built.stdout}"
    return folder


@pytest.mark.timeout(450)
def test_the_site_builds_strict(site: Path):
    assert (site / "index.html").is_file()
    assert (site / "search" / "search_index.json").is_file()  # Material's search
    reference = (site / "api-reference" / "index.html").read_text(encoding="utf-8")
    assert ":meth:" not in reference and ":class:" not in reference  # roles read as code
    ids = _Ids()
    ids.feed(reference)
    public = [
        "connect", "Printer", "PrintJob", "Reply", "session.events.Progress", "errors.HostError",
    ]  # fmt: skip
    for name in public:
        assert f"repetrel_host.{name}" in ids.ids, name
    for name in ("HyrelPrinter", "AsyncHyrelPrinter", "HyrelController", "PrintResult"):
        module = "jobs" if name == "PrintResult" else "facade"
        assert f"repetrel_host.pytest_plugin.{module}.{name}" in ids.ids, name


@pytest.mark.timeout(450)
def test_a_broken_link_fails_the_build(tmp_path: Path):
    """The strict build is what catches a broken page: shown on a copy with one bad link."""
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# Home\n\n[gone](streaming.md#no-such-anchor)\n")
    (docs / "streaming.md").write_text("# Streaming\n")
    # Our own file, with a Python name in it (the Mermaid fence's format): unsafe_load and
    # dump read and write that tag; safe_load refuses it.
    config = yaml.unsafe_load((ROOT / "mkdocs.yml").read_text())
    config["docs_dir"] = str(docs)
    config["nav"] = ["index.md", "streaming.md"]
    config["plugins"] = ["search"]
    config["hooks"] = [str(ROOT / hook) for hook in config.get("hooks", [])]  # from the copy
    (tmp_path / "mkdocs.yml").write_text(yaml.dump(config))
    built = mkdocs_build(tmp_path / "site", tmp_path / "mkdocs.yml")
    assert built.returncode != 0
    assert "no-such-anchor" in built.stderr


def nav_pages(nav: object) -> list[str]:
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, list):
        return [page for entry in nav for page in nav_pages(entry)]
    if isinstance(nav, dict):
        return [page for value in nav.values() for page in nav_pages(value)]
    return []


def test_every_page_is_in_the_nav():
    config = yaml.unsafe_load((ROOT / "mkdocs.yml").read_text())
    in_nav = nav_pages(config["nav"])
    on_disk = sorted(str(path.relative_to(DOCS)) for path in DOCS.rglob("*.md"))
    assert sorted(in_nav) == on_disk
    assert len(in_nav) == len(set(in_nav))


def readme_links() -> list[tuple[str, str]]:
    """(page, anchor) of each README link into docs/."""
    text = README.read_text(encoding="utf-8")
    return [
        (page, anchor) for page, anchor in re.findall(r"\]\(docs/([^)#\s]+)(?:#([^)\s]+))?\)", text)
    ]


class _Ids(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.ids.update(value for name, value in attrs if name == "id" and value)


@pytest.mark.timeout(450)
def test_readme_links_resolve(site: Path):
    links = readme_links()
    assert links
    for page, anchor in links:
        assert (DOCS / page).is_file(), f"README links to docs/{page}, which does not exist"
        built = site / page.removesuffix(".md") / "index.html"
        if page == "index.md":
            built = site / "index.html"
        assert built.is_file(), f"docs/{page} was not built"
        if anchor:
            ids = _Ids()
            ids.feed(built.read_text(encoding="utf-8"))
            assert anchor in ids.ids, f"README links to docs/{page}#{anchor}: no such anchor"


def test_every_page_is_one_click_from_the_readme():
    linked = {page for page, _ in readme_links()}
    pages = {str(path.relative_to(DOCS)) for path in DOCS.rglob("*.md")} - {"index.md"}
    assert pages <= linked, f"pages the README does not link to: {sorted(pages - linked)}"


def test_the_readme_keeps_its_two_commands():
    """The set-up-and-run and the set-up-and-test commands; .ci/run runs the second verbatim."""
    text = README.read_text(encoding="utf-8")
    run = (
        "python3 -m venv .venv && .venv/bin/pip install -q -e . && "
        ".venv/bin/hyrel-send examples/square-tube.gcode"
    )
    test = (
        "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && "
        ".venv/bin/pip install -q --no-deps printrun==2.2.0 && .venv/bin/pytest"
    )
    assert f"```sh\n{run}\n```" in text
    assert f"```sh\n{test}\n```" in text
    assert test in (ROOT / ".ci" / "run").read_text()
    assert "mkdocs serve" in text
    assert len(text.splitlines()) <= 150


# --- the examples -----------------------------------------------------------------------


@pytest.fixture
def environment(tmp_path: Path) -> dict[str, str]:
    """No printer, no HYREL_* setting; history and configuration in a temporary folder."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HYREL_")}
    env.update(
        PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}",
        XDG_DATA_HOME=str(tmp_path / "data"),
        XDG_CONFIG_HOME=str(tmp_path / "config"),
        TMPDIR=str(tmp_path),
        NO_COLOR="1",
    )
    return env


def commands(code: str) -> list[str]:
    """The block's command lines, a trailing backslash joining a line to the next."""
    lines: list[str] = []
    pending = ""
    for raw in code.splitlines():
        line = pending + raw
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        pending = ""
        if line.strip() and not line.strip().startswith("#"):
            lines.append(line)
    return lines


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def run(
    argv: list[str], *, cwd: Path, env: dict[str, str], timeout: float, stdin: str | None = None
) -> subprocess.CompletedProcess[str]:
    """Run in a session of its own, so that whatever it started in the background goes too."""
    process = subprocess.Popen(
        argv,
        cwd=cwd,
        env=env,
        stdin=subprocess.PIPE if stdin is not None else subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = process.communicate(stdin, timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        out, err = process.communicate()
        pytest.fail(f"timed out after {timeout} s: {argv}\n{out[-3000:]}\n{err[-3000:]}")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(argv, process.returncode, out, err)


def check(result: subprocess.CompletedProcess[str], what: str) -> None:
    if result.returncode != 0:
        pytest.fail(
            f"{what}: exit {result.returncode}\n--- stdout\n{result.stdout[-3000:]}"
            f"\n--- stderr\n{result.stderr[-3000:]}"
        )


def run_example(example: Example, folder: Path, env: dict[str, str]) -> None:
    """Run one example; fail with its output when it does not succeed."""
    code = example.code
    job = str(ROOT / "examples" / "square-tube.gcode")
    if example.kind == "python":
        check(run([sys.executable, "-c", code], cwd=ROOT, env=env, timeout=180), str(example))
    elif example.kind == "shell":
        for line in commands(code):
            result = run(["bash", "-c", line], cwd=ROOT, env=env, timeout=120)
            check(result, f"{example}: {line}")
    elif example.kind == "script":
        (folder / "examples").symlink_to(ROOT / "examples")
        script = folder / "example.sh"
        port = str(free_port())
        script.write_text(
            "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null; wait' EXIT\n"
            + code.replace("8765", port)
        )
        check(run(["bash", str(script)], cwd=folder, env=env, timeout=240), str(example))
    elif example.kind == "pytest":
        test_file = folder / "test_example.py"
        test_file.write_text(code)
        argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test_file)]
        check(run([*argv, "--timeout=120"], cwd=folder, env=env, timeout=240), str(example))
    elif example.kind in ("loadout", "config"):
        settings = folder / f"{example.kind}.toml"
        settings.write_text(code)
        option = ["--loadout", str(settings), "--check"]
        if example.kind == "config":
            option = ["--config", str(settings), "--dry-run"]
        argv = [sys.executable, "-m", "repetrel_host.cli", job, *option]
        check(run(argv, cwd=ROOT, env=env, timeout=120), str(example))
    else:
        pytest.fail(f"{example}: no one runs examples of this kind")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("example", EXAMPLES, ids=str)
def test_the_example_runs(example: Example, tmp_path: Path, environment: dict[str, str]):
    run_example(example, tmp_path, environment)


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("kind", "code"),
    [
        ("python", "import repetrel_host as rh\nrh.connect('sim').no_such_method()\n"),
        ("shell", "hyrel-send examples/no-such-job.gcode --dry-run\n"),
        ("script", "hyrel-send examples/square-tube.gcode --dry-run --no-such-option\n"),
        (
            "pytest",
            "def test_it(hyrel_printer):\n    assert not hyrel_printer.command('M105').ok\n",
        ),
        ("loadout", 'machine = "hydra-16a"\n[[heads]]\nslot = 2\nhead = "NO-SUCH-HEAD"\n'),
        ("config", "[printer]\nno_such_key = 1\n"),
    ],
)
def test_a_wrong_example_fails(kind: str, code: str, tmp_path: Path, environment: dict[str, str]):
    """The runner is no rubber stamp: a wrong example of each kind fails its test."""
    with pytest.raises(pytest.fail.Exception):
        run_example(Example("wrong.md", 1, kind, code), tmp_path, environment)
