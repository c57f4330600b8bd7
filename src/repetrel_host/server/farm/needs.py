"""What a farm job needs and what a printer has, as JSON documents where "has" contains
"needs" (PostgreSQL's ``jsonb @>``: the claim is one indexed condition, and
:func:`missing` says the same in Python, in words).

A printer's capabilities::

    {"names": ["left", "bench-a/left"], "machine": "hydra-16a", "protocol": "reprap",
     "tags": ["abs"], "materials": ["PLA"], "heads": ["MK1-250"], "nozzles": [0.5],
     "tools": {"T1": {"slot": 2, "head": "MK1-250", "material": "PLA", "nozzle": 0.5}}}

A job's needs hold any part of that: ``{"materials": ["PLA"]}`` (some tool has PLA),
``{"tools": {"T1": {"material": "PLA"}}}`` (T1 has), ``{"names": ["left"]}``.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

Document = dict[str, Any]

# A requirement's key: what it asks of the printer (plain) or of one tool (T1.material).
_PLAIN = {
    "machine": "machine",
    "protocol": "protocol",
    "printer": "names",
    "tag": "tags",
    "material": "materials",
    "head": "heads",
    "nozzle": "nozzles",
}
_LISTS = ("names", "tags", "materials", "heads", "nozzles")
_TOOL = re.compile(r"T(\d+)\.(material|head|nozzle)")
KEYS = (*_PLAIN, "T<n>.material", "T<n>.head", "T<n>.nozzle")


class BadRequirement(ValueError):
    """A requirement that cannot be read; its message is one sentence."""


def _value(key: str, text: str) -> str | float:
    text = text.strip()
    if not text:
        raise BadRequirement(f"{key}=: give a value")
    if key.endswith("nozzle"):
        try:
            size = float(text.removesuffix("mm"))
        except ValueError:
            raise BadRequirement(f"{key}={text}: a nozzle is a size in mm (0.5)") from None
        if size <= 0:
            raise BadRequirement(f"{key}={text}: a nozzle is a size in mm (0.5)")
        return size
    if key.endswith("material"):
        return text.upper()  # PLA, pla and Pla are one material
    if key == "tag":
        return text.lower()
    return text


def parse(requirements: Iterable[str]) -> Document:
    """``["material=PLA", "T1.head=MK1-250", "tag=abs"]`` as a job's needs."""
    needs: Document = {}
    for requirement in requirements:
        key, sep, text = requirement.partition("=")
        key = key.strip()
        if not sep:
            raise BadRequirement(f"'{requirement}': give KEY=VALUE (keys: {', '.join(KEYS)})")
        tool = _TOOL.fullmatch(key)
        if tool is not None:
            tools = needs.setdefault("tools", {})
            tools.setdefault(f"T{tool[1]}", {})[tool[2]] = _value(key, text)
        elif key in _PLAIN:
            field = _PLAIN[key]
            value = _value(key, text)
            if field in _LISTS:
                listed = needs.setdefault(field, [])
                if value not in listed:
                    listed.append(value)
            elif field in needs and needs[field] != value:
                raise BadRequirement(f"{key} is asked for twice ({needs[field]}, {value})")
            else:
                needs[field] = value
        else:
            known = ", ".join(KEYS)
            raise BadRequirement(f"'{key}' is not something a printer has (keys: {known})")
    return needs


def capabilities(
    name: str,
    node: str,
    machine: str | None,
    protocol: str,
    heads: Iterable[Mapping[str, Any]],
    tags: Iterable[str] = (),
) -> Document:
    """A printer's capabilities; ``heads``: each loaded head's ``tool``, ``slot``,
    ``head``, and ``material`` and ``nozzle`` where the loadout gives them."""
    tools: Document = {}
    materials: list[str] = []
    types: list[str] = []
    nozzles: list[float] = []
    for head in heads:
        tool: Document = {"slot": head["slot"], "head": head["head"]}
        types.append(head["head"])
        if head.get("material"):
            tool["material"] = str(head["material"]).upper()
            materials.append(tool["material"])
        if head.get("nozzle"):
            tool["nozzle"] = float(head["nozzle"])
            nozzles.append(tool["nozzle"])
        tools[f"T{head['tool']}"] = tool
    found: Document = {
        "names": [name, f"{node}/{name}"],
        "protocol": protocol,
        "tags": sorted({tag.lower() for tag in tags}),
        "materials": sorted(set(materials)),
        "heads": sorted(set(types)),
        "nozzles": sorted(set(nozzles)),
        "tools": tools,
    }
    if machine is not None:
        found["machine"] = machine
    return found


def missing(has: Document, needs: Document) -> list[str]:
    """What ``has`` lacks of ``needs``, in words (empty: the printer can take the job).
    The same test as PostgreSQL's ``has @> needs``."""
    lacks: list[str] = []
    for field, wanted in needs.items():
        if field == "tools":
            for tool, parts in wanted.items():
                loaded = has.get("tools", {}).get(tool)
                if loaded is None:
                    lacks.append(f"no head on {tool}")
                    continue
                for part, value in parts.items():
                    if loaded.get(part) != value:
                        there = loaded.get(part)
                        shown = f"{there}" if there is not None else "none given"
                        lacks.append(f"{tool} has {part} {shown}, not {value}")
        elif field in _LISTS:
            for value in wanted:
                if value not in has.get(field, []):
                    what = {"names": "is not printer", "nozzles": "no nozzle of"}.get(
                        field, f"no {field[:-1]}"
                    )
                    lacks.append(f"{what} {value}")
        elif has.get(field) != wanted:
            lacks.append(f"{field} is {has.get(field) or 'not given'}, not {wanted}")
    return lacks


def describe(needs: Document) -> str:
    """The needs as the requirements that make them (``material=PLA, T1.head=MK1-250``)."""
    words: list[str] = []
    plain = {field: key for key, field in _PLAIN.items()}
    for field, wanted in needs.items():
        if field == "tools":
            for tool, parts in wanted.items():
                words += [f"{tool}.{part}={value}" for part, value in parts.items()]
        elif isinstance(wanted, list):
            words += [f"{plain[field]}={value}" for value in wanted]
        else:
            words.append(f"{plain[field]}={wanted}")
    return ", ".join(words) or "any printer"
