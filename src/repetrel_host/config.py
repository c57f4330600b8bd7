"""Configuration: machine profiles, the head library, loadouts and user settings (TOML).

Shipped files live in the repository's ``config/`` (``machines.toml``, ``heads.toml``,
``loadouts/``).
A user's ``config.toml`` (``--config FILE``, else ``$XDG_CONFIG_HOME/repetrel-host/``)
may add or replace machines and heads under ``[machines.NAME]`` and ``[heads.NAME]``,
and holds ``[printer]`` and ``[host]`` settings. Every error names the file, the
field and what is allowed.
"""

from __future__ import annotations

import os
import shlex
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    ValidationError,
)

from repetrel_host.errors import ConfigError
from repetrel_host.gcode import addressing
from repetrel_host.gcode.estimate import DEFAULT_LIMITS, Limits

# Numbers keep the type they were written with, so 1.0 prints "1.0" and 77 prints "77",
# the way the Hyrel reference writes them.
Number = StrictInt | StrictFloat


M = TypeVar("M", bound=BaseModel)


def _camera_command(value: str) -> str:
    """The camera command, when it is a command line: a ValueError (pydantic's error, naming
    the setting) when it is not."""
    try:
        argv = shlex.split(value)
    except ValueError as exc:
        raise ValueError(f"the camera command cannot be split into words ({exc})") from None
    if not argv:
        raise ValueError("the camera command is empty")
    return value


# A camera command line (M791/M790 snapshots), checked as it is read.
CameraCommand = Annotated[str, AfterValidator(_camera_command)]


class _Model(BaseModel):
    # Built on first use: a plain job never validates a machine or a head.
    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class LinkDefaults(_Model):
    baud: int = Field(default=115200, gt=0)
    # reprap: numbered lines, ok and Resend; hyrel: Hyrel's own link (ACK bytes, control bytes)
    protocol: Literal["reprap", "hyrel"] = "reprap"
    flow: Literal["buffered", "unbuffered"] = "buffered"
    # The window; default: the protocol's (reprap: 128 bytes and 8 lines, AVR Marlin's
    # buffer; hyrel: 2048 bytes and 256 lines, the controller's headroom).
    rx_buffer: int | None = Field(default=None, ge=2)
    max_lines: int | None = Field(default=None, ge=1)
    checksum: bool = False  # hyrel: every line with the additive checksum


Axis = Literal["X", "Y", "Z", "E"]
Positive = Annotated[float, Field(gt=0)]


class HeatRates(_Model):
    """Degrees per second each kind of heater gains (for the heat waits)."""

    hotend: Positive = DEFAULT_LIMITS.heat_rates["hotend"]
    bed: Positive = DEFAULT_LIMITS.heat_rates["bed"]
    chamber: Positive = DEFAULT_LIMITS.heat_rates["chamber"]


class MachineLimits(_Model):
    """What a machine's planner runs with, for the print time: ``[NAME.limits]``. What is not
    given is Marlin's default; ``source`` says where the figures come from."""

    source: str = Field(min_length=1)
    max_feedrate: dict[Axis, Positive] = {}  # mm/s (M203 on Marlin)
    max_acceleration: dict[Axis, Positive] = {}  # mm/s² (M201)
    jerk: dict[Axis, Positive] = {}  # mm/s (M205 X Y Z E)
    junction_deviation: float = Field(default=0.0, ge=0)  # mm (M205 J); 0: the classic jerk
    print_acceleration: Positive = DEFAULT_LIMITS.print_acceleration  # mm/s² (M204 P)
    retract_acceleration: Positive = DEFAULT_LIMITS.retract_acceleration  # M204 R
    travel_acceleration: Positive = DEFAULT_LIMITS.travel_acceleration  # M204 T
    rapid: dict[Axis, Positive] = {}  # mm/min: Hyrel's G0 speed per axis (its M203)
    heat_rates: HeatRates = HeatRates()
    tool_change: float = Field(default=0.0, ge=0)  # seconds beyond the moves

    def planner(self) -> Limits:
        """These figures as the estimator's limits."""
        return Limits(
            max_feedrate=_over(DEFAULT_LIMITS.max_feedrate, self.max_feedrate),
            max_acceleration=_over(DEFAULT_LIMITS.max_acceleration, self.max_acceleration),
            jerk=_over(DEFAULT_LIMITS.jerk, self.jerk),
            print_acceleration=self.print_acceleration,
            retract_acceleration=self.retract_acceleration,
            travel_acceleration=self.travel_acceleration,
            source=f"the machine profile ({self.source})",
            junction_deviation=self.junction_deviation,
            rapid={str(axis): value / 60.0 for axis, value in self.rapid.items()},
            heat_rates=self.heat_rates.model_dump(),
            tool_change=self.tool_change,
        )


def _over(base: dict[str, float], given: Mapping[Axis, float]) -> dict[str, float]:
    """``base``'s figures per axis, with ``given``'s in their place."""
    return {**base, **{str(axis): value for axis, value in given.items()}}


class Machine(_Model):
    description: str = ""
    # hyrel: Hyrel's code chart and T addressing apply; marlin: a RepRap-style controller.
    family: Literal["hyrel", "marlin"] = "hyrel"
    yokes: int = Field(ge=1, le=addressing.MAX_YOKES)
    slots_per_yoke: int = Field(ge=1, le=addressing.ADDRESSES_PER_YOKE)
    firmware: addressing.Firmware
    pause_sync: str = "M400"
    safe_stop: list[str] | None = None  # default: the standard footer's safe part
    link: LinkDefaults = LinkDefaults()
    limits: MachineLimits | None = None  # for the print time; default: Marlin's

    def planner_limits(self) -> Limits:
        """The limits its print time is estimated with, when the file gives none."""
        return self.limits.planner() if self.limits is not None else DEFAULT_LIMITS


class Unprime(_Model):
    speed: Number  # pulses per second
    pulses: Number
    time: Number  # ms; negative: before the end of the printing move


class Prime(_Model):
    speed: Number  # pulses per second
    pulses: Number
    time: Number  # ms of dwell at the start of the next printing move


class Flow(_Model):
    multiplier: Number
    pulses_per_ul: Number
    width: Number  # mm
    layer: Number  # mm


class Head(_Model):
    description: str = ""
    max_temp: Number | None = Field(default=None, gt=0)  # °C, where the maker gives it
    unprime: Unprime
    prime: Prime
    flow: Flow
    current_boost: Number = 0


class Offset(_Model):
    x: Number = 0
    y: Number = 0
    z: Number = 0
    a: Number | None = None
    b: Number | None = None


class LoadedHead(_Model):
    """One ``[[heads]]`` entry of a loadout; unprime/prime/flow/current_boost override the head."""

    yoke: int = Field(default=1, ge=1, le=addressing.MAX_YOKES)
    slot: int = Field(ge=1, le=addressing.ADDRESSES_PER_YOKE)
    head: str
    offset: Offset = Offset()
    offset_register: int | None = Field(default=None, ge=0)  # M6 O; default: the T number + 1
    unprime: dict[str, Any] | None = None
    prime: dict[str, Any] | None = None
    flow: dict[str, Any] | None = None
    current_boost: Number | None = None
    # What a farm matches jobs against (hyrel-server --farm): the loaded material and nozzle.
    material: str | None = None
    nozzle: Number | None = Field(default=None, gt=0)  # mm


class LoadoutFile(_Model):
    machine: str
    heads: list[LoadedHead] = []


class PrinterSettings(_Model):
    port: str | None = None
    machine: str | None = None
    loadout: Path | None = None


class HostSettings(_Model):
    history_dir: Path | None = None
    # The print history is pruned (oldest runs first) to this size when a job starts; 0: never.
    history_max_mb: Number = Field(default=500, ge=0)
    allow_shell: bool = False  # M792 SHELL runs a program: off unless asked for
    speech_program: str | None = None  # M792 SAY; default: the first of espeak-ng, espeak, say
    safe_stop: list[str] | None = None  # default: the standard footer's safe part
    camera: CameraCommand | None = None  # M791/M790 snapshots ({path}: the image to write)
    layer_snapshots: bool = False  # a snapshot at every M790 (new layer) too


class UserConfig(_Model):
    printer: PrinterSettings = PrinterSettings()
    host: HostSettings = HostSettings()
    machines: dict[str, dict[str, Any]] = {}
    heads: dict[str, dict[str, Any]] = {}


@dataclass(frozen=True, slots=True)
class ResolvedHead:
    """A head in a position, with its values after the loadout's overrides."""

    yoke: int
    slot: int
    tool: int  # tool-change number: T<tool>
    variable: int  # T value inside M-codes
    register: int  # M6 offset register
    name: str
    head: Head
    offset: Offset
    material: str | None = None  # loaded filament, as the loadout says (farm matching)
    nozzle: float | None = None  # mm


@dataclass(frozen=True, slots=True)
class Loadout:
    path: Path
    machine_name: str
    machine: Machine
    heads: tuple[ResolvedHead, ...]

    @property
    def loaded_tools(self) -> frozenset[int]:
        return frozenset(h.tool for h in self.heads)


@dataclass(frozen=True, slots=True)
class Library:
    machines: Mapping[str, Machine]
    heads: Mapping[str, Head]


def shipped_config_dir() -> Path:
    """The shipped configuration: the repository's ``config/``, which the wheel holds as
    ``repetrel_host/shipped_config/`` (an editable install reads it where it is)."""
    installed = Path(__file__).parent / "shipped_config"
    return installed if installed.is_dir() else Path(__file__).parents[2] / "config"


def user_config_path() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "repetrel-host" / "config.toml"


def load_user_config(path: Path | None) -> UserConfig:
    """``path`` (which must exist), else the per-user file if there is one, else defaults."""
    if path is None:
        path = user_config_path()
        try:
            if not path.exists():
                return UserConfig()
        except OSError as exc:
            raise ConfigError(f"{path}: cannot be read ({exc.strerror})") from None
    return _validate(UserConfig, read_toml(path), path)


class _Shipped(Mapping[str, M]):
    """Shipped entries, validated when first used (a job names one machine, if any);
    the user's own entries are validated at once, so a mistake there is found."""

    def __init__(self, model: type[M], path: Path, user: Mapping[str, M]) -> None:
        self._model = model
        self._path = path
        self._raw = read_toml(path)
        self._done: dict[str, M] = dict(user)

    def __getitem__(self, name: str) -> M:
        if name not in self._done:
            self._done[name] = _validate(self._model, self._raw[name], self._path, name)
        return self._done[name]

    def __iter__(self) -> Iterator[str]:
        return iter({**self._raw, **self._done})

    def __len__(self) -> int:
        return len({**self._raw, **self._done})


def load_library(user: UserConfig) -> Library:
    """The shipped machines and heads, with the user's additions and replacements."""
    shipped = shipped_config_dir()
    user_file = user_config_path()
    machines = {
        n: _validate(Machine, d, user_file, f"machines.{n}") for n, d in user.machines.items()
    }
    heads = {n: _validate(Head, d, user_file, f"heads.{n}") for n, d in user.heads.items()}
    return Library(
        _Shipped(Machine, shipped / "machines.toml", machines),
        _Shipped(Head, shipped / "heads.toml", heads),
    )


def find_loadout(value: Path) -> Path:
    """A loadout path as given, or a bare name found in the user's or the shipped loadouts."""
    if value.exists() or value.suffix or len(value.parts) > 1:
        return value
    folders = (user_config_path().parent / "loadouts", shipped_config_dir() / "loadouts")
    for folder in folders:
        candidate = folder / f"{value}.toml"
        if candidate.exists():
            return candidate
    known = sorted({p.stem for folder in folders if folder.is_dir() for p in folder.glob("*.toml")})
    raise ConfigError(
        f"{value}: no such loadout (known: {', '.join(known)}; or give the path of a TOML file)"
    )


def load_loadout(path: Path, library: Library) -> Loadout:
    """Read a loadout and resolve every head against the machine and the head library."""
    data = _validate(LoadoutFile, read_toml(path), path)
    machine = library.machines.get(data.machine)
    if machine is None:
        known = ", ".join(sorted(library.machines))
        raise ConfigError(f"{path}: machine: unknown machine '{data.machine}' (known: {known})")
    resolved: list[ResolvedHead] = []
    taken: set[tuple[int, int]] = set()
    for number, entry in enumerate(data.heads, start=1):
        where = f"{path}: heads #{number}"
        if entry.yoke > machine.yokes or entry.slot > machine.slots_per_yoke:
            raise ConfigError(
                f"{where}: yoke {entry.yoke} slot {entry.slot} is not on a {data.machine} "
                f"({machine.yokes} yoke(s) of {machine.slots_per_yoke} slots)"
            )
        if (entry.yoke, entry.slot) in taken:
            raise ConfigError(f"{where}: yoke {entry.yoke} slot {entry.slot} is loaded twice")
        taken.add((entry.yoke, entry.slot))
        base = library.heads.get(entry.head)
        if base is None:
            known = ", ".join(sorted(library.heads))
            raise ConfigError(f"{where}: head: unknown head '{entry.head}' (known: {known})")
        head = _override(base, entry, where)
        try:
            variable = addressing.head_variable(machine.firmware, entry.yoke, entry.slot)
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        tool = addressing.tool_number(entry.yoke, entry.slot)
        register = entry.offset_register if entry.offset_register is not None else tool + 1
        resolved.append(
            ResolvedHead(
                entry.yoke,
                entry.slot,
                tool,
                variable,
                register,
                entry.head,
                head,
                entry.offset,
                entry.material,
                entry.nozzle,
            )
        )
    resolved.sort(key=lambda h: h.tool)  # slot order, left to right
    return Loadout(path, data.machine, machine, tuple(resolved))


def read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a TOML file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def _override(base: Head, entry: LoadedHead, where: str) -> Head:
    data = base.model_dump()
    for section in ("unprime", "prime", "flow"):
        changes = getattr(entry, section)
        if changes:
            data[section] = {**data[section], **changes}
    if entry.current_boost is not None:
        data["current_boost"] = entry.current_boost
    try:
        return Head.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{where}: {_describe(exc, Head)}") from None


def _validate(model: type[M], data: object, path: Path, prefix: str = "") -> M:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        where = f"{path}: {prefix}." if prefix else f"{path}: "
        raise ConfigError(where + _describe(exc, model)) from None


def _describe(exc: ValidationError, model: type[BaseModel]) -> str:
    """The first problem as ``field: message``, with the allowed fields for a typo."""
    error = exc.errors()[0]
    loc = [str(part) for part in error["loc"] if not isinstance(part, int)]
    field = ".".join(loc) or "(top level)"
    if error["type"] == "extra_forbidden":
        allowed = ", ".join(_fields_at(model, loc[:-1]))
        return f"{field}: unknown field (allowed: {allowed})"
    if error["type"] == "missing":
        return f"{field}: missing"
    return f"{field}: {error['msg']}"


def _fields_at(model: type[BaseModel], path: list[str]) -> list[str]:
    current: type[BaseModel] = model
    for name in path:
        field = current.model_fields.get(name)
        # The model itself, or the one inside list[...] / dict[...] / ... | None.
        candidates = [field.annotation, *get_args(field.annotation)] if field else []
        inner = [c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)]
        if not inner:
            return []
        current = inner[0]
    return list(current.model_fields)
