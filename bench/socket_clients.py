"""Push socket clients for ``bench/server.py --socket-clients N``: N clients on each printer
of a hyrel-server, each as a farm manager connects (OctoPrint's passive login with the
key, the raw websocket ``/printers/NAME/sockjs/websocket``, ``auth``, ``throttle`` 1), all
reading every message, in one process.

They share the server's two cores here (on a farm they run elsewhere), so they cost as
little as reading can: an asyncio protocol that takes the frames' headers to count the
messages and skips their bodies, and answers the server's pings (a websocket that does not
is closed): no library's frame parsing, no decoding, no JSON.

    python bench/socket_clients.py HOST:PORT KEY CLIENTS PRINTER...
    python bench/socket_clients.py --moonraker HOST:PORT KEY CLIENTS PRINTER...

Prints ``ready`` once every client has its history; on SIGTERM (or SIGINT) prints what
they received as JSON (messages, bytes, and each kind: connected, history, current, event)
and exits.

``--moonraker``: Moonraker's websocket (``/printers/NAME/websocket`` with the key), each
client subscribed to every object as Mainsail subscribes; the kinds are the notifications'
methods, ``history`` the subscription's answer.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import signal
import sys
import urllib.request
from collections import Counter


def passive_login(address: str, key: str) -> str:
    request = urllib.request.Request(
        f"http://{address}/api/login",
        data=json.dumps({"passive": True}).encode(),
        headers={"X-Api-Key": key, "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=30) as answer:
        user = json.loads(answer.read())
    return f"{user['name']}:{user['session']}"


def client_frame(opcode: int, payload: bytes) -> bytes:
    """A frame as a client sends it: masked."""
    mask = os.urandom(4)
    length = len(payload)
    head = bytes([0x80 | opcode])
    if length < 126:
        head += bytes([0x80 | length])
    else:
        head += bytes([0x80 | 126]) + length.to_bytes(2, "big")
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


# Mainsail subscribes to every object its printer lists (these, on the server's printers).
MOONRAKER_OBJECTS = (
    "webhooks print_stats virtual_sdcard display_status pause_resume idle_timeout toolhead "
    "gcode_move motion_report fan heaters configfile system_stats extruder heater_bed"
).split()


class Reader(asyncio.Protocol):
    def __init__(
        self, host: str, path: str, auth: str, counts: Counter[str], key: str | None = None
    ) -> None:
        header = f"X-Api-Key: {key}\r\n" if key is not None else ""
        self.request = (
            f"GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\n{header}"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}"
            "\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
        self.moonraker = key is not None
        self.auth = auth
        self.counts = counts
        self.buffer = bytearray()
        self.open = False
        self.transport: asyncio.Transport | None = None
        self.ended = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        transport.write(self.request)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.ended.done():
            self.ended.set_result(None)

    def data_received(self, data: bytes) -> None:
        buffer = self.buffer
        buffer += data
        assert self.transport is not None
        if not self.open:
            end = buffer.find(b"\r\n\r\n")
            if end < 0:
                return
            del buffer[: end + 4]
            self.open = True
            if self.moonraker:
                subscribe = "printer.objects.subscribe"
                params = {"objects": dict.fromkeys(MOONRAKER_OBJECTS)}
                messages: list[object] = [
                    {"jsonrpc": "2.0", "method": subscribe, "params": params, "id": 1}
                ]
            else:
                messages = [{"auth": self.auth}, {"throttle": 1}]
            for message in messages:
                self.transport.write(client_frame(1, json.dumps(message).encode()))
        counts, position, size = self.counts, 0, len(buffer)
        while size - position >= 2:
            opcode, length, head = buffer[position] & 0x0F, buffer[position + 1] & 0x7F, 2
            if length == 126:
                if size - position < 4:
                    break
                length, head = int.from_bytes(buffer[position + 2 : position + 4], "big"), 4
            elif length == 127:
                if size - position < 10:
                    break
                length, head = int.from_bytes(buffer[position + 2 : position + 10], "big"), 10
            if size - position < head + length:
                break
            body = position + head
            if opcode == 1:
                if self.moonraker:  # {"jsonrpc": "2.0", "method": "notify_...", or a result
                    start = bytes(buffer[body : body + 80])
                    named = start.find(b'"method": "')
                    kind = "history"
                    if named >= 0:
                        kind = start[named + 11 :].split(b'"', 1)[0].decode()
                else:
                    start = bytes(buffer[body + 2 : body + 20])  # {"current":...
                    kind = start[: start.find(b'"')].decode()
                counts["messages"] += 1
                counts["bytes"] += length
                counts[kind] += 1
            elif opcode == 9:  # a ping: the pong, or the server closes the socket
                self.transport.write(client_frame(10, bytes(buffer[body : body + length])))
            position = body + length
        del buffer[:position]


async def main() -> int:
    arguments = sys.argv[1:]
    moonraker = arguments[0] == "--moonraker"
    address, key, per_printer, *printers = arguments[moonraker:]
    host, port = address.rsplit(":", 1)
    auth = "" if moonraker else passive_login(address, key)
    counts: Counter[str] = Counter()
    loop = asyncio.get_running_loop()
    readers: list[Reader] = []
    for printer in printers:
        for _ in range(int(per_printer)):
            path = f"/printers/{printer}/{'websocket' if moonraker else 'sockjs/websocket'}"
            _, reader = await loop.create_connection(
                lambda path=path: Reader(address, path, auth, counts, key if moonraker else None),
                host,
                int(port),
            )
            readers.append(reader)
    while counts["history"] < len(readers):
        await asyncio.sleep(0.05)
    print("ready", flush=True)
    stop = asyncio.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    await stop.wait()
    gone = sum(reader.ended.done() for reader in readers)
    print(json.dumps({**counts, "clients": len(readers), "ended early": gone}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(asyncio.run(main()))
