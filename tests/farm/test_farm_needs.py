"""What a printer offers the farm's requirements: the heads of its loadout, and nothing
without one."""

from __future__ import annotations

from pathlib import Path

from repetrel_host.config import UserConfig, find_loadout, load_library, load_loadout
from repetrel_host.server.farm import needs


def offers(loadout_name: str | None) -> needs.Document:
    """A printer's capabilities with that shipped loadout, as its node makes them."""
    heads = []
    machine = None
    if loadout_name is not None:
        loadout = load_loadout(find_loadout(Path(loadout_name)), load_library(UserConfig()))
        machine = loadout.machine_name
        heads = [
            {"tool": h.tool, "slot": h.slot, "head": h.name, "material": h.material,
             "nozzle": h.nozzle}
            for h in loadout.heads
        ]  # fmt: skip
    return needs.capabilities("left", "a", machine, "reprap", heads)


def test_a_fake_with_a_shipped_loadout_takes_what_the_farm_page_asks_for() -> None:
    """docs/farm.md gives its fake printers wiki-one-head and asks for material=PLA (its
    example runs in tests/test_docs.py where PostgreSQL is installed)."""
    pla = needs.parse(["material=PLA"])
    for name in ("wiki-one-head", "wiki-two-heads"):
        assert needs.missing(offers(name), pla) == [], name
        assert needs.missing(offers(name), needs.parse(["head=MK1-250"])) == []
    assert needs.missing(offers("wiki-one-head"), needs.parse(["T0.material=pla"])) == []
    assert needs.missing(offers(None), pla) == ["no material PLA"]  # a fake without one
