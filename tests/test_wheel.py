"""The package as a user gets it: installed from the clone (not editable) into a venv of
its own by the very command Getting started gives (docs/getting-started.md, its
``<!-- test: install -->`` block, with a temporary folder for /opt/repetrel-host), every
module imported, and the programs run on the fake.

The editable install the other tests use finds any module under src/; the install holds
only what the wheel's build found, so a package left out of it shows here and nowhere else."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.support.doc_examples import DOCS, clone, examples_in, fresh_shell
from tests.support.paths import ROOT

SRC = ROOT / "src"
OPT = "/opt/repetrel-host"

# Import failures a base install (no extras) must give, and nothing else: the farm needs
# the [farm] extra, the pytest plugin the [hil] extra (with its one sentence).
WITHOUT_EXTRAS = {
    "repetrel_host.server.farm.api": "No module named 'psycopg'",
    "repetrel_host.server.farm.db": "No module named 'psycopg'",
    "repetrel_host.server.farm.node": "No module named 'psycopg'",
    "repetrel_host.pytest_plugin": "needs pytest: pip install -e '.[hil]' in repetrel-host's clone",
}

IMPORT_ALL = """
import importlib, pkgutil, sys
import repetrel_host
assert "/src/" not in repetrel_host.__file__, repetrel_host.__file__
failed = {}
for module in pkgutil.walk_packages(repetrel_host.__path__, "repetrel_host."):
    try:
        importlib.import_module(module.name)
    except Exception as exc:
        failed[module.name] = str(exc)
for name, why in sorted(failed.items()):
    print(f"{name}\\t{why}")
"""


def run(*command: str | Path, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(part) for part in command], cwd=cwd, env=env, capture_output=True, text=True,
        timeout=400,
    )  # fmt: skip


def the_install_command() -> str:
    """Getting started's install, which the systemd unit's comment repeats."""
    (example,) = [e for e in examples_in(DOCS / "getting-started.md") if e.kind == "install"]
    ((command, _),) = example.commands()
    unit = (ROOT / "contrib" / "hyrel-server.service").read_text()
    assert f"# {command}\n" in unit and f"ExecStart={OPT}/bin/hyrel-server " in unit
    return command


@pytest.mark.timeout(900)
@pytest.mark.slow
def test_the_install_from_the_clone_runs_in_a_fresh_venv(tmp_path: Path) -> None:
    folder, env = clone(tmp_path), fresh_shell(tmp_path)
    env.pop("PYTHONPATH", None)  # a user's shell: nothing but the install finds the package
    target = tmp_path / "opt"
    command = the_install_command().replace(OPT, str(target))
    installed = run("bash", "-c", command, cwd=folder, env=env)
    assert installed.returncode == 0, installed.stderr
    python, bin_dir = target / "bin" / "python", target / "bin"

    # Every module and data file of the package is installed: the wheel's RECORD.
    (record,) = target.glob("lib/python3*/site-packages/repetrel_host-*.dist-info/RECORD")
    names = {line.split(",")[0] for line in record.read_text().splitlines()}
    package = SRC / "repetrel_host"
    tree = {
        str(path.relative_to(SRC))
        for path in package.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert tree - names == set()
    modules = {name for name in names if name.endswith(".py")}
    assert modules - tree == set()  # and no module that the tree no longer has
    shipped = {  # the repository's config/, inside the package
        f"repetrel_host/shipped_config/{path.relative_to(ROOT / 'config')}"
        for path in (ROOT / "config").rglob("*.toml")
    }
    assert shipped and shipped - names == set()

    # Not even pytest: a print server does not install a test runner.
    assert run(python, "-c", "import pytest", cwd=tmp_path, env=env).returncode != 0
    imported = run(python, "-c", IMPORT_ALL, cwd=tmp_path, env=env)
    assert imported.returncode == 0, imported.stderr
    failed = dict(line.split("\t", 1) for line in imported.stdout.splitlines())
    assert set(failed) == set(WITHOUT_EXTRAS), failed
    for name, why in WITHOUT_EXTRAS.items():
        assert why in failed[name], (name, failed[name])

    job = ROOT / "examples" / "square-tube.gcode"
    sent = run(bin_dir / "hyrel-send", job, cwd=tmp_path, env=env)
    assert sent.returncode == 0, sent.stderr
    assert "square-tube.gcode: done: 334 lines" in sent.stdout
    with_loadout = run(
        bin_dir / "hyrel-send", job, "--loadout", "wiki-two-heads", cwd=tmp_path, env=env
    )
    assert with_loadout.returncode == 0, with_loadout.stderr
    for program in ("hyrel-server", "hyrel-fake-controller"):
        helped = run(bin_dir / program, "--help", cwd=tmp_path, env=env)
        assert helped.returncode == 0 and "usage" in helped.stdout.lower(), helped.stderr
    farm = run(
        bin_dir / "hyrel-server", "--printer", "a1=fake", "--data-dir", tmp_path / "data",
        "--farm", "postgresql://farm@localhost/farm", cwd=tmp_path, env=env,
    )  # fmt: skip
    assert farm.returncode != 0
    assert (
        "--farm needs PostgreSQL's client: pip install -e '.[farm]' in repetrel-host's clone"
        in farm.stderr
    )

    # An extra, as Getting started adds one (in brackets, from the clone): with [hil], the
    # plugin loads and runs a lab's test on the fake.
    extra = run(bin_dir / "pip", "install", "-q", ".[hil]", cwd=folder, env=env)
    assert extra.returncode == 0, extra.stderr
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "test_rig.py").write_text(
        "def test_rig(hyrel_printer, hyrel_controller):\n"
        "    assert hyrel_printer.command('M105').ok\n"
        "    assert hyrel_controller.executed == ['M105']\n"
    )
    tested = run(
        python, "-m", "pytest", "-q", "-p", "no:cacheprovider", cwd=tmp_path / "lab", env=env
    )
    assert tested.returncode == 0, tested.stdout + tested.stderr
    assert "1 passed" in tested.stdout
