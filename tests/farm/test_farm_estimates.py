"""The pace a farm job's estimate is listed at: the printer's that prints it, else the
printers' that could take it, else the plan's."""

from __future__ import annotations

from typing import Any

import pytest

from repetrel_host.server.farm import needs
from repetrel_host.server.farm.estimates import PLAN, PRINTER, PRINTERS, Paces, pace_of


def printer(name: str, pace: float | None, material: str = "PLA", lost: bool = False) -> Any:
    heads = [{"tool": 0, "slot": 1, "head": "MK1-250", "material": material, "nozzle": 0.5}]
    caps = needs.capabilities(name, "n", "hydra-16a", "reprap", heads)
    return {"node": "n-id", "name": name, "caps": caps, "pace": pace, "lost": lost}


def job(wants: list[str], on: str | None = None, refused: tuple[str, ...] = ()) -> Any:
    return {
        "node": "n-id" if on else None,
        "printer": on,
        "needs": needs.parse(wants),
        "refused": {key: "its lint refused it" for key in refused},
    }


FARM = [
    printer("fast", 0.2),
    printer("slow", 0.8),
    printer("new", None),
    printer("abs", 0.4, "ABS"),
    printer("gone", 0.1, lost=True),
]


def test_a_queued_job_takes_the_median_pace_of_the_printers_that_could_take_it() -> None:
    # fast, slow and new (the plan's 1) can print PLA; abs cannot, gone's node is lost.
    assert pace_of(job(["material=PLA"]), FARM) == (0.8, PRINTERS)
    assert pace_of(job([]), FARM) == (pytest.approx(0.6), PRINTERS)  # abs too: 0.2 0.4 0.8 1
    # One that gave it back does not count.
    assert pace_of(job(["material=PLA"], refused=("n-id/slow",)), FARM) == (0.6, PRINTERS)


def test_a_job_for_one_printer_or_on_one_takes_its_pace_and_a_new_one_the_plan() -> None:
    assert pace_of(job(["printer=fast"]), FARM) == (0.2, PRINTER)
    assert pace_of(job(["material=ABS"]), FARM) == (0.4, PRINTER)
    assert pace_of(job(["material=PLA"], on="slow"), FARM) == (0.8, PRINTER)
    assert pace_of(job([], on="gone"), FARM) == (0.1, PRINTER)  # what it ran on, lost or not
    assert pace_of(job(["printer=new"]), FARM) == (1.0, PLAN)
    assert pace_of(job([], on="new"), FARM) == (1.0, PLAN)
    assert pace_of(job(["material=PETG"]), FARM) == (1.0, PLAN)  # none can take it now
    assert pace_of(job([], on="forgotten"), FARM) == (1.0, PLAN)


def test_a_listing_matches_alike_jobs_once_and_tells_each_its_own() -> None:
    paces = Paces(FARM)
    assert paces.of(job(["material=PLA"])) == (0.8, PRINTERS)
    assert paces.of(job(["material=PLA"])) == (0.8, PRINTERS)
    assert paces.of(job(["material=PLA"], on="fast")) == (0.2, PRINTER)
    assert paces.of(job(["material=PLA"], refused=("n-id/slow",))) == (0.6, PRINTERS)


def test_a_listed_estimate_scales_the_moves_and_keeps_the_heat_waits_as_planned() -> None:
    from repetrel_host.server.farm.api import _times

    queued = {**job([], on="fast"), "estimated_time": 600.0, "expected_end": None}
    heated = _times({**queued, "estimated_heating": 100.0}, Paces(FARM))
    assert heated["estimated_time"] == pytest.approx(500 * 0.2 + 100)  # fast's pace: 0.2
    assert heated["planned_time"] == 600.0
    unknown = _times({**queued, "estimated_heating": None}, Paces(FARM))  # planned before
    assert unknown["estimated_time"] == pytest.approx(600 * 0.2)
