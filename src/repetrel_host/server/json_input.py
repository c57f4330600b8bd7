"""JSON a client sent, read the same way on every face: nesting past :data:`MAX_DEPTH`
levels is refused with one sentence (:class:`JsonTooDeep`), and so is what Python's own
parser cannot nest (a 100,000-deep list raised RecursionError: a 500 over HTTP, a
websocket request that died without an answer). No client sends more than a few levels;
a value nested hundreds deep could be stored and then never be written out again."""

from __future__ import annotations

import json
from typing import Any

MAX_DEPTH = 64
TOO_DEEP = f"the JSON is nested too deep (more than {MAX_DEPTH} levels)"


class JsonTooDeep(Exception):
    """JSON nested past :data:`MAX_DEPTH`; not a ValueError, so that the faces' "not
    JSON" answers do not swallow it: each says :data:`TOO_DEEP` in its own shape."""

    def __init__(self) -> None:
        super().__init__(TOO_DEEP)


def parse_json(text: str | bytes) -> Any:
    """``text`` parsed; ValueError when it is not JSON, :class:`JsonTooDeep` when it nests
    too deep. Refusing a 100,000-deep body costs milliseconds: the parser stops at its
    recursion limit."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise JsonTooDeep from None
    # Cheap first: fewer brackets than the bound cannot nest past it.
    if isinstance(text, bytes):
        opened = text.count(b"[") + text.count(b"{")
    else:
        opened = text.count("[") + text.count("{")
    if opened > MAX_DEPTH and _deeper_than(value, MAX_DEPTH):
        raise JsonTooDeep
    return value


def _deeper_than(value: Any, most: int) -> bool:
    """Whether ``value`` nests lists and objects more than ``most`` levels (a walk of its
    containers, without recursion)."""
    if not isinstance(value, (dict, list)):
        return False
    level: list[Any] = [value]
    for _ in range(most):
        level = [
            child
            for container in level
            for child in (container.values() if isinstance(container, dict) else container)
            if isinstance(child, (dict, list))
        ]
        if not level:
            return False
    return True
