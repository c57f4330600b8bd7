"""Moonraker's database (``server.database.*``): namespaces of JSON where Mainsail, Fluidd
and KlipperScreen keep their settings, kept in the server's store (they outlive a restart).
One set of namespaces for the server, as one Moonraker instance has one; a key may name a
nested item with dots (``uiSettings.general``)."""

from __future__ import annotations

from typing import Any

from repetrel_host.server.moonraker.rpc import Call, RpcError, method


def _key(call: Call, required: bool) -> list[str]:
    """The item's key as its parts: ``a.b`` or ``["a", "b"]``; [] for the whole namespace."""
    key = call.required("key") if required else call.get("key")
    if key is None or key == "":
        return []
    parts = key if isinstance(key, list) else str(key).split(".")
    if not all(isinstance(part, str) and part for part in parts):
        raise RpcError(400, f"Invalid key: {key!r}")
    return list(parts)


def _namespace(call: Call) -> str:
    namespace = call.string("namespace")
    if not namespace:
        raise RpcError(400, "Invalid namespace: an empty name")
    return namespace


def _missing(namespace: str, key: list[str]) -> RpcError:
    if not key:
        return RpcError(404, f"Namespace {namespace} not found")
    return RpcError(404, f"Key '{'.'.join(key)}' in namespace '{namespace}' not found")


@method("/server/database/list")
async def database_list(call: Call) -> dict[str, Any]:
    return {"namespaces": call.server.store.client_namespaces(), "backups": []}


@method("/server/database/item", "GET", name="server.database.get_item")
async def get_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=False)
    value: Any = call.server.store.client_data(namespace)
    if value is None:
        raise _missing(namespace, [])
    for part in key:
        if not isinstance(value, dict) or part not in value:
            raise _missing(namespace, key)
        value = value[part]
    return {"namespace": namespace, "key": call.get("key"), "value": value}


@method("/server/database/item", "POST", name="server.database.post_item")
async def post_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=True)
    value = call.required("value", null=True)
    data = call.server.store.client_data(namespace) or {}
    place = data
    for part in key[:-1]:
        inner = place.get(part)
        if not isinstance(inner, dict):
            inner = place[part] = {}
        place = inner
    place[key[-1]] = value
    call.server.store.keep_client_data(namespace, data)
    return {"namespace": namespace, "key": call.get("key"), "value": value}


@method("/server/database/item", "DELETE", name="server.database.delete_item")
async def delete_item(call: Call) -> dict[str, Any]:
    namespace, key = _namespace(call), _key(call, required=True)
    data = call.server.store.client_data(namespace)
    if data is None:
        raise _missing(namespace, [])
    place: Any = data
    for part in key[:-1]:
        place = place.get(part) if isinstance(place, dict) else None
    if not isinstance(place, dict) or key[-1] not in place:
        raise _missing(namespace, key)
    value = place.pop(key[-1])
    call.server.store.keep_client_data(namespace, data)
    return {"namespace": namespace, "key": call.get("key"), "value": value}
