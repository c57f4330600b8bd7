"""Header injection, golden against the T addressing v5 page's examples."""

from pathlib import Path

import pytest

from repetrel_host.config import UserConfig, load_library, load_loadout, shipped_config_dir
from repetrel_host.session.header import format_number, header_commands
from tests.support.helpers import hyrel_send

# Copied by hand from "One Head Loaded" and "Two Heads Loaded".
WIKI_ONE_HEAD = """\
M6 T0 O1 X0 Y0 Z0
M721 S10000 E100 P-15 T0
M722 S10000 E100 P20 T0
M221 S1.0 T0 P77 W0.5 Z0.3
M728 T0 S0
"""
WIKI_TWO_HEADS = """\
M6 T1 O2 X0 Y0 Z0
M721 S10000 E100 P-15 T1
M722 S10000 E100 P20 T1
M221 S1.0 T1 P77 W0.5 Z0.3
M728 T1 S0
M6 T2 O3 X0 Y0 Z0
M721 S10000 E160 P-100 T2
M722 S10000 E200 P100 T2
M221 S1.0 T2 P81.0 W1.6 Z0.3
M728 T2 S0
"""
LOADOUTS = shipped_config_dir() / "loadouts"


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    ("loadout", "expected"),
    [("wiki-one-head.toml", WIKI_ONE_HEAD), ("wiki-two-heads.toml", WIKI_TWO_HEADS)],
)
def test_dry_run_prints_the_wiki_header_exactly(
    loadout: str, expected: str, tmp_path: Path
) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28 ; home\nG1 X10 Y10\n")
    result = hyrel_send(str(job), "--loadout", str(LOADOUTS / loadout), "--dry-run")
    assert result.returncode == 0, result.stderr
    assert result.stdout == expected + "G4 P1\nG28\nG1 X10 Y10\n"


@pytest.mark.timeout(30)
def test_dry_run_framed_shows_the_wire(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("T0\n")
    result = hyrel_send(
        str(job), "--loadout", str(LOADOUTS / "wiki-one-head.toml"), "--dry-run", "--framed"
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    # The greeting (M110, and a probe behind it: an M105 that runs), the header, the job,
    # the two probes that confirm it (XOR checksums worked by hand: "N9 M105" is 46).
    assert lines[:3] == ["N0 M110 N0*125", "N1 M105*38", "N2 M6 T0 O1 X0 Y0 Z0*118"]
    assert lines[-3:] == ["N8 T0*50", "N9 M105*46", "N10 M105*22"]


@pytest.mark.timeout(30)
def test_no_header(tmp_path: Path) -> None:
    job = tmp_path / "job.gcode"
    job.write_text("G28\n")
    result = hyrel_send(
        str(job), "--loadout", str(LOADOUTS / "wiki-one-head.toml"), "--dry-run", "--no-header"
    )
    assert result.stdout == "G28\n"


def test_header_origins_name_the_head() -> None:
    loadout = load_loadout(LOADOUTS / "wiki-two-heads.toml", load_library(UserConfig()))
    origins = {origin for _, origin in header_commands(loadout)}
    assert origins == {"header: head T1 (MK1-250)", "header: head T2 (SDS-05)", "header"}


@pytest.mark.parametrize(
    ("value", "text"),
    [
        (0, "0"),
        (-15, "-15"),
        (77, "77"),
        (1.0, "1.0"),
        (81.0, "81.0"),
        (0.5, "0.5"),
        (1e-05, "0.00001"),
        (2.5e20, "250000000000000000000.0"),
    ],
)
def test_numbers_print_as_the_reference_writes_them(value: float, text: str) -> None:
    assert format_number(value) == text
