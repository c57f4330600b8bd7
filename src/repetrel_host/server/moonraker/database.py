"""Moonraker's database (``server.database.*``): namespaces of JSON where Mainsail, Fluidd
and KlipperScreen keep their settings, kept in the data folder (they outlive a restart;
``database_store`` keeps them, within its bounds). One set of namespaces for the server,
as one Moonraker instance has one; a key may name a nested item with dots
(``uiSettings.general``) or be a list of its parts."""

from __future__ import annotations

from collections.abc import Awaitable
from typing import Any, TypeVar

from repetrel_host.server.moonraker.database_store import ItemRefused
from repetrel_host.server.moonraker.rpc import Call, RpcError, method

T = TypeVar("T")


def _key(call: Call, required: bool) -> list[str]:
    """The item's key as its parts: ``a.b`` or ``["a", "b"]``; [] for the whole namespace."""
    key = call.required("key") if required else call.get("key")
    if key is None or key == "":
        return []
    parts = key if isinstance(key, list) else str(key).split(".")
    if not all(isinstance(part, str) and part for part in parts):
        shown = repr(key) if len(parts) <= 32 else f"a key of {len(parts)} parts"
        raise RpcError(400, f"Invalid key: {shown}")
    return list(parts)


def _namespace(call: Call) -> str:
    namespace = call.string("namespace")
    if not namespace:
        raise RpcError(400, "Invalid namespace: an empty name")
    return namespace


async def _kept(work: Awaitable[T]) -> T:
    """The database's answer; its refusals as Moonraker's errors."""
    try:
        return await work
    except ItemRefused as exc:
        raise RpcError(exc.status, exc.message) from None


@method("/server/database/list")
async def database_list(call: Call) -> dict[str, Any]:
    return {"namespaces": await call.face.database.namespaces(), "backups": []}


@method("/server/database/item", "GET", name="server.database.get_item")
async def get_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=False)
    value = await _kept(call.face.database.get(namespace, key))
    return {"namespace": namespace, "key": call.get("key"), "value": value}


@method("/server/database/item", "POST", name="server.database.post_item")
async def post_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=True)
    value = call.required("value", null=True)
    await _kept(call.face.database.post(namespace, key, value))
    return {"namespace": namespace, "key": call.get("key"), "value": value}


@method("/server/database/item", "DELETE", name="server.database.delete_item")
async def delete_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=True)
    value = await _kept(call.face.database.delete(namespace, key))
    return {"namespace": namespace, "key": call.get("key"), "value": value}
