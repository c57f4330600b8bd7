"""Push socket clients for ``bench/server.py --socket-clients N``: N clients on each printer
of a hyrel-server, each as a farm manager connects (OctoPrint's passive login with the
key, the raw websocket ``/printers/NAME/sockjs/websocket``, ``auth``, ``throttle`` 1), all
reading every message, in one process (one event loop: the readers' own CPU stays small).

    python bench/socket_clients.py HOST:PORT KEY CLIENTS PRINTER...

Prints ``ready`` once every client has its history; on SIGTERM (or SIGINT) prints what
they received as JSON (messages, currents, events, bytes) and exits.
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import urllib.request
from collections import Counter

from websockets.asyncio.client import connect


def passive_login(address: str, key: str) -> str:
    request = urllib.request.Request(
        f"http://{address}/api/login",
        data=json.dumps({"passive": True}).encode(),
        headers={"X-Api-Key": key, "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=30) as answer:
        user = json.loads(answer.read())
    return f"{user['name']}:{user['session']}"


async def client(
    address: str, printer: str, auth: str, counts: Counter[str], ready: asyncio.Event
) -> None:
    url = f"ws://{address}/printers/{printer}/sockjs/websocket"
    async with connect(url, max_size=None, compression=None) as socket:
        await socket.send(json.dumps({"auth": auth}))
        await socket.send(json.dumps({"throttle": 1}))
        while True:
            # The bytes as they came: no UTF-8 decoding, no JSON (the readers share the
            # server's two cores: their own cost must stay small).
            data = await socket.recv(decode=False)
            counts["messages"] += 1
            counts["bytes"] += len(data)
            kind = data[2 : data.index(b'"', 2)].decode()  # {"current":...
            counts[kind] += 1
            if kind == "history":
                counts["ready"] += 1
                ready.set()


async def main() -> int:
    address, key, per_printer, *printers = sys.argv[1:]
    auth = passive_login(address, key)
    counts: Counter[str] = Counter()
    ready = asyncio.Event()
    tasks = [
        asyncio.create_task(client(address, printer, auth, counts, ready))
        for printer in printers
        for _ in range(int(per_printer))
    ]
    while counts["ready"] < len(tasks):
        ready.clear()
        await ready.wait()
    print("ready", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    await stop.wait()
    gone = sum(task.done() for task in tasks)
    for task in tasks:
        task.cancel()
    print(json.dumps({**counts, "clients": len(tasks), "ended early": gone}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(asyncio.run(main()))
