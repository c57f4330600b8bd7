"""The documentation site: it builds with ``mkdocs build --strict`` (a broken link, anchor
or snippet, a page left out of the nav, a docstring that does not render fails it), every
page in docs/ is in the nav and one click from the README, the README's links land on a
page and an anchor that exist, and the pages' commands run as written.

An example runs when a marker comment stands on the line before its fence::

    <!-- test: python -->    the block runs as a Python script (from the repository's root)
    <!-- test: shell -->     each command line runs in bash and must exit 0
    <!-- test: script -->    the block runs as one bash script; its background processes
                             are stopped after it
    <!-- test: daemon -->    one command that runs until it is stopped: it must answer HTTP
                             on the 127.0.0.1 address it names or, naming none, print a
                             line; then Ctrl-C (SIGINT), as a reader stops it, and it must
                             exit 0 or 130 (Ctrl-C's own) without a traceback
    <!-- test: farm -->      a script with a throwaway PostgreSQL (tests/support/pg.py) as
                             its database: postgresql://farm@localhost/hyrel_farm and
                             PGPASSWORD=secret become that cluster's (skipped without one)
    <!-- test: pytest -->    the block is a test file, run by pytest (the hyrel plugin)
    <!-- test: loadout -->   a loadout file: hyrel-send --check of the example job with it
    <!-- test: config -->    a configuration file: hyrel-send --dry-run of the example job
    <!-- test: install -->   the install from the clone: tests/test_wheel.py runs it, with a
                             temporary folder for /opt/repetrel-host

Shell, script, daemon and farm examples run as a reader runs them in a new shell: in a
clone (the repository's files, linked, and its ``.venv``, which is the venv the tests run
in, as the README's set-up makes it), with no venv on PATH, so that ``hyrel-send`` and the
venv's other programs are not found. The docs' one convention: a page that gives commands
says ``. .venv/bin/activate`` before the first (the README and Getting started as a step,
the other pages in a sentence), and from there on its examples run with the venv
activated. The ports 8765, 8766 and 8000 become free ones. The print history,
configuration and temporary files are in a temporary folder. Nothing needs a printer.

A shell block (sh, bash, console) without a marker needs what no test has: UNRUN lists
each with why (a printer, sudo, a database's host, minutes...). A lint over every shell
block makes sure that none runs a program of the venv before its page activated it.
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
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from tests.support.doc_examples import (
    ACTIVATE,
    BIN,
    DOCS,
    README,
    SHELLS,
    Fence,
    clone,
    examples_in,
    fences,
    fresh_shell,
    markdown_files,
)
from tests.support.paths import ROOT
from tests.support.pg import PASSWORD

_ANY_MARKER = re.compile(r"<!-- test: (\w+) -->")
MKDOCS_BUILD = [sys.executable, "-m", "mkdocs", "build", "--strict"]
KINDS = {"python", "shell", "script", "daemon", "farm", "pytest", "loadout", "config", "install"}
EXAMPLES = [example for path in markdown_files() for example in examples_in(path)]
RUN_HERE = [example for example in EXAMPLES if example.kind != "install"]  # test_wheel's
# A pytest run, a PostgreSQL farm or a long-running program take seconds each: run with --slow.
HEAVY_KINDS = {"pytest", "farm", "daemon"}


def slow_if_heavy(example: Fence) -> Any:
    """The example as a test case, marked slow when its kind is heavy (or it runs pytest)."""
    heavy = example.kind in HEAVY_KINDS or "pytest" in example.code
    return pytest.param(example, marks=pytest.mark.slow) if heavy else example


def test_every_marker_is_an_example_of_a_known_kind() -> None:
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
@pytest.mark.slow
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
@pytest.mark.slow
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
    return fresh_shell(tmp_path)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def free_ports(code: str) -> str:
    """The docs' servers' ports, each a free one: a server on them here, or another test's,
    does not get in the way."""
    for port in ("8765", "8766", "8000"):
        code = re.sub(rf"(?<!\d){port}(?!\d)", str(free_port()), code)
    return code


def activation(activated: bool) -> str:
    return f"{ACTIVATE}\n" if activated else ""


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


def run_script(example: Fence, code: str, folder: Path, env: dict[str, str]) -> None:
    script = folder / "example.sh"
    script.write_text(
        activation(example.activated)
        + "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null; wait' EXIT\n"
        + free_ports(code)
    )
    check(run(["bash", str(script)], cwd=folder, env=env, timeout=240), str(example))


def answers(address: str | None, log: Path) -> bool:
    """Ready: answering HTTP at ``address`` (any status: 403 is an answer), or without one,
    having said something."""
    if address is None:
        return log.stat().st_size > 0
    try:
        httpx.get(f"http://{address}/", timeout=2)
    except httpx.TransportError:
        return False
    return True


def run_daemon(example: Fence, folder: Path, env: dict[str, str]) -> None:
    (command, activated), *more = example.commands()
    assert not more, f"{example}: a daemon example is one command"
    command = free_ports(command)
    address = re.search(r"127\.0\.0\.1:\d+", command)
    log = folder / "daemon.log"
    with log.open("w") as sink:
        process = subprocess.Popen(
            ["bash", "-c", activation(activated) + command],
            cwd=folder, env=env, stdin=subprocess.DEVNULL, stdout=sink,
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not answers(address[0] if address else None, log):
            if process.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"{example}: not ready, exit {process.poll()}\n{log.read_text()}")
            time.sleep(0.2)
        time.sleep(1)  # and it keeps running
        if process.poll() is not None:
            pytest.fail(f"{example}: ended by itself, exit {process.poll()}\n{log.read_text()}")
        os.killpg(process.pid, signal.SIGINT)  # Ctrl-C, as at the reader's terminal
        code = process.wait(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    output = log.read_text()
    if code not in (0, 130) or "Traceback" in output:
        pytest.fail(f"{example}: after Ctrl-C, exit {code}\n{output[-3000:]}")


def run_example(
    example: Fence, folder: Path, env: dict[str, str], database: str | None = None
) -> None:
    """Run one example; fail with its output when it does not succeed."""
    code = example.code
    job = str(ROOT / "examples" / "square-tube.gcode")
    if example.kind == "python":
        check(run([sys.executable, "-c", code], cwd=ROOT, env=env, timeout=180), str(example))
    elif example.kind == "shell":
        for line, activated in example.commands():
            result = run(["bash", "-c", activation(activated) + line], cwd=folder, env=env,
                         timeout=120)  # fmt: skip
            check(result, f"{example}: {line}")
    elif example.kind == "script":
        run_script(example, code, folder, env)
    elif example.kind == "farm":
        assert database is not None
        url, password = "postgresql://farm@localhost/hyrel_farm", "PGPASSWORD=secret"
        assert url in code and password in code, f"{example}: give {url} and {password}"
        code = code.replace(url, database).replace(password, f"PGPASSWORD={PASSWORD}")
        run_script(example, code, folder, env)
    elif example.kind == "daemon":
        run_daemon(example, folder, env)
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
        pytest.fail(f"{example}: no one runs examples of this kind here")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("example", [slow_if_heavy(example) for example in RUN_HERE], ids=str)
def test_the_example_runs(
    example: Fence, tmp_path: Path, environment: dict[str, str], request: pytest.FixtureRequest
) -> None:
    database = request.getfixturevalue("farm_db") if example.kind == "farm" else None
    run_example(example, clone(tmp_path), environment, database)


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("kind", "code", "activated"),
    [
        ("python", "import repetrel_host as rh\nrh.connect('sim').no_such_method()\n", True),
        ("shell", "hyrel-send examples/no-such-job.gcode --dry-run\n", True),
        ("shell", "hyrel-send examples/square-tube.gcode --dry-run\n", False),  # not found
        ("script", "hyrel-send examples/square-tube.gcode --dry-run --no-such-option\n", True),
        ("script", "hyrel-send examples/square-tube.gcode --dry-run\n", False),
        ("daemon", "hyrel-server --data-dir data --printer a=fake --no-such-option\n", True),
        ("daemon", "echo ready && sleep 600\n", True),  # killed by Ctrl-C: no clean exit
        ("daemon", "echo ready\n", True),  # it does not run until stopped
        ("daemon", "hyrel-server --data-dir data --printer a=fake\n", False),
        pytest.param(
            "pytest",
            "def test_it(hyrel_printer):\n    assert not hyrel_printer.command('M105').ok\n",
            True,
            marks=pytest.mark.slow,
        ),
        ("loadout", 'machine = "hydra-16a"\n[[heads]]\nslot = 2\nhead = "NO-SUCH-HEAD"\n', True),
        ("config", "[printer]\nno_such_key = 1\n", True),
    ],
)
def test_a_wrong_example_fails(
    kind: str, code: str, activated: bool, tmp_path: Path, environment: dict[str, str]
) -> None:
    """The runner is no rubber stamp: a wrong example of each kind fails its test, and so
    does a command of the venv on a page that did not activate it."""
    lang = "sh" if kind in ("shell", "script", "daemon") else "text"
    example = Fence("wrong.md", 1, lang, kind, code, activated)
    with pytest.raises(pytest.fail.Exception):
        run_example(example, clone(tmp_path), environment)


# --- the shell blocks no test runs ------------------------------------------------------

# Each shell block no test runs: its page, how it starts, and what it needs that no test has.
# fmt: off
UNRUN = [
    ("README.md", "python3 -m venv .venv && .venv/bin/pip install -q -e . ", "the set-up itself"),
    ("README.md", "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]'",
     "the set-up and the whole test run (.ci/run runs it verbatim)"),
    ("README.md", "hyrel-send part.gcode --port /dev/ttyUSB0", "a printer"),
    ("docs/getting-started.md", "python3 -m venv .venv && .venv/bin/pip install -q -e . ",
     "the set-up itself"),
    ("docs/getting-started.md", "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]'",
     "the set-up and the whole test run"),
    ("docs/getting-started.md", "hyrel-send examples/square-tube.gcode --port /dev/ttyUSB0",
     "a printer"),
    ("docs/streaming.md", "hyrel-send JOB --port /dev/ttyUSB0", "a printer"),
    ("docs/streaming.md", "$ hyrel-send part.gcode --port /dev/ttyUSB0", "a printer"),
    ("docs/console.md", "$ hyrel-send --console --port /dev/ttyUSB0", "a printer"),
    ("docs/hyrel-jobs.md", "hyrel-send job.gcode --loadout wiki-two-heads --port /dev/ttyACM0",
     "a printer"),
    ("docs/pytest-plugin.md", "pytest examples/hil --hyrel-port=/dev/ttyUSB0", "a printer"),
    ("docs/pytest-plugin.md", "pip install -e '.[hil]'",
     "it changes the venv the tests run in (tests/test_wheel.py installs an extra)"),
    ("docs/farm.md", "pip install -e '.[farm]'",
     "it changes the venv the tests run in (tests/test_wheel.py installs an extra)"),
    ("docs/farm.md", "sudo -u postgres createuser -P farm",
     "sudo on a database's host, and printers (the farm example runs the same on fakes)"),
    ("docs/farm.md", "hyrel-send part.gcode --server http://NODE-A:8765 --farm",
     "a farm's nodes (the farm example runs the same on fakes)"),
    ("docs/server.md", "hyrel-send part.gcode --server 127.0.0.1:8765",
     "the page's first example's server, running, with jobs"),
    ("docs/benchmarks.md", "pip install -q --no-deps printrun==2.2.0",
     "minutes (tests/test_bench.py runs each benchmark on small inputs)"),
    ("docs/exactly-once.md", "python bench/soak.py",
     "minutes (tests/protocol/test_soak.py streams 20,000 lines on every run)"),
    ("bench/README.md", "pip install -q --no-deps printrun==2.2.0", "minutes"),
    ("bench/README.md", "python bench/run.py --no-big", "minutes"),
    ("bench/README.md", "python3 -m venv /tmp/octo-venv", "OctoPrint, and minutes"),
    ("bench/README.md", "python bench/server.py --socket-clients 10 --repeat 5", "minutes"),
    ("bench/README.md", "python bench/server.py --socket-clients 10 --moonraker", "minutes"),
]
# fmt: on

SHELL_FENCES = [
    fence for path in markdown_files() for fence in fences(path) if fence.lang in SHELLS
]


def unrun_entry(fence: Fence) -> int | None:
    """Its entry in UNRUN, by index."""
    first = fence.code.lstrip().splitlines()[0]
    found = [
        i
        for i, (page, start, _) in enumerate(UNRUN)
        if (page, start) == (fence.page, first[: len(start)])
    ]
    return found[0] if found else None


def test_every_shell_block_runs_or_says_why_not() -> None:
    """A shell block a test could run is marked to run; UNRUN names each of the others
    once, and nothing that is no longer there."""
    unmarked = [fence for fence in SHELL_FENCES if fence.kind is None]
    missing = [str(fence) for fence in unmarked if unrun_entry(fence) is None]
    assert not missing, f"shell blocks neither marked nor in UNRUN: {missing}"
    found = sorted(i for fence in unmarked if (i := unrun_entry(fence)) is not None)
    assert found == list(range(len(UNRUN))), "UNRUN names a block twice, or one not there"


_KEYWORDS = {"until", "while", "if", "then", "do", "else", "!", "time", "exec", "done", "fi"}
# The venv's programs: what its set-up installs (python3 aside, which makes the venv), and
# the package's own even before it is installed.
VENV_PROGRAMS = {
    path.name for path in BIN.iterdir() if not re.fullmatch(r"python3(\.\d+)?", path.name)
} | {"hyrel-send", "hyrel-server", "hyrel-fake-controller"}


def programs(command: str) -> list[str]:
    """The programs a command line runs: the first word of each of its commands."""
    bare = re.sub(r"'[^']*'|\"[^\"]*\"", "''", command.split(" #")[0])  # quotes, comment
    names = []
    for part in re.split(r"&&|\|\||[|;&`]|\$\(", bare):
        words = part.split()
        while words and (re.fullmatch(r"\w+=\S*", words[0]) or words[0] in _KEYWORDS):
            words.pop(0)  # VAR=value, until, do...
        if words:
            names.append(words[0].strip(")"))
    return names


def not_found(fence: Fence) -> list[str]:
    """Its commands that run a program of the venv before the page activated it."""
    return [
        f"{fence.page}:{fence.line}: {name} ({line.strip()})"
        for line, activated in fence.commands()
        for name in programs(line)
        if name in VENV_PROGRAMS and not activated
    ]


def test_no_shell_block_runs_a_program_of_the_venv_before_its_page_activates_it() -> None:
    """In a new shell, hyrel-send, pytest, mkdocs, pip, python are not the venv's (or not
    there): the page says ``. .venv/bin/activate`` first, or the command names .venv/bin/."""
    wrong = [line for fence in SHELL_FENCES for line in not_found(fence)]
    assert not wrong, "run before the page says '. .venv/bin/activate':\n" + "\n".join(wrong)


def test_the_lint_finds_the_venvs_programs_in_a_command_line() -> None:
    line = "PGPASSWORD=x hyrel-server --a 'b | c' && until grep -q x; do pytest; done # mkdocs"
    assert programs(line) == ["hyrel-server", "grep", "pytest"]
    code = "cat > a.toml <<'EOF'\npytest = 1\nEOF\n$(python -V) && .venv/bin/pip -V\n"
    assert not_found(Fence("a.md", 1, "sh", None, code, False)) == [
        "a.md:1: python ($(python -V) && .venv/bin/pip -V)"
    ]
    transcript = "$ mkdocs serve\nhyrel-send is output\n$ . .venv/bin/activate\n$ mkdocs serve\n"
    assert len(not_found(Fence("a.md", 1, "console", None, transcript, False))) == 1
    assert not_found(Fence("a.md", 1, "sh", None, "hyrel-send a\n", True)) == []
