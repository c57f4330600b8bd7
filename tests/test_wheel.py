"""The package as a user gets it: the wheel built from this tree, installed (not editable)
in a fresh virtualenv, every module imported, and the programs run on the fake.

The editable install the other tests use finds any module under src/; a wheel holds only
what the build found, so a package left out of it shows here and nowhere else."""

from __future__ import annotations

import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"

# Import failures a base install (no extras) must give, and nothing else: the farm needs
# the [farm] extra, the pytest plugin the [hil] extra (with its one sentence).
WITHOUT_EXTRAS = {
    "repetrel_host.server.farm.api": "No module named 'psycopg'",
    "repetrel_host.server.farm.db": "No module named 'psycopg'",
    "repetrel_host.server.farm.node": "No module named 'psycopg'",
    "repetrel_host.pytest_plugin": "needs pytest: pip install 'repetrel-host[hil]'",
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


def run(*command: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(part) for part in command], cwd=cwd, capture_output=True, text=True, timeout=400
    )


@pytest.mark.timeout(900)
def test_the_wheel_installs_and_runs_in_a_fresh_virtualenv(tmp_path: Path) -> None:
    built = run(
        sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp_path / "dist", ROOT,
        cwd=tmp_path,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr
    (wheel,) = (tmp_path / "dist").glob("repetrel_host-*.whl")

    # Every module and data file of the package is in the wheel.
    names = set(zipfile.ZipFile(wheel).namelist())
    package = SRC / "repetrel_host"
    tree = {
        str(path.relative_to(SRC))
        for path in package.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert tree - names == set()
    shipped = {  # the repository's config/, in the wheel inside the package
        f"repetrel_host/shipped_config/{path.relative_to(ROOT / 'config')}"
        for path in (ROOT / "config").rglob("*.toml")
    }
    assert shipped and shipped - names == set()

    env = tmp_path / "env"
    venv.create(env, with_pip=True)
    python, bin_dir = env / "bin" / "python", env / "bin"
    installed = run(python, "-m", "pip", "install", "-q", wheel, cwd=tmp_path)
    assert installed.returncode == 0, installed.stderr

    # Not even pytest: a print server does not install a test runner.
    assert run(python, "-c", "import pytest", cwd=tmp_path).returncode != 0
    imported = run(python, "-c", IMPORT_ALL, cwd=tmp_path)
    assert imported.returncode == 0, imported.stderr
    failed = dict(line.split("\t", 1) for line in imported.stdout.splitlines())
    assert set(failed) == set(WITHOUT_EXTRAS), failed
    for name, why in WITHOUT_EXTRAS.items():
        assert why in failed[name], (name, failed[name])

    job = ROOT / "examples" / "square-tube.gcode"
    sent = run(bin_dir / "hyrel-send", job, cwd=tmp_path)
    assert sent.returncode == 0, sent.stderr
    assert "square-tube.gcode: done: 334 lines" in sent.stdout
    with_loadout = run(bin_dir / "hyrel-send", job, "--loadout", "wiki-two-heads", cwd=tmp_path)
    assert with_loadout.returncode == 0, with_loadout.stderr
    for program in ("hyrel-server", "hyrel-fake-controller"):
        helped = run(bin_dir / program, "--help", cwd=tmp_path)
        assert helped.returncode == 0 and "usage" in helped.stdout.lower(), helped.stderr
    farm = run(
        bin_dir / "hyrel-server", "--printer", "a1=fake", "--data-dir", tmp_path / "data",
        "--farm", "postgresql://farm@localhost/farm", cwd=tmp_path,
    )  # fmt: skip
    assert farm.returncode != 0
    assert "--farm needs PostgreSQL's client: pip install 'repetrel-host[farm]'" in farm.stderr

    # With the [hil] extra, the plugin loads and runs a lab's test on the fake.
    extra = run(python, "-m", "pip", "install", "-q", f"{wheel}[hil]", cwd=tmp_path)
    assert extra.returncode == 0, extra.stderr
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "test_rig.py").write_text(
        "def test_rig(hyrel_printer, hyrel_controller):\n"
        "    assert hyrel_printer.command('M105').ok\n"
        "    assert hyrel_controller.executed == ['M105']\n"
    )
    tested = run(python, "-m", "pytest", "-q", "-p", "no:cacheprovider", cwd=tmp_path / "lab")
    assert tested.returncode == 0, tested.stdout + tested.stderr
    assert "1 passed" in tested.stdout
