"""Moonraker's ``server.*`` and ``machine.*`` methods about the server itself: its info and
configuration, the websocket's identity, the temperature and G-code stores, the machine's
system info and process statistics, and the access methods a client asks on load."""

from __future__ import annotations

import os
import platform
import socket
import sys
from typing import Any

import repetrel_host as rh
from repetrel_host.server.moonraker.face import GCODE_STORE
from repetrel_host.server.moonraker.host import interfaces, meminfo, uptime
from repetrel_host.server.moonraker.objects import heater_names, klippy_state, reading
from repetrel_host.server.moonraker.rpc import Call, RpcError, method

MOONRAKER_VERSION = "0.11.0"  # the release whose API this face follows
API_VERSION = (1, 5, 0)
# The components a client may use (Mainsail and Fluidd ask for a component's methods only
# when it is listed): only those this face implements.
COMPONENTS = [
    "database",
    "file_manager",
    "klippy_apis",
    "machine",
    "data_store",
    "proc_stats",
    "job_state",
    "job_queue",
    "history",
    "webcam",
    "authorization",
    "update_manager",
    "announcements",
]
TEMPERATURE_STORE = 1200  # samples of each heater, a second apart


@method("/server/info")
async def server_info(call: Call) -> dict[str, Any]:
    state = klippy_state(call.service)
    return {
        "klippy_connected": state != "disconnected",
        "klippy_state": state,
        "components": COMPONENTS,
        "failed_components": [],
        "registered_directories": ["gcodes"],
        "warnings": [],
        "websocket_count": len(call.face.connections),
        "moonraker_version": MOONRAKER_VERSION,
        "missing_klippy_requirements": [],
        "api_version": list(API_VERSION),
        "api_version_string": ".".join(map(str, API_VERSION)),
    }


@method("/server/config")
async def server_config(call: Call) -> dict[str, Any]:
    config = {
        "server": {"host": "", "port": 0, "klippy_uds_address": ""},
        "data_store": {
            "temperature_store_size": TEMPERATURE_STORE,
            "gcode_store_size": GCODE_STORE,
        },
        "file_manager": {"enable_object_processing": False},
        "history": {},
        "job_queue": {"automatic_transition": call.service.automatic_transition},
        "authorization": {"trusted_clients": []},
    }
    return {"config": config, "orig": config, "files": []}


@method("/server/connection/identify", "POST", http=False)
async def identify(call: Call) -> dict[str, int]:
    connection = call.connection
    if connection is None:
        raise RpcError(400, "the websocket's only: it names the websocket's client")
    connection.client = {key: call.get(key) for key in ("client_name", "version", "type", "url")}
    # Moonraker's way to sign a websocket in after it opened (websockets.py): a key (or a
    # login token, which this server makes none of) is its user from now on; a wrong one
    # leaves it nothing, trusted network or not, until an identify with a right one.
    key = call.get("access_token") or call.get("api_key")
    if key is not None:
        user = call.server.access.user_for_key(str(key))
        connection.refused = user is None
        if user is None:
            raise RpcError(401, "Invalid API Key")
        connection.user = user
    return {"connection_id": connection.id}


@method("/server/websocket/id", http=False)
async def websocket_id(call: Call) -> dict[str, int]:
    if call.connection is None:
        raise RpcError(400, "the websocket's only: it names the websocket's client")
    return {"websocket_id": call.connection.id}


@method("/server/temperature_store")
async def temperature_store(call: Call) -> dict[str, Any]:
    """Each heater's last 1,200 seconds: temperatures, targets and powers, oldest first."""
    service = call.service
    names = heater_names(service)
    store: dict[str, dict[str, list[float]]] = {
        name: {"temperatures": [], "targets": [], "powers": []} for name in names
    }
    for _, readings in list(service.temperature_history)[-TEMPERATURE_STORE:]:
        for name, sensor in names.items():
            found = reading(readings, sensor)
            if found is None:
                continue
            actual, target = found
            store[name]["temperatures"].append(round(actual, 2))
            store[name]["targets"].append(float(target or 0.0))
            store[name]["powers"].append(0.0)
    return store


@method("/server/gcode_store")
async def gcode_store(call: Call) -> dict[str, Any]:
    count = call.integer("count", GCODE_STORE)
    kept = list(call.face.gcode_store[call.service.name])
    return {"gcode_store": kept[-count:] if count > 0 else []}


@method("/machine/system_info")
async def system_info(call: Call) -> dict[str, Any]:
    return {
        "system_info": {
            "python": {"version": list(sys.version_info[:5]), "version_string": sys.version},
            "cpu_info": {
                "cpu_count": os.cpu_count() or 1,
                "bits": platform.architecture()[0],
                "processor": platform.machine(),
                "cpu_desc": "",
                "serial_number": "",
                "hardware_desc": "",
                "model": "",
                "total_memory": meminfo("MemTotal"),
                "memory_units": "kB",
            },
            "sd_info": {},
            "distribution": {
                "name": platform.system(),
                "id": platform.system().lower(),
                "version": platform.release(),
                "version_parts": {"major": "", "minor": "", "build_number": ""},
                "like": "",
                "codename": "",
                "release_info": {},
                "kernel_version": platform.release(),
            },
            "available_services": [],
            "instance_ids": {"moonraker": "repetrel-host", "klipper": call.service.name},
            "service_state": {},
            "virtualization": {"virt_type": "none", "virt_identifier": "none"},
            "network": interfaces(),
            "canbus": {},
            "provider": "none",
            "hostname": socket.gethostname(),
            "software": f"repetrel-host {rh.__version__}",
        }
    }


@method("/machine/proc_stats")
async def machine_proc_stats(call: Call) -> dict[str, Any]:
    now = call.face.proc_stats()
    return {
        "moonraker_stats": [now["moonraker_stats"]],
        "throttled_state": None,
        "cpu_temp": None,
        "network": now["network"],
        "system_cpu_usage": now["system_cpu_usage"],
        "system_memory": now["system_memory"],
        "system_uptime": uptime(),
        "websocket_connections": len(call.face.connections),
    }


@method("/server/webcams/list")
async def webcams(call: Call) -> dict[str, Any]:
    """The printer's camera, where it has one: its latest snapshot (no stream)."""
    service = call.service
    if service.camera is None:
        return {"webcams": []}
    snapshot = f"/v1/printers/{service.name}/snapshots/latest"
    return {
        "webcams": [
            {
                "name": service.name,
                "location": "printer",
                "service": "mjpegstreamer-adaptive",
                "enabled": True,
                "icon": "mdiWebcam",
                "target_fps": 1,
                "target_fps_idle": 1,
                "stream_url": "",
                "snapshot_url": snapshot,
                "flip_horizontal": False,
                "flip_vertical": False,
                "rotation": 0,
                "aspect_ratio": "4:3",
                "extra_data": {},
                "source": "config",
                "uid": f"repetrel-{service.name}",
            }
        ]
    }


@method("/machine/update/status")
@method("/machine/update/refresh", "POST")
async def update_status(call: Call) -> dict[str, Any]:
    """Nothing to update from here: the server is updated with pip, not by a client."""
    return {
        "busy": False,
        "github_rate_limit": None,
        "github_requests_remaining": None,
        "github_limit_reset_time": None,
        "version_info": {},
    }


@method("/server/announcements/list")
async def announcements(call: Call) -> dict[str, Any]:
    return {"entries": [], "feeds": []}


@method("/access/oneshot_token")
async def oneshot_token(call: Call) -> str:
    return call.face.oneshot(call.user)


@method("/access/user", "GET", name="access.get_user")
async def get_user(call: Call) -> dict[str, Any]:
    """The key's user; a trusted network's caller is Moonraker's trusted user."""
    name = call.user if call.user is not None else "_TRUSTED_USER_"
    return {"username": name, "source": "moonraker", "created_on": call.face.started}


@method("/access/info")
async def access_info(call: Call) -> dict[str, Any]:
    return {
        "default_source": "moonraker",
        "available_sources": ["moonraker"],
        "login_required": False,
        "trusted": call.user is None,  # it came in by its network, not a key
    }
