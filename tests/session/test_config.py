"""Configuration: shipped files load; every mistake is one sentence naming file and field."""

from pathlib import Path

import pytest

from repetrel_host.config import (
    Library,
    UserConfig,
    find_loadout,
    load_library,
    load_loadout,
    load_user_config,
    shipped_config_dir,
)
from repetrel_host.errors import ConfigError


@pytest.fixture
def library() -> Library:
    return load_library(UserConfig())


def write(tmp_path: Path, text: str, name: str = "loadout.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_shipped_machines_cover_the_reference_models(library: Library) -> None:
    machines = library.machines
    assert machines["hydra-16a"].slots_per_yoke == 5
    assert machines["hydra-16a-dual"].yokes == 2
    assert machines["ehr"].slots_per_yoke == 5
    assert machines["esr"].slots_per_yoke == 4
    assert machines["30m"].slots_per_yoke == 4
    assert machines["hydra-16a-v4"].firmware == "v4"
    assert set(library.heads) >= {"MK1-250", "SDS-05"}


def test_every_shipped_machine_and_head_is_valid(library: Library) -> None:
    # Read when a job names them: each must still be valid.
    assert all(library.machines[name].yokes >= 1 for name in library.machines)
    assert all(library.heads[name].flow.multiplier > 0 for name in library.heads)
    assert library.machines["marlin"].family == "marlin"
    assert library.machines["hyrel"].family == "hyrel"


def test_loadout_resolves_positions_registers_and_overrides(
    library: Library, tmp_path: Path
) -> None:
    path = write(
        tmp_path,
        """
        machine = "hydra-16a-dual"
        [[heads]]
        yoke = 2
        slot = 1
        head = "SDS-05"
        offset = { x = 12.5, y = -3, z = 0, a = 1 }
        flow = { width = 1.2 }
        [[heads]]
        slot = 5
        head = "MK1-250"
        offset_register = 9
        current_boost = 2
        """,
    )
    loadout = load_loadout(path, library)
    first, second = loadout.heads  # in slot order
    assert (first.yoke, first.slot, first.tool, first.register) == (1, 5, 4, 9)
    assert first.head.current_boost == 2
    assert (second.tool, second.variable, second.register) == (5, 5, 6)
    assert second.head.flow.width == 1.2
    assert second.head.flow.pulses_per_ul == 81.0  # the rest comes from the library
    assert second.offset.a == 1
    assert loadout.loaded_tools == {4, 5}


def test_v4_loadout_uses_t11_to_t15(library: Library, tmp_path: Path) -> None:
    path = write(tmp_path, 'machine = "hydra-16a-v4"\n[[heads]]\nslot = 2\nhead = "MK1-250"\n')
    (head,) = load_loadout(path, library).heads
    assert (head.tool, head.variable) == (1, 12)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('machine = "hydra-99"\n', ["machine", "hydra-99", "known:", "hydra-16a"]),
        ('machine = "esr"\n[[heads]]\nslot = 5\nhead = "MK1-250"\n', ["slot 5", "esr"]),
        ('machine = "esr"\n[[heads]]\nslot = 1\nhead = "MK9"\n', ["unknown head 'MK9'", "SDS-05"]),
        (
            'machine = "esr"\n[[heads]]\nslot = 1\nhead = "MK1-250"\n'
            '[[heads]]\nslot = 1\nhead = "SDS-05"\n',
            ["heads #2", "loaded twice"],
        ),
        (
            'machine = "esr"\n[[heads]]\nslot = 1\nhead = "MK1-250"\nofset = {}\n',
            ["heads.ofset", "unknown field", "allowed:", "offset"],
        ),
        (
            'machine = "esr"\n[[heads]]\nslot = 1\nhead = "MK1-250"\nflow = { width = "wide" }\n',
            ["heads #1", "flow.width"],
        ),
        ('machine = "esr"\n[[heads]]\nhead = "MK1-250"\n', ["heads.slot", "missing"]),
        ("machine = \n", ["not valid TOML"]),
    ],
)
def test_loadout_errors_name_file_field_and_choices(
    library: Library, tmp_path: Path, text: str, words: list[str]
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as error:
        load_loadout(path, library)
    message = str(error.value)
    assert message.startswith(str(path))
    for word in words:
        assert word in message


def test_machine_firmware_must_be_v4_or_v5(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        '[machines.mine]\nyokes = 1\nslots_per_yoke = 4\nfirmware = "v6"\n',
        "config.toml",
    )
    user = load_user_config(path)
    with pytest.raises(
        ConfigError, match=r"machines\.mine\.firmware: Input should be 'v4' or 'v5'"
    ):
        load_library(user)


def test_user_config_adds_heads_and_machines(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
        [printer]
        port = "/dev/ttyACM0"
        [host]
        allow_shell = true
        [machines.lab-esr]
        yokes = 1
        slots_per_yoke = 4
        firmware = "v5"
        [heads.KR2-15]
        unprime = { speed = 10000, pulses = 50, time = -10 }
        prime = { speed = 10000, pulses = 50, time = 10 }
        flow = { multiplier = 0.9, pulses_per_ul = 300, width = 0.25, layer = 0.1 }
        """,
        "config.toml",
    )
    user = load_user_config(path)
    library = load_library(user)
    assert user.printer.port == "/dev/ttyACM0"
    assert user.host.allow_shell
    assert library.machines["lab-esr"].slots_per_yoke == 4
    assert library.heads["KR2-15"].flow.multiplier == 0.9
    assert "MK1-250" in library.heads


def test_per_user_config_is_found_and_missing_one_is_fine(
    private_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert load_user_config(None) == UserConfig()
    folder = private_home / "config-home" / "repetrel-host"
    folder.mkdir(parents=True)
    (folder / "config.toml").write_text('[printer]\nmachine = "esr"\n')
    assert load_user_config(None).printer.machine == "esr"


def test_missing_explicit_config_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_user_config(tmp_path / "nope.toml")


def test_loadouts_by_name() -> None:
    assert (
        find_loadout(Path("wiki-one-head"))
        == shipped_config_dir() / "loadouts" / "wiki-one-head.toml"
    )
    assert find_loadout(Path("elsewhere/x.toml")) == Path("elsewhere/x.toml")


def test_a_mistyped_loadout_name_lists_the_known_ones() -> None:
    with pytest.raises(ConfigError, match="wiki-one-head, wiki-two-heads") as error:
        find_loadout(Path("wiki-one-haed"))
    assert "no such loadout" in str(error.value)


def test_a_machines_limits_are_the_print_times_and_say_where_they_come_from(
    tmp_path: Path, library: Library
) -> None:
    # No shipped Hyrel profile has figures (Hyrel publishes none): Marlin's defaults.
    assert library.machines["hydra-16a"].planner_limits().source == "Marlin's defaults"
    path = write(
        tmp_path,
        """
        [machines.lab-16a]
        yokes = 1
        slots_per_yoke = 5
        firmware = "v5"
        [machines.lab-16a.limits]
        source = "our Repetrel settings"
        max_feedrate = { X = 150 }
        junction_deviation = 0.05
        rapid = { X = 6000 }
        heat_rates = { bed = 0.25 }
        tool_change = 3
        """,
        "config.toml",
    )
    limits = load_library(load_user_config(path)).machines["lab-16a"].planner_limits()
    assert limits.source == "the machine profile (our Repetrel settings)"
    assert limits.max_feedrate["X"] == 150 and limits.max_feedrate["Y"] == 300  # Marlin's
    assert limits.rapid == {"X": 100.0}  # mm/min in the file, mm/s inside
    assert limits.heat_rates == {"hotend": 2.0, "bed": 0.25, "chamber": 0.1}
    assert (limits.junction_deviation, limits.tool_change) == (0.05, 3)
    bad = write(tmp_path, path.read_text().replace("X = 150", "X = 0"), "bad.toml")
    with pytest.raises(ConfigError, match=r"machines\.lab-16a\.limits\.max_feedrate\.X"):
        load_library(load_user_config(bad))
    unsourced = write(tmp_path, path.read_text().replace('source = "our Repetrel settings"', ""))
    with pytest.raises(ConfigError, match=r"limits\.source"):
        load_library(load_user_config(unsourced))
