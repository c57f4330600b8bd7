"""The server's kept analyses: made in a worker process with the print time from the moves
beside the slicer's, read back whole after a restart, and made again when they were kept
by an older server (which had no time from the moves)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from repetrel_host.gcode.estimate import PlanSettings, estimate_file
from repetrel_host.server.analyses import Analyses
from repetrel_host.session.workers import stop_workers
from tests.support.paths import DATA


@pytest.mark.timeout(120)
def test_a_kept_analysis_carries_both_times_and_an_older_one_is_made_again(
    tmp_path: Path,
) -> None:
    root = tmp_path / "files"
    root.mkdir()
    cone = root / "cone.gcode"
    shutil.copy(DATA / "cone-prusaslicer.gcode", cone)
    bare = root / "bare.gcode"
    bare.write_text("G28\nG1 X10 Y10 F3000\nG1 X50 E2\n")  # moves, no time comment
    kept = tmp_path / "analysis"
    try:
        analyses = Analyses(kept, root)
        made = analyses.analyse(cone).summary  # in a worker process
        assert made is not None
        assert made.planned_seconds == estimate_file(cone).seconds
        assert made.slicer_seconds == 753
        assert made.planned_limits_from == "the file's slicer settings"
        without = analyses.analyse(bare).summary
        assert without is not None and without.slicer_seconds is None
        assert without.planned_seconds == estimate_file(bare).seconds

        # A restart reads them from the data folder, whole.
        restarted = Analyses(kept, root)
        assert restarted.cached(cone) == made
        assert restarted.cached(bare) == without

        # One kept by the server before the time from the moves: stale, so made again.
        (entry,) = [
            p for p in kept.glob("*.json") if json.loads(p.read_text())["file"] == "cone.gcode"
        ]
        older = json.loads(entry.read_text())
        older["format"] = 2
        entry.write_text(json.dumps(older))
        assert Analyses(kept, root).cached(cone) is None
    finally:
        stop_workers()


@pytest.mark.timeout(120)
def test_a_print_time_planned_for_another_printer_setting_is_planned_again(
    tmp_path: Path,
) -> None:
    """Planned before the printer's firmware answered (its profile a guess), or with another
    machine: the rest of the analysis stands, its print time is made again, as the printer
    plans now (and kept so across a restart)."""
    root = tmp_path / "files"
    root.mkdir()
    cone = root / "cone.gcode"
    shutil.copy(DATA / "cone-prusaslicer.gcode", cone)
    key = ["no firmware yet"]
    settings = {"no firmware yet": PlanSettings(), "hyrel": PlanSettings(hyrel=True)}

    def analyses() -> Analyses:
        made = Analyses(tmp_path / "analysis", root)
        made.plan_as, made.plan_key = (lambda path: settings[key[0]]), (lambda: key[0])
        return made

    try:
        first = analyses()
        guessed = first.analyse(cone).summary
        assert guessed is not None and guessed.planned_seconds is not None
        key[0] = "hyrel"  # the firmware answered: another plan
        stale = first.cached(cone)
        assert stale is not None and stale.planned_seconds is None and stale.layers > 0
        assert first.known(cone) == stale
        replanned = first.analyse(cone).summary  # as summary() has it made in the background
        assert replanned is not None and replanned.planned_seconds is not None
        assert replanned.planned_seconds != guessed.planned_seconds  # Hyrel's code chart
        assert analyses().cached(cone) == replanned  # kept for this setting
        key[0] = "no firmware yet"
        again = analyses().cached(cone)
        assert again is not None and again.planned_seconds is None
    finally:
        stop_workers()
