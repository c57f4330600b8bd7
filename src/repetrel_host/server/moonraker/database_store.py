"""Where Moonraker's database keeps its namespaces: one SQLite file of its own in the data
folder, one row per item written, worked on in one thread of its own.

A row is keyed by its namespace and its key's parts joined by :data:`SEP` (a key cannot hold
it). No row lies below another: writing ``a.b.c`` drops the rows at and below it, splits a
row above it that holds an object into rows of its children (a row above holding anything
else is replaced by an object, as Moonraker replaces it) and adds one row. So a write costs
its own size, and the rows it split (each split once), never its namespace's size.

Every item stays within bounds that fit what Mainsail, Fluidd and KlipperScreen keep
(small settings objects): a refused write is a :class:`ItemRefused` with the status and
sentence the client is told."""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger("repetrel_host.server.moonraker")

SEP = "\x1f"  # joins a key's parts in a row's key (ASCII's unit separator)
_END = "\x20"  # the character after SEP: a row's descendants sort between the two

MB = 1 << 20
VALUE_BYTES = 1 * MB  # one value, as JSON
NAMESPACE_BYTES = 2 * MB  # a namespace's rows, keys and values
NAMESPACES = 100  # Moonraker's own limit
DEPTH = 32  # a key's parts and its value's nesting, together
KEY_BYTES = 1024  # a key, its parts joined
NAME_BYTES = 256  # a namespace's name

_SCHEMA = """
CREATE TABLE IF NOT EXISTS items (
    namespace TEXT NOT NULL,
    key TEXT NOT NULL,        -- the key's parts joined by SEP
    value TEXT NOT NULL,      -- JSON
    size INTEGER NOT NULL,    -- bytes of key and value
    PRIMARY KEY (namespace, key)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS namespaces (
    namespace TEXT PRIMARY KEY,
    items INTEGER NOT NULL,
    size INTEGER NOT NULL
);
"""

T = TypeVar("T")
Row = tuple[list[str], Any]  # a key's parts and its value


class ItemRefused(Exception):
    """A refused call: ``status`` (400, 404) and the sentence the client is told."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


def missing(namespace: str, key: list[str]) -> ItemRefused:
    """Moonraker's 404 for a namespace, or a key in it, that is not there."""
    if not key:
        return ItemRefused(404, f"Namespace {namespace} not found")
    return ItemRefused(404, f"Key '{'.'.join(key)}' in namespace '{namespace}' not found")


def check_key(namespace: str, parts: list[str]) -> None:
    """Refuse a namespace name or a key past its bounds (before anything is read)."""
    if len(namespace.encode()) > NAME_BYTES:
        raise ItemRefused(400, f"Invalid namespace: a name of at most {NAME_BYTES} bytes")
    if len(parts) > DEPTH:
        raise ItemRefused(400, f"Invalid key: {len(parts)} parts, at most {DEPTH}")
    # No control characters: then the rows at and below a key are exactly those between it
    # and it followed by a space (SEP sorts below every character a part may hold).
    if any(char < " " for part in parts for char in part):
        raise ItemRefused(400, "Invalid key: a part holds a control character")
    if len(SEP.join(parts).encode()) > KEY_BYTES:
        raise ItemRefused(400, f"Invalid key: longer than {KEY_BYTES} bytes")


def encode(parts: list[str], value: Any) -> str:
    """``value`` as JSON, refused if it is nested past :data:`DEPTH` with its key's parts or
    bigger than :data:`VALUE_BYTES` (measured before encoding: a huge value is refused
    without the cost of encoding it)."""
    room = DEPTH - len(parts)
    estimate = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            children: Iterable[Any] = item.values()
            estimate += sum(len(name) + 4 for name in item) + 2
        elif isinstance(item, list):
            children = item
            estimate += len(item) + 2
        else:
            estimate += len(item) + 2 if isinstance(item, str) else 8
            continue
        if level + 1 > room:
            raise ItemRefused(400, f"Invalid value: nested deeper than {DEPTH} levels with its key")
        if estimate > VALUE_BYTES:
            break
        stack.extend((child, level + 1) for child in children)
    text = json.dumps(value) if estimate <= VALUE_BYTES else ""
    if not text or len(text) > VALUE_BYTES:
        raise ItemRefused(400, f"Invalid value: larger than {VALUE_BYTES // MB} MB as JSON")
    return text


def split(parts: list[str], value: Any, key: list[str]) -> list[Row]:
    """The rows a row at ``parts`` holding ``value`` becomes when ``key`` (below it) is
    written or deleted: the siblings along the way down, each its own row; nothing at or
    below ``key``. A value on the way that is not an object holds nothing kept."""
    rows: list[Row] = []
    for part in key[len(parts) :]:
        if not isinstance(value, dict):
            break
        rows += [([*parts, name], child) for name, child in value.items() if name != part]
        parts, value = [*parts, part], value.get(part)
    return rows


def assemble(rows: Iterable[tuple[str, str]], skip: int) -> dict[str, Any]:
    """The object the rows (key, JSON) make, their keys' first ``skip`` parts left out."""
    whole: dict[str, Any] = {}
    for key, text in rows:
        parts = key.split(SEP)[skip:]
        place = whole
        for part in parts[:-1]:
            place = place.setdefault(part, {})
        place[parts[-1]] = json.loads(text)
    return whole


def _size(key: str, text: str) -> int:
    return len(key.encode()) + len(text)


class Database:
    """Moonraker's namespaces: each call runs in the database's own thread, one at a time
    (the event loop never waits on SQLite, and the thread's calls need no locks)."""

    def __init__(self, path: Path, legacy: Path | None = None) -> None:
        """Open (or make) the file at ``path``; ``legacy``: the job store of a data folder
        that kept the namespaces in its ``client_data`` table, moved here once."""
        self.path = path
        # Clients' settings: WAL with synchronous=NORMAL survives a kill -9 (only a power
        # cut may lose the last writes), and a write costs no fsync.
        self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        if legacy is not None and legacy.exists():
            self._migrate(legacy)
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="moonraker-database")

    def close(self) -> None:
        self._thread.shutdown(wait=True)
        self._db.close()

    async def _run(self, work: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._thread, work, *args)

    # --- the calls ------------------------------------------------------------------

    async def namespaces(self) -> list[str]:
        """The namespaces that hold something, by name."""
        return await self._run(self._namespaces)

    async def get(self, namespace: str, key: list[str]) -> Any:
        """The item at ``key`` ([]: the whole namespace)."""
        check_key(namespace, key)
        return await self._run(self._get, namespace, key)

    async def post(self, namespace: str, key: list[str], value: Any) -> None:
        """``value`` at ``key`` from now on (its ancestors made objects where they were not)."""
        check_key(namespace, key)
        await self._run(self._post, namespace, key, value)

    async def delete(self, namespace: str, key: list[str]) -> Any:
        """Remove the item at ``key``; its value. An object left empty by it stays (``{}``)
        below the namespace's top level; a namespace left empty is dropped (Moonraker's)."""
        check_key(namespace, key)
        return await self._run(self._delete, namespace, key)

    # --- in the database's thread ------------------------------------------------------

    def _namespaces(self) -> list[str]:
        rows = self._db.execute("SELECT namespace FROM namespaces ORDER BY namespace")
        return [str(row[0]) for row in rows]

    def _row(self, namespace: str, key: str) -> str | None:
        found = self._db.execute(
            "SELECT value FROM items WHERE namespace = ? AND key = ?", (namespace, key)
        ).fetchone()
        return str(found[0]) if found is not None else None

    def _below(self, namespace: str, key: str) -> list[tuple[str, str]]:
        """The rows below ``key`` (every row of the namespace for "")."""
        if not key:
            found = self._db.execute(
                "SELECT key, value FROM items WHERE namespace = ? ORDER BY key", (namespace,)
            )
        else:
            found = self._db.execute(
                "SELECT key, value FROM items WHERE namespace = ? AND key > ? AND key < ?"
                " ORDER BY key",
                (namespace, key + SEP, key + _END),
            )
        return [(str(k), str(v)) for k, v in found]

    def _above(self, namespace: str, parts: list[str]) -> tuple[list[str], Any] | None:
        """The row above ``parts`` (there is at most one), as its parts and value."""
        above = [SEP.join(parts[:end]) for end in range(1, len(parts))]
        if not above:
            return None
        marks = ",".join("?" * len(above))
        found = self._db.execute(
            f"SELECT key, value FROM items WHERE namespace = ? AND key IN ({marks})",
            (namespace, *above),
        ).fetchone()
        return (str(found[0]).split(SEP), json.loads(found[1])) if found is not None else None

    def _get(self, namespace: str, parts: list[str]) -> Any:
        key = SEP.join(parts)
        text = self._row(namespace, key) if parts else None
        if text is not None:
            return json.loads(text)
        below = self._below(namespace, key)
        if below:
            return assemble(below, len(parts))
        above = self._above(namespace, parts)
        if above is not None:
            value = above[1]
            for part in parts[len(above[0]) :]:
                if not isinstance(value, dict) or part not in value:
                    raise missing(namespace, parts)
                value = value[part]
            return value
        raise missing(namespace, parts if self._exists(namespace) else [])

    def _exists(self, namespace: str) -> bool:
        found = self._db.execute("SELECT 1 FROM namespaces WHERE namespace = ?", (namespace,))
        return found.fetchone() is not None

    def _post(self, namespace: str, parts: list[str], value: Any) -> None:
        text = encode(parts, value)
        key = SEP.join(parts)
        above = self._above(namespace, parts)
        added = [(SEP.join(p), json.dumps(v)) for p, v in split(*above, parts)] if above else []
        added.append((key, text))
        removed = self._sizes(namespace, key)
        if above is not None:
            above_key = SEP.join(above[0])
            removed.append((above_key, self._size_of(namespace, above_key)))
        self._change(namespace, added, removed)

    def _delete(self, namespace: str, parts: list[str]) -> Any:
        key = SEP.join(parts)
        removed = self._sizes(namespace, key)
        added: list[tuple[str, str]] = []
        if removed:
            value = self._get(namespace, parts)
        else:
            above = self._above(namespace, parts)
            if above is None:
                raise missing(namespace, parts if self._exists(namespace) else [])
            value = self._get(namespace, parts)  # 404 when it is not in the row above
            added = [(SEP.join(p), json.dumps(v)) for p, v in split(*above, parts)]
            above_key = SEP.join(above[0])
            removed.append((above_key, self._size_of(namespace, above_key)))
        parent = SEP.join(parts[:-1])
        kept_below = any(k.startswith(parent + SEP) for k, _ in added)
        if len(parts) > 2 and not kept_below and not self._siblings(namespace, parent, key):
            added.append((parent, "{}"))  # Moonraker leaves the emptied object
        self._change(namespace, added, removed)
        return value

    def _siblings(self, namespace: str, parent: str, key: str) -> bool:
        """Whether a row below ``parent`` lies outside ``key`` and what is below it."""
        found = self._db.execute(
            "SELECT 1 FROM items WHERE namespace = ? AND key > ? AND key < ?"
            " AND NOT (key >= ? AND key < ?) LIMIT 1",
            (namespace, parent + SEP, parent + _END, key, key + _END),
        )
        return found.fetchone() is not None

    def _sizes(self, namespace: str, key: str) -> list[tuple[str, int]]:
        """The rows at and below ``key``, with their sizes."""
        found = self._db.execute(
            "SELECT key, size FROM items WHERE namespace = ? AND key >= ? AND key < ?",
            (namespace, key, key + _END),
        )
        return [(str(k), int(s)) for k, s in found]

    def _size_of(self, namespace: str, key: str) -> int:
        found = self._db.execute(
            "SELECT size FROM items WHERE namespace = ? AND key = ?", (namespace, key)
        ).fetchone()
        return int(found[0])

    def _change(
        self,
        namespace: str,
        added: list[tuple[str, str]],
        removed: list[tuple[str, int]],
    ) -> None:
        """One transaction: drop the ``removed`` rows (key, size), add the ``added`` rows
        (key, JSON); refused when it would pass a namespace's bounds."""
        kept = self._db.execute(
            "SELECT items, size FROM namespaces WHERE namespace = ?", (namespace,)
        ).fetchone()
        items, size = (int(kept[0]), int(kept[1])) if kept is not None else (0, 0)
        growth = sum(_size(k, v) for k, v in added) - sum(s for _, s in removed)
        if growth > 0 and size + growth > NAMESPACE_BYTES:
            raise ItemRefused(
                400, f"Namespace '{namespace}' would pass {NAMESPACE_BYTES // MB} MB: not stored"
            )
        if kept is None and added and len(self._namespaces()) >= NAMESPACES:
            raise ItemRefused(400, f"Too many namespaces: at most {NAMESPACES}")
        items += len(added) - len(removed)
        self._db.execute("BEGIN IMMEDIATE")
        try:
            self._db.executemany(
                "DELETE FROM items WHERE namespace = ? AND key = ?",
                [(namespace, k) for k, _ in removed],
            )
            self._db.executemany(
                "INSERT INTO items (namespace, key, value, size) VALUES (?, ?, ?, ?)",
                [(namespace, k, v, _size(k, v)) for k, v in added],
            )
            if items > 0:
                self._db.execute(
                    "INSERT INTO namespaces (namespace, items, size) VALUES (?, ?, ?)"
                    " ON CONFLICT (namespace) DO UPDATE SET items = excluded.items,"
                    " size = excluded.size",
                    (namespace, items, size + growth),
                )
            else:
                self._db.execute("DELETE FROM namespaces WHERE namespace = ?", (namespace,))
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    # --- a data folder of an earlier version -------------------------------------------

    def _migrate(self, legacy: Path) -> None:
        """Move the namespaces a data folder kept whole in its job store's ``client_data``
        table (one JSON object each) here, each top-level item a row; an item nested past
        the bounds (it could never be answered) is left out, said in the log. Run again
        after a crash half way, it does the same."""
        old = sqlite3.connect(legacy, isolation_level=None, timeout=30)
        try:
            table = old.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'client_data'"
            ).fetchone()
            if table is None:
                return
            rows = old.execute("SELECT namespace, value FROM client_data").fetchall()
            self._db.execute("BEGIN IMMEDIATE")
            for namespace, whole in rows:
                self._db.execute("DELETE FROM items WHERE namespace = ?", (namespace,))
                self._db.execute("DELETE FROM namespaces WHERE namespace = ?", (namespace,))
                kept = []
                try:
                    items = json.loads(whole).items()
                except RecursionError:
                    log.warning("the database's %s was left out: nested too deep", namespace)
                    items = {}.items()
                for name, value in items:
                    try:
                        check_key(namespace, [name])
                        kept.append((name, encode([name], value)))
                    except (ItemRefused, RecursionError) as exc:
                        log.warning("the database's %s.%s was left out: %s", namespace, name, exc)
                self._db.executemany(
                    "INSERT INTO items (namespace, key, value, size) VALUES (?, ?, ?, ?)",
                    [(namespace, k, v, _size(k, v)) for k, v in kept],
                )
                if kept:
                    self._db.execute(
                        "INSERT INTO namespaces (namespace, items, size) VALUES (?, ?, ?)",
                        (namespace, len(kept), sum(_size(k, v) for k, v in kept)),
                    )
            self._db.execute("COMMIT")
            old.execute("DROP TABLE client_data")
        finally:
            old.close()
