"""What each attack on ``hyrel-server`` costs it (issue 49): the server's peak memory and
its worst answer delay while the attack runs, with a printer streaming beside it.

A ``hyrel-server`` process serves one fake printer, ``busy``, on the link ``--protocol``
names, streaming moves of 5 ms each; its settings trust the network 192.168.1.0/24 (as
Moonraker's ``trusted_clients``), and its process has the shipped unit's file limit. A
poller process asks ``GET /v1/printers/busy`` every 10 ms with the key and keeps each
answer's time. Each attack then runs in turn, and for each the script prints how the server
answered it, the server's peak resident memory during it (``VmHWM``, reset before each
attack through ``/proc/PID/clear_refs``), the poller's worst answer meanwhile (the event
loop's delay seen from outside: an answer's own time is about 1 ms), and ``busy``'s lines/s.
At the end: whether each of ``busy``'s moves ran once, in order, up to the cancel.

    .venv/bin/python bench/attacks.py [--protocol reprap] [--scale 1.0] [--only NAME]

``--scale`` shrinks the attacks (0.1: bodies of 100 MB, not 1,000, and a tenth of the
sockets and calls) for a quick look.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import resource
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from websockets.exceptions import InvalidStatus, WebSocketException
from websockets.sync.client import connect

sys.path.insert(0, str(Path(__file__).parent.parent))

from loop_delay import lines
from tests.support.helpers import executed
from tests.support.server import KEY, Server

from repetrel_host.fakes.fake_controller import BuiltInFake

MOVES = 200_000  # 1,000 s at 200 lines/s: longer than every attack together
UNIT = Path(__file__).parent.parent / "contrib" / "hyrel-server.service"
CHUNK = 1 << 20


@dataclass
class Target:
    """Where the attacks go: the server's address and the scale asked for."""

    url: str
    host: str
    port: int
    scale: float

    @property
    def ws(self) -> str:
        return self.url.replace("http://", "ws://")

    def count(self, full: int) -> int:
        return max(1, int(full * self.scale))


def megabytes(target: Target, full: int) -> Iterator[bytes]:
    """A body of ``full`` MB (times the scale), made as it is sent: JSON's opening, then
    spaces, so a server that reads it whole holds it all."""
    yield b'{"passive": true, "pad": "'
    for _ in range(target.count(full)):
        yield b" " * CHUNK
    yield b'"}'


def status_of(send: Callable[[], httpx.Response]) -> str:
    try:
        answer = send()
    except httpx.HTTPError as exc:  # the server closed the connection mid-body
        return f"cut ({type(exc).__name__})"
    return f"{answer.status_code} {answer.text[:70]!r}"


def websocket_status(url: str, **headers: str) -> str:
    try:
        with connect(url, additional_headers=headers, open_timeout=30) as websocket:
            websocket.send(
                json.dumps(
                    {
                        "jsonrpc": "2.0",
                        "method": "printer.gcode.script",
                        "params": {"script": "M104 S222"},
                        "id": 1,
                    }
                )
            )
            return f"opened, M104 answered {json.dumps(answer_of(websocket, 30))[:70]!r}"
    except InvalidStatus as exc:
        return f"refused: {exc.response.status_code}"
    except (WebSocketException, OSError, TimeoutError) as exc:
        return f"failed: {type(exc).__name__}"


# --- the attacks: each answers what the server said -------------------------------------


def nothing(target: Target) -> str:
    """No attack for 10 s: the figures of a quiet server, to read the others against."""
    time.sleep(10)
    return "(no attack)"


def forwarded_for(target: Target) -> str:
    """A spoofed X-Forwarded-For in the trusted network, no key: a one-shot token (the
    way to everything) is given, or refused."""
    return status_of(
        lambda: httpx.get(
            f"{target.url}/access/oneshot_token",
            headers={"X-Forwarded-For": "192.168.1.77"},
            timeout=30,
        )
    )


def answer_of(websocket: Any, timeout: float = 300) -> Any:
    """The next message that answers a call (a batch's list, or one with an id): the
    notifications before it are skipped; "no answer" after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            message = json.loads(websocket.recv(timeout=max(deadline - time.monotonic(), 0)))
        except TimeoutError:
            return "no answer"
        if isinstance(message, list) or "id" in message:
            return message


def cookie_websocket(target: Target) -> str:
    """The page's session cookie on Moonraker's websocket, from a foreign Origin."""
    login = httpx.post(
        f"{target.url}/api/login", json={"passive": True}, headers={"X-Api-Key": KEY}
    )
    cookie = "; ".join(f"{name}={value}" for name, value in login.cookies.items())
    return websocket_status(f"{target.ws}/websocket", Cookie=cookie, Origin="http://evil.example")


def body_to(path: str, full: int = 1000) -> Callable[[Target], str]:
    def attack(target: Target) -> str:
        return status_of(
            lambda: httpx.post(
                f"{target.url}{path}",
                content=megabytes(target, full),
                headers={"Content-Type": "application/json"},
                timeout=600,
            )
        )

    attack.__doc__ = f"A {full} MB JSON body to {path}, no key."
    return attack


def xhr_send(target: Target) -> str:
    """A 400 MB body to SockJS's xhr_send of a session just opened, no key."""
    session = f"{target.url}/sockjs/000/attack{int(time.time())}"
    httpx.post(f"{session}/xhr", timeout=30)
    return status_of(
        lambda: httpx.post(f"{session}/xhr_send", content=megabytes(target, 400), timeout=600)
    )


def slowloris(target: Target) -> str:
    """1,100 requests whose head never ends, each fed a header line every 5 s for 45 s;
    meanwhile a keyed request every second must be answered."""
    sockets: list[socket.socket] = []
    opened = refused = 0
    for _ in range(target.count(1100)):
        try:
            made = socket.create_connection((target.host, target.port), timeout=5)
            made.sendall(b"GET /v1/printers HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            sockets.append(made)
            opened += 1
        except OSError:
            refused += 1
    answered = failed = 0
    closed_by_server = 0
    deadline = time.monotonic() + 45 * max(target.scale, 0.3)
    while time.monotonic() < deadline:
        for made in list(sockets):
            try:
                made.sendall(b"X-a: b\r\n")
            except OSError:
                sockets.remove(made)
                closed_by_server += 1
        for _ in range(5):
            try:
                httpx.get(f"{target.url}/v1/printers", headers={"X-Api-Key": KEY}, timeout=5)
                answered += 1
            except httpx.HTTPError:
                failed += 1
            time.sleep(1)
    for made in sockets:
        made.close()
    return (
        f"{opened} opened ({refused} refused), {closed_by_server} closed by the server; "
        f"keyed requests meanwhile: {answered} answered, {failed} failed"
    )


def rpc(method: str, params: dict[str, Any], ident: int) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "method": method, "params": params, "id": ident}


def keyed_websocket(target: Target) -> Any:
    return connect(f"{target.ws}/websocket", additional_headers={"X-Api-Key": KEY}, max_size=None)


def database_flood(target: Target) -> str:
    """10,000 ``server.database.post_item`` (1.9 MB in all) in batches of the largest size
    the server takes, over the websocket."""
    calls = [
        rpc(
            "server.database.post_item",
            {"namespace": "flood", "key": f"item{i}", "value": "v" * 150},
            i,
        )
        for i in range(target.count(10_000))
    ]
    errors = answers = 0
    with keyed_websocket(target) as websocket:
        for start in range(0, len(calls), 100):
            websocket.send(json.dumps(calls[start : start + 100]))
            answered = answer_of(websocket)
            for answer in answered if isinstance(answered, list) else [answered]:
                answers += 1
                errors += "error" in answer
    return f"{answers} answers, {errors} errors"


def big_value(target: Target) -> str:
    """A 200 MB value to ``server.database.post_item`` over HTTP."""

    def body() -> Iterator[bytes]:
        yield b'{"namespace": "big", "key": "k", "value": "'
        for _ in range(target.count(200)):
            yield b"v" * CHUNK
        yield b'"}'

    return status_of(
        lambda: httpx.post(
            f"{target.url}/server/database/item",
            content=body(),
            headers={"X-Api-Key": KEY, "Content-Type": "application/json"},
            timeout=600,
        )
    )


def gcode_store_batch(target: Target) -> str:
    """A batch of 10,000 ``server.gcode_store`` calls over the websocket, its store full
    (1,000 commands sent first, 100 a batch); then a batch of 100 of them."""
    batch = [rpc("server.gcode_store", {}, i) for i in range(target.count(10_000))]
    said = []
    with keyed_websocket(target) as websocket:
        for _ in range(10):
            script = [rpc("printer.gcode.script", {"script": "M105"}, i) for i in range(100)]
            websocket.send(json.dumps(script))
            answer_of(websocket)
        for calls in (batch, batch[:100]):
            websocket.send(json.dumps(calls))
            answer = json.dumps(answer_of(websocket))
            said.append(f"{len(calls)} calls: {len(answer) / 1e6:.1f} MB {answer[-60:]!r}")
    return "; ".join(said)


def deep_json(target: Target) -> str:
    """100,000-deep JSON over HTTP, with the key, and over the websocket."""
    deep = "[" * 100_000 + "]" * 100_000
    over_http = status_of(
        lambda: httpx.post(
            f"{target.url}/server/jsonrpc",
            content=deep,
            headers={"X-Api-Key": KEY, "Content-Type": "application/json"},
            timeout=60,
        )
    )
    with keyed_websocket(target) as websocket:
        websocket.send(deep)
        over_socket = json.dumps(answer_of(websocket, 10))[:70]
    return f"HTTP {over_http}; websocket {over_socket!r}"


ATTACKS: dict[str, Callable[[Target], str]] = {
    "none": nothing,
    "forwarded-for": forwarded_for,
    "cookie-websocket": cookie_websocket,
    "login-body": body_to("/api/login"),
    "appkeys-body": body_to("/plugin/appkeys/request"),
    "xhr-send-body": xhr_send,
    "slowloris": slowloris,
    "database-flood": database_flood,
    "database-big-value": big_value,
    "gcode-store-batch": gcode_store_batch,
    "deep-json": deep_json,
}


# --- measuring ----------------------------------------------------------------------------


def poll(url: str, stop: Any, results: Any) -> None:
    """``GET /v1/printers/busy`` every 10 ms until ``stop``; sends back (when, seconds) each."""
    answers = []
    with httpx.Client(base_url=url, headers={"X-Api-Key": KEY}, timeout=120) as client:
        while not stop.is_set():
            at = time.monotonic()
            started = time.perf_counter()
            with contextlib.suppress(httpx.HTTPError):  # a refused poll counts too
                client.get("/v1/printers/busy").raise_for_status()
            answers.append((at, time.perf_counter() - started))
            if len(answers) == 1:
                results.send("polling")
            time.sleep(0.01)
    results.send(answers)


def peak_memory(pid: int) -> float:
    """The process's peak resident memory since its last reset, in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return 0.0


def reset_peak(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def unit_file_limit() -> int:
    """The shipped unit's ``LimitNOFILE``; systemd's default (1,024) where it sets none."""
    for line in UNIT.read_text().splitlines():
        if line.startswith("LimitNOFILE="):
            return int(line.split("=")[1].split(":")[-1])
    return 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--protocol", choices=("reprap", "hyrel"), default="hyrel")
    parser.add_argument("--scale", type=float, default=1.0, help="shrink the attacks")
    parser.add_argument("--only", action="append", choices=sorted(ATTACKS), help="repeatable")
    args = parser.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 8192)), hard))
    chosen = args.only or list(ATTACKS)
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        moves = [f"G1 X{i % 200} Y{i // 200 % 200} F3000" for i in range(MOVES)]
        fake_args = ["--move-time", "0.005", "--protocol", args.protocol]
        with BuiltInFake(folder / "busy.log", fake_args) as busy:
            config = folder / "server.toml"
            config.write_text(
                'moonraker_trusted_clients = ["192.168.1.0/24"]\n'
                f'[printers.busy]\nport = "{busy.port}"\nprotocol = "{args.protocol}"\n'
            )
            server = Server(folder / "data", {}, "--api-key", KEY, "--config", str(config))
            server.start()
            assert server.process is not None
            pid = server.process.pid
            # The shipped unit's file limit, not this process's (raised for its sockets).
            limit = unit_file_limit()
            resource.prlimit(pid, resource.RLIMIT_NOFILE, (limit, limit))
            rows: list[tuple[str, str, float, float, float, str]] = []
            try:
                with server.client() as client:
                    job = client.post(
                        "/v1/printers/busy/jobs",
                        files={"file": ("moves.gcode", "\n".join(moves) + "\n")},
                    ).json()["id"]
                    time.sleep(3)
                    spawn = multiprocessing.get_context("spawn")
                    stop = spawn.Event()
                    receiving, sending = spawn.Pipe(duplex=False)
                    poller = spawn.Process(
                        target=poll, args=(server.url, stop, sending), daemon=True
                    )
                    poller.start()
                    assert receiving.recv() == "polling"
                    target = Target(server.url, "127.0.0.1", server.port, args.scale)
                    spans = []
                    for name in chosen:
                        reset_peak(pid)
                        first, begun = lines(client, job), time.monotonic()
                        try:
                            said = ATTACKS[name](target)
                        except Exception as exc:  # the attack's client gave up: say how
                            said = f"{type(exc).__name__}: {exc}"[:120]
                        ended = time.monotonic()
                        rate = (lines(client, job) - first) / (ended - begun)
                        spans.append((name, said, begun, ended, rate, peak_memory(pid)))
                        time.sleep(1)
                    stop.set()
                    answers: list[tuple[float, float]] = receiving.recv()
                    poller.join()
                    printing = client.get(f"/v1/jobs/{job}").json()["state"] == "printing"
                    with contextlib.suppress(httpx.HTTPError):
                        client.delete(f"/v1/jobs/{job}")
                        while client.get(f"/v1/jobs/{job}").json()["state"] == "printing":
                            time.sleep(0.5)
                    for name, said, begun, ended, rate, peak in spans:
                        times = sorted(t for at, t in answers if begun <= at < ended) or [0.0]
                        median, worst = times[len(times) // 2], times[-1]
                        shown = f"{rate:.0f}" if ended - begun >= 2 else "-"  # too short to tell
                        rows.append((name, said, peak, median * 1000, worst * 1000, shown))
            finally:
                server.stop()
            ran = [line for line in executed(busy.log_path) if line.endswith(" F3000")]
            once = ran == moves[: len(ran)]
    print(f"link: {args.protocol}, scale {args.scale}, server file limit {unit_file_limit()}")
    print(
        "| attack | the server's answer | peak MB | answers: median ms | worst ms | busy lines/s |"
    )
    print("|---|---|---|---|---|---|")
    for name, said, peak, median_ms, worst_ms, rate in rows:
        print(f"| {name} | {said} | {peak:.0f} | {median_ms:.1f} | {worst_ms:.0f} | {rate} |")
    print(f"the job beside still printing at the end: {printing}; each move once, in order: {once}")


if __name__ == "__main__":
    main()
